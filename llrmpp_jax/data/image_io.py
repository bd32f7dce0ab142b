"""Image and depth-map files through OpenImageIO (JPEG, PNG 8/16-bit, EXR float, ...).

Colour images come back as ``[H, W, 3]`` float32 in [0, 1] (8-bit / 255, 16-bit / 65535,
float formats as stored); grey images are repeated to 3 channels and alpha is dropped.
Depth maps come back as ``[H, W]`` float32 metres: integer files (ScanNet / nerfstudio
16-bit PNG) are multiplied by ``scale`` (default 1e-3: millimetres), float files (EXR)
are taken as metres. Every failure names the file: ``FileNotFoundError`` when it does
not exist, ``ValueError`` when it cannot be decoded (corrupt or truncated).
"""

from __future__ import annotations

import os

import numpy as np
import OpenImageIO as oiio

from llrmpp_jax.array_typing import Float
from llrmpp_jax.errors import MissingInputError, UserError
from llrmpp_jax.file_kinds import looks_like

_INT_RANGES = {"uint8": 255.0, "uint16": 65535.0}


def _one_line(err: str) -> str:
    """OpenImageIO's message on one line (its readers report several problems a line each)."""
    return "; ".join(x.strip() for x in err.splitlines() if x.strip())


def _open(path: str) -> oiio.ImageInput:
    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        err = _one_line(oiio.geterror())
        if not os.path.exists(path):
            raise MissingInputError(f"image file not found: {path}")
        raise UserError(f"cannot open image file {path}: {err} (it looks like {looks_like(path)})")
    return inp


def _read(path: str) -> tuple[np.ndarray, str]:
    """Raw pixels ``[H, W, C]`` in the file's own type (uint8, uint16 or float32)."""
    inp = _open(path)
    try:
        spec = inp.spec()
        kind = str(spec.format)
        fmt = kind if kind in _INT_RANGES else "float"
        pixels = inp.read_image(0, 0, 0, spec.nchannels, fmt)
        if pixels is None or inp.has_error:
            raise UserError(f"cannot decode image file {path} (corrupt or truncated): {_one_line(inp.geterror())}")
    finally:
        inp.close()
    if pixels.ndim == 2:
        pixels = pixels[:, :, None]
    return pixels, fmt


def image_size(path: str) -> tuple[int, int]:
    """``(H, W)`` of an image file from its header, without decoding the pixels."""
    inp = _open(path)
    try:
        spec = inp.spec()
        return int(spec.height), int(spec.width)
    finally:
        inp.close()


def read_image(path: str) -> Float[np.ndarray, "H W 3"]:
    """Colour image ``[H, W, 3]`` float32 in [0, 1] (float files are not clipped)."""
    pixels, fmt = _read(path)
    if fmt in _INT_RANGES:
        pixels = pixels.astype(np.float32) / np.float32(_INT_RANGES[fmt])
    else:
        pixels = pixels.astype(np.float32)
        if not np.isfinite(pixels).all():
            raise UserError(f"image file {path} has non-finite pixel values")
    channels = pixels.shape[2]
    if channels in (1, 2):  # grey or grey + alpha
        return np.repeat(pixels[:, :, :1], 3, axis=2)
    return np.ascontiguousarray(pixels[:, :, :3])


def read_depth(path: str, scale: float = 1e-3) -> Float[np.ndarray, "H W"]:
    """Depth map ``[H, W]`` float32: integer files times ``scale``, float files as stored.
    Non-finite and negative values become 0 (invalid)."""
    pixels, fmt = _read(path)
    if fmt == "uint8":
        raise UserError(f"depth file {path}: 8-bit depth is not supported (expected 16-bit PNG or float EXR)")
    depth = pixels[:, :, 0].astype(np.float64)
    if fmt == "uint16":
        depth = depth * scale
    depth = np.where(np.isfinite(depth) & (depth > 0), depth, 0.0)
    return depth.astype(np.float32)


def _write(path: str, pixels: np.ndarray, fmt: str, attributes: dict[str, str] | None = None) -> None:
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    h, w, c = pixels.shape
    out = oiio.ImageOutput.create(str(path))
    if out is None:
        raise UserError(f"cannot write image file {path}: {oiio.geterror()}")
    spec = oiio.ImageSpec(w, h, c, {"uint8": oiio.UINT8, "uint16": oiio.UINT16, "float": oiio.FLOAT}[fmt])
    if str(path).lower().endswith((".jpg", ".jpeg")):
        spec.attribute("Compression", "jpeg:95")
    for name, value in (attributes or {}).items():
        spec.attribute(name, str(value))
    ok = out.open(str(path), spec) and out.write_image(np.ascontiguousarray(pixels))
    err = out.geterror()
    out.close()
    if not ok:
        raise UserError(f"cannot write image file {path}: {err}")


def write_image(path: str, image: Float[np.ndarray, "H W 3"], bits: int = 8) -> None:
    """Write ``[H, W, 3]`` colour in [0, 1]. ``bits`` 8 or 16 quantise (round to nearest,
    clipped); 32 writes float (EXR, lossless). JPEG supports 8 only."""
    image = np.asarray(image, dtype=np.float32)
    if image.ndim != 3 or image.shape[2] != 3:
        raise UserError(f"write_image {path}: image must have shape [H, W, 3], got {image.shape}")
    if bits == 32:
        _write(path, image, "float")
    elif bits in (8, 16):
        top = 255.0 if bits == 8 else 65535.0
        q = np.rint(np.clip(image, 0.0, 1.0) * top)
        _write(path, q.astype(np.uint8 if bits == 8 else np.uint16), "uint8" if bits == 8 else "uint16")
    else:
        raise UserError(f"write_image {path}: bits must be 8, 16 or 32, got {bits}")


def write_depth(
    path: str, depth: Float[np.ndarray, "H W"], scale: float | None = 1e-3, attributes: dict[str, str] | None = None
) -> None:
    """Write a ``[H, W]`` depth map: ``scale`` given -> 16-bit integers ``round(depth / scale)``
    (PNG; ``ValueError`` if a value exceeds 65535 units); ``scale=None`` -> float32 (EXR).
    ``attributes``: metadata written into the file's header (e.g. what the values mean)."""
    depth = np.asarray(depth, dtype=np.float32)
    if depth.ndim != 2:
        raise UserError(f"write_depth {path}: depth must have shape [H, W], got {depth.shape}")
    if scale is None:
        _write(path, depth[:, :, None], "float", attributes)
        return
    units = np.rint(depth.astype(np.float64) / scale)
    if units.max(initial=0.0) > 65535:
        raise UserError(
            f"write_depth {path}: depth {float(depth.max())} m exceeds the 16-bit range at scale {scale} m/unit"
        )
    _write(path, units.astype(np.uint16)[:, :, None], "uint16", attributes)
