"""The base-colour texture of a textured glTF input, read with its mesh (``load_shape(texture=True)``) and kept
with the shape (``Shape.texture``) for ``fastmesh.export.bake``."""

from __future__ import annotations

import io
from dataclasses import dataclass

import numpy as np

MAX_SOURCE_SIDE = 2048  # an input texture is read at most this many texels a side (a baked one has 1024)


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


def _pixels(image) -> np.ndarray | None:
    """(H, W, 4) uint8 of a PIL image, at most :data:`MAX_SOURCE_SIDE` a side; None where it does not decode."""
    from PIL import Image

    try:
        rgba = image.convert("RGBA")
        rgba.thumbnail((MAX_SOURCE_SIDE, MAX_SOURCE_SIDE))
        return np.asarray(rgba)
    except (OSError, ValueError, Image.DecompressionBombError):
        return None


def drop_unreadable(mesh) -> None:
    """Strip the visuals of a trimesh mesh whose base-colour image does not decode (copying it would fail)."""
    import trimesh

    image, _ = _image_of_material(getattr(mesh.visual, "material", None))
    if image is not None and _pixels(image) is None:
        mesh.visual = trimesh.visual.ColorVisuals()


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
