"""The error an input that cannot become a shape raises: its own module, so that every reader of inputs (the
shape type, textures) can raise it without importing the others."""

from __future__ import annotations


class ShapeError(ValueError):
    """Input that cannot become a shape.  ``code`` is a stable machine-readable reason."""

    def __init__(self, code: str, message: str):
        super().__init__(message)
        self.code = code
        self.message = message
