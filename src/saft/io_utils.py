"""Atomic file writing and image I/O shared by every package (no half-written results)."""

from __future__ import annotations

import json
import os
import tempfile
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator

import numpy as np
from saft.errors import SaftInputError


@contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """Yield a temporary path beside `path`; on success it is renamed onto `path`, on error removed."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=path.suffix or ".tmp", dir=path.parent)
    try:
        os.fchmod(fd, 0o666 & ~_umask())   # mkstemp creates 0600; a result is as readable as any new file
    finally:
        os.close(fd)
    tmp_path = Path(tmp)
    try:
        yield tmp_path
        os.replace(tmp_path, path)
    finally:
        if tmp_path.exists():
            tmp_path.unlink()


def _umask() -> int:
    """The process umask (read without changing it where /proc allows, else set and restored at once)."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("Umask:"):
                return int(line.split()[1], 8)
    except (OSError, ValueError, IndexError):
        pass
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def atomic_write_text(path: str | Path, text: str) -> None:
    with atomic_path(path) as tmp:
        tmp.write_text(text)


def atomic_write_bytes(path: str | Path, data: bytes) -> None:
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)


def atomic_write_json(path: str | Path, obj) -> None:
    atomic_write_text(path, json.dumps(obj, indent=2, default=_json_default) + "\n")


def atomic_save_npy(path: str | Path, array: np.ndarray) -> None:
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            np.save(fh, array)


def _json_default(obj):
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, Path):
        return str(obj)
    raise TypeError(f"not JSON serialisable: {type(obj).__name__}")


def read_image(path: str | Path) -> np.ndarray:
    """Read an image as float32 in [0, 1], H×W×C (C = 1, 3 or 4 as stored; 16-bit PNGs keep their precision).

    Raises SaftInputError naming the file when it is missing or cannot be decoded.
    """
    import imageio.v3 as iio

    path = Path(path)
    if not path.is_file():
        raise SaftInputError(path, "image not found")
    try:
        img = iio.imread(path)
    except Exception as exc:  # imageio raises many kinds of errors for corrupt files
        raise SaftInputError(path, f"cannot decode the image ({type(exc).__name__})") from None
    img = np.asarray(img)
    if img.ndim == 2:
        img = img[:, :, None]
    if img.ndim != 3:
        raise SaftInputError(path, f"unexpected image shape {img.shape}")
    if img.dtype == np.uint8:
        out = img.astype(np.float32) / 255.0
    elif img.dtype == np.uint16:
        out = img.astype(np.float32) / 65535.0
    elif np.issubdtype(img.dtype, np.floating):
        out = img.astype(np.float32)
    elif img.dtype == bool:
        out = img.astype(np.float32)
    else:
        raise SaftInputError(path, f"unsupported pixel type {img.dtype}")
    return out


def write_image(path: str | Path, image: np.ndarray, compress_level: int | None = None) -> None:
    """Write a float image in [0, 1] (H×W, H×W×1, ×3 or ×4) as an 8-bit PNG/JPEG, atomically.
    compress_level: PNG's zlib level (None: Pillow's default, 6)."""
    import imageio.v3 as iio

    img = np.asarray(image, dtype=np.float32)
    if img.ndim == 3 and img.shape[2] == 1:
        img = img[:, :, 0]
    img8 = (np.clip(img, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
    path = Path(path)
    extra = {} if compress_level is None or path.suffix.lower() != ".png" else {"compress_level": compress_level}
    with atomic_path(path) as tmp:
        iio.imwrite(tmp, img8, extension=path.suffix, **extra)


def resize_images(images, height: int, width: int):
    """Resize a torch batch (N, H, W) or (N, H, W, C) to (height, width): area averaging when shrinking,
    bilinear (align_corners=False) otherwise. Differentiable."""
    import torch.nn.functional as F

    if tuple(images.shape[1:3]) == (height, width):
        return images
    x = images[..., None] if images.dim() == 3 else images
    x = x.permute(0, 3, 1, 2)
    if height <= x.shape[2] and width <= x.shape[3]:
        x = F.interpolate(x, size=(height, width), mode="area")
    else:
        x = F.interpolate(x, size=(height, width), mode="bilinear", align_corners=False)
    x = x.permute(0, 2, 3, 1).contiguous()
    return x[..., 0] if images.dim() == 3 else x


def bilinear_sample(image: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Sample an (H, W) or (H, W, C) array at float pixel positions (P, 2) = (u, v); clamped at the border."""
    from scipy.ndimage import map_coordinates

    coords = points[:, ::-1].T                                     # (row, column) for map_coordinates
    if image.ndim == 2:
        return map_coordinates(image, coords, order=1, mode="nearest")
    return np.stack([map_coordinates(image[..., c], coords, order=1, mode="nearest")
                     for c in range(image.shape[2])], axis=1)
