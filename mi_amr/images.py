"""Image files: EXR through the OpenEXR package, PNG previews through
Mitsuba's ``Bitmap`` (sRGB tone mapping)."""

from __future__ import annotations

from pathlib import Path

import mitsuba as mi
import numpy as np
import OpenEXR


def write_exr(path, image) -> Path:
    """Write a float image (H, W), (H, W, 1), (H, W, 3) or (H, W, 4) as EXR."""
    img = np.ascontiguousarray(np.asarray(image, dtype=np.float32))
    if img.ndim == 2:
        img = img[..., None]
    if img.ndim != 3 or img.shape[2] not in (1, 3, 4):
        raise ValueError(f"{path}: cannot write an image of shape {img.shape} as EXR")
    name = {1: "Y", 3: "RGB", 4: "RGBA"}[img.shape[2]]
    data = img[..., 0] if name == "Y" else img
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    with OpenEXR.File(header, {name: np.ascontiguousarray(data)}) as f:
        f.write(str(path))
    return Path(path)


def read_exr(path) -> np.ndarray:
    """Read an EXR file as float32 (H, W, C), channels in RGB(A) or Y order."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such file")
    try:
        with OpenEXR.File(str(path), separate_channels=True) as f:
            ch = {k: np.asarray(v.pixels, dtype=np.float32) for k, v in f.channels().items()}
    except Exception as e:  # OpenEXR raises bare Exceptions on damaged files
        raise ValueError(f"{path}: cannot read EXR file ({e})") from e
    for names in (("R", "G", "B", "A"), ("R", "G", "B"), ("Y",)):
        if all(n in ch for n in names):
            return np.stack([ch[n] for n in names], axis=-1)
    keys = sorted(ch)
    return np.stack([ch[k] for k in keys], axis=-1)


def _srgb8_bitmap(image):
    img = np.nan_to_num(np.asarray(image, dtype=np.float32)[..., :3], nan=0.0, posinf=0.0, neginf=0.0)
    bmp = mi.Bitmap(np.ascontiguousarray(img), mi.Bitmap.PixelFormat.RGB)
    return bmp.convert(mi.Bitmap.PixelFormat.RGB, mi.Struct.Type.UInt8, srgb_gamma=True)


def srgb8(image) -> np.ndarray:
    """A linear float image (H, W, 3+) as sRGB uint8 (H, W, 3), as `write_png`
    writes it (``mitsuba.Bitmap``: clipped, NaN/Inf as 0)."""
    return np.array(_srgb8_bitmap(image), copy=True).reshape(*np.shape(image)[:2], 3)


def write_png(path, image) -> Path:
    """sRGB 8-bit preview of a linear float image, via ``mitsuba.Bitmap``."""
    _srgb8_bitmap(image).write(str(path))
    return Path(path)


def png_bytes(image) -> bytes:
    """The sRGB 8-bit PNG of a linear float image, as bytes (what `write_png`
    writes; for a notebook's inline display)."""
    stream = mi.MemoryStream()
    _srgb8_bitmap(image).write(stream, mi.Bitmap.FileFormat.PNG)
    return bytes(stream.raw_buffer())


def compare_images(a, b) -> dict:
    """Error statistics of image ``a`` against reference ``b`` (H, W, C)."""
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    if a.shape != b.shape:
        raise ValueError(f"images differ in shape: {a.shape} vs {b.shape}")
    d = a - b
    out = {"rmse": float(np.sqrt(np.mean(d * d))),
           "mae": float(np.mean(np.abs(d))),
           "max_abs": float(np.max(np.abs(d))),
           "relative_rmse": float(np.sqrt(np.mean(d * d)) / max(np.sqrt(np.mean(b * b)), 1e-30)),
           "mean_a": float(a.mean()), "mean_b": float(b.mean()),
           "nonfinite_a": int((~np.isfinite(a)).sum()), "nonfinite_b": int((~np.isfinite(b)).sum()),
           "channels": []}
    if a.ndim == 3:
        for c in range(a.shape[2]):
            dc = d[..., c]
            out["channels"].append({"rmse": float(np.sqrt(np.mean(dc * dc))),
                                    "mean_a": float(a[..., c].mean()),
                                    "mean_b": float(b[..., c].mean()),
                                    "max_abs": float(np.abs(dc).max())})
    return out
