"""The base-colour texture of a textured glTF input, read with its mesh (``load_shape(texture=True)``) and kept
with the shape (``Shape.texture``) for ``fastmesh.export.bake``."""

from __future__ import annotations

import io
from dataclasses import dataclass

import numpy as np

from .errors import ShapeError

MAX_SOURCE_SIDE = 2048  # an input texture is read at most this many texels a side (a baked one has 1024)
# Pixels of the largest input texture read for ``bake`` (8K a side): decoded whole once (4 bytes a pixel, 256 MiB at
# the limit) before it is scaled down, which a parse's capped process holds beside its libraries.
MAX_TEXTURE_SIDE = 8192
MAX_TEXTURE_PIXELS = MAX_TEXTURE_SIDE * MAX_TEXTURE_SIDE


@dataclass
class SurfaceTexture:
    """The base-colour textures of a mesh input.

    Attributes
    ----------
    uv : (N, 2) float64
        UV coordinates of the input's vertices (OBJ's convention: v up); NaN where a vertex has none.
    image_of : (N,) int64
        Which of ``images`` the vertex's triangles are textured with; -1 for none.
    images : list of (H, W, 4) uint8
        RGBA images, the first row the top.
    factors : (K, 4) float64
        Each image's material base colour factor (RGBA, 0..1).
    """

    uv: np.ndarray
    image_of: np.ndarray
    images: list
    factors: np.ndarray

    def to_arrays(self) -> dict[str, np.ndarray]:
        """Arrays to store in an npz (the images as PNG bytes)."""
        from PIL import Image

        out = {"tex_uv": self.uv.astype(np.float32), "tex_image_of": self.image_of.astype(np.int32),
               "tex_factors": self.factors}
        for k, img in enumerate(self.images):
            buf = io.BytesIO()
            Image.fromarray(img, "RGBA").save(buf, format="PNG")
            out[f"tex_png_{k}"] = np.frombuffer(buf.getvalue(), dtype=np.uint8)
        return out

    @classmethod
    def from_arrays(cls, z) -> SurfaceTexture | None:
        """The texture :meth:`to_arrays` stored in the npz ``z`` (None when it holds none)."""
        if "tex_uv" not in z:
            return None
        factors = np.asarray(z["tex_factors"], dtype=np.float64).reshape(-1, 4)
        images = [_rgba(np.asarray(z[f"tex_png_{k}"]).tobytes()) for k in range(len(factors))]
        return cls(uv=z["tex_uv"].astype(np.float64), image_of=z["tex_image_of"].astype(np.int64), images=images,
                   factors=factors)


def _rgba(data: bytes) -> np.ndarray:
    from PIL import Image

    with Image.open(io.BytesIO(data)) as img:
        return np.asarray(img.convert("RGBA"))


def _image_of_material(material) -> tuple[object | None, np.ndarray]:
    """(PIL image or None, RGBA factor) of a trimesh material: a glTF PBR one or a simple one."""
    image = getattr(material, "baseColorTexture", None)
    if image is None:
        image = getattr(material, "image", None)
    factor = getattr(material, "baseColorFactor", None)
    factor = np.ones(4) if factor is None else np.asarray(factor, dtype=np.float64).reshape(-1)
    if factor.max(initial=0) > 1.0:  # trimesh keeps some factors as 0..255 bytes
        factor = factor / 255.0
    return image, np.pad(factor, (0, 4 - len(factor)), constant_values=1.0)[:4]


def check_texture_size(image) -> None:
    """Refuse a texture image of more than :data:`MAX_TEXTURE_PIXELS`, from its header (before it is decoded).

    Raises
    ------
    ShapeError
        ``too_large``, naming the image's size and the limit.
    """
    width, height = image.size
    if width * height > MAX_TEXTURE_PIXELS:
        raise ShapeError("too_large", f"the input's base-colour texture is {width} x {height} pixels "
                                      f"({width * height:,}), over the limit of {MAX_TEXTURE_PIXELS:,} pixels "
                                      f"({MAX_TEXTURE_SIDE} x {MAX_TEXTURE_SIDE}) read for bake=true; scale the "
                                      "texture down, or submit without bake")


def _reduced(image):
    """A PIL image as RGBA of at most :data:`MAX_SOURCE_SIDE` a side, or None where it does not decode.

    Scaled in place before the conversion (JPEG even decodes at the smaller scale): the full-size image is held
    once, in its own mode, never copied at full size.
    """
    from PIL import Image

    try:
        if image.mode not in ("RGB", "RGBA", "L", "LA"):  # palettes and 16-bit images scale badly as they are
            image = image.convert("RGBA")
        image.thumbnail((MAX_SOURCE_SIDE, MAX_SOURCE_SIDE))
        return image.convert("RGBA")
    except (OSError, ValueError, Image.DecompressionBombError):
        return None


def _pixels(image) -> np.ndarray | None:
    """(H, W, 4) uint8 of a PIL image, at most :data:`MAX_SOURCE_SIDE` a side; None where it does not decode."""
    small = _reduced(image)
    return None if small is None else np.asarray(small)


def read_texture(mesh) -> None:
    """Decode the base-colour image of a trimesh mesh once, scaled down to :data:`MAX_SOURCE_SIDE` a side, in place
    of the full one (which copying the mesh would copy); strip the visuals of a mesh whose image does not decode.

    Raises
    ------
    ShapeError
        ``too_large``: the image has more than :data:`MAX_TEXTURE_PIXELS` (:func:`check_texture_size`).
    """
    import trimesh

    material = getattr(mesh.visual, "material", None)
    image, _ = _image_of_material(material)
    if image is None:
        return
    check_texture_size(image)
    small = _reduced(image)
    if small is None:
        mesh.visual = trimesh.visual.ColorVisuals()
        return
    setattr(material, "baseColorTexture" if getattr(material, "baseColorTexture", None) is not None else "image",
            small)


def texture_of(meshes: list) -> SurfaceTexture | None:
    """The base-colour textures of trimesh ``meshes`` in the order their vertices are concatenated, or None
    when none has UVs and a texture image that decodes."""
    uvs, owners, images, factors, keys = [], [], [], [], {}
    for mesh in meshes:
        n = len(mesh.vertices)
        uv = getattr(mesh.visual, "uv", None)
        image, factor = _image_of_material(getattr(mesh.visual, "material", None))
        pixels = None if uv is None or image is None or len(uv) != n else _pixels(image)
        if pixels is None:
            uvs.append(np.full((n, 2), np.nan))
            owners.append(np.full(n, -1))
            continue
        key = (pixels.shape, hash(pixels.tobytes()), tuple(factor))  # meshes that share a material share it here
        if key not in keys:
            keys[key] = len(images)
            images.append(pixels)
            factors.append(factor)
        uvs.append(np.asarray(uv, dtype=np.float64))
        owners.append(np.full(n, keys[key]))
    if not images:
        return None
    return SurfaceTexture(uv=np.concatenate(uvs), image_of=np.concatenate(owners), images=images,
                          factors=np.asarray(factors))
