"""FrameSequence: the video frames (RGB + mask) of a scene, loaded lazily, optionally cropped and rescaled."""

from __future__ import annotations

import logging
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Iterator, Sequence

import numpy as np

from saft.errors import SaftInputError
from saft.io_utils import read_image, resize_images
from saft.scene.camera import Crop

log = logging.getLogger("saft")

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp", ".exr")

# Pixels at or below this value (in [0, 1]) in every channel count as background when masks are derived.
DERIVED_MASK_THRESHOLD = 4.0 / 255.0


@dataclass(frozen=True)
class Frame:
    """One video frame: rgb (H, W, 3) float32 sRGB in [0, 1], mask (H, W) float32 in {0, 1}."""

    rgb: np.ndarray
    mask: np.ndarray


@dataclass(frozen=True)
class FrameSequence:
    """Frames in sorted order; images are read only when a frame is accessed.

    `crop` (in full-image pixels) and `scale` (resize factor applied after the crop) describe the working
    view; `camera.cropped(crop).scaled(scale)` is the matching camera.
    """

    rgb_paths: tuple[Path, ...]
    mask_paths: tuple[Path, ...] | None
    width: int
    height: int
    crop: Crop | None = None
    scale: float = 1.0
    _warned: list = field(default_factory=list, compare=False, repr=False)

    def __len__(self) -> int:
        return len(self.rgb_paths)

    @property
    def has_masks(self) -> bool:
        return self.mask_paths is not None

    @property
    def size(self) -> tuple[int, int]:
        """(height, width) of the frames as returned (after crop and scale)."""
        h, w = (self.crop.height, self.crop.width) if self.crop else (self.height, self.width)
        if self.scale != 1.0:
            w, h = max(1, int(round(w * self.scale))), max(1, int(round(h * self.scale)))
        return h, w

    def view(self, crop: Crop | None = None, scale: float = 1.0) -> "FrameSequence":
        """The same frames seen through a crop of the full image and a resize factor."""
        return replace(self, crop=crop, scale=scale)

    def __getitem__(self, index: int) -> Frame:
        if not -len(self) <= index < len(self):
            raise IndexError(index)
        rgb_path = self.rgb_paths[index]
        rgb = read_image(rgb_path)
        self._check_size(rgb_path, rgb)
        if rgb.shape[2] == 1:
            rgb = np.repeat(rgb, 3, axis=2)
        rgb = rgb[:, :, :3]
        if self.mask_paths is not None:
            mask_path = self.mask_paths[index]
            m = read_image(mask_path)
            self._check_size(mask_path, m)
            mask = mask_from_image(m)
            what = mask_path, "the mask is empty (no non-zero pixel)"
        else:
            if not self._warned:
                self._warned.append(True)
                log.warning("no masks given: deriving them from the non-black pixels of the frames")
            mask = (rgb.max(axis=2) > DERIVED_MASK_THRESHOLD).astype(np.float32)
            what = rgb_path, "the frame is black, so its mask (derived from non-black pixels) is empty"
        if self.crop is not None:
            rows, cols = self.crop.as_slices()
            rgb, mask = rgb[rows, cols], mask[rows, cols]
        if not mask.any():
            raise SaftInputError(what[0], f"frame {index}: {what[1]}{' inside the crop' if self.crop else ''}; "
                                          "every frame needs the cloth in its mask")
        if self.scale != 1.0:
            h, w = self.size
            rgb = _resize(rgb, h, w)
            mask = _resize(mask[:, :, None], h, w)[:, :, 0]
        return Frame(np.ascontiguousarray(rgb, dtype=np.float32), np.ascontiguousarray(mask, dtype=np.float32))

    def __iter__(self) -> Iterator[Frame]:
        for i in range(len(self)):
            yield self[i]

    def load(self, indices: Sequence[int] | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Stack frames: rgb (F, H, W, 3), mask (F, H, W)."""
        idx = range(len(self)) if indices is None else indices
        frames = [self[i] for i in idx]
        return np.stack([f.rgb for f in frames]), np.stack([f.mask for f in frames])

    def _check_size(self, path: Path, img: np.ndarray) -> None:
        if img.shape[0] != self.height or img.shape[1] != self.width:
            raise SaftInputError(
                path, f"image is {img.shape[1]}x{img.shape[0]} but the scene's frames are {self.width}x{self.height}"
            )


def mask_from_image(img: np.ndarray) -> np.ndarray:
    """(H, W) float32 {0, 1} foreground of a mask image (H, W, C) read by read_image.

    Any non-zero value is foreground (so 0/1 masks, 0/255 masks and soft masks all work). An image with an
    alpha channel whose colour channels are constant while its alpha varies is a mask stored in the alpha
    channel, and is read from there.
    """
    channels = img.shape[2]
    if channels in (2, 4):
        colour, alpha = img[:, :, :-1], img[:, :, -1]
        if colour.max() == colour.min() and alpha.max() != alpha.min():
            return (alpha > 0).astype(np.float32)
        img = colour
    return (img.max(axis=2) > 0).astype(np.float32)


def _resize(img: np.ndarray, height: int, width: int) -> np.ndarray:
    """(H, W, C) numpy image resized with saft.io_utils.resize_images (area down, bilinear up)."""
    import torch

    return resize_images(torch.from_numpy(np.ascontiguousarray(img))[None], height, width)[0].numpy()


def list_images(folder: Path) -> list[Path]:
    """Image files of a folder in sorted (natural) order; SaftInputError if the folder is missing or empty."""
    if not folder.is_dir():
        raise SaftInputError(folder, "folder not found")
    files = sorted((p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES and p.is_file()),
                   key=_natural_key)
    if not files:
        raise SaftInputError(folder, "no images in this folder")
    return files


def _natural_key(path: Path):
    import re

    return [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", path.name)]


def frame_sequence_from_folders(rgb_dir: Path, mask_dir: Path | None, size: tuple[int, int] | None = None,
                                size_source: str | Path | None = None) -> FrameSequence:
    """Build a FrameSequence, checking counts and that the first frame (and its mask) can be read.

    size: (width, height) the frames must have (the camera's, named by `size_source`); without it the first
    frame sets the size.
    """
    rgb_paths = list_images(rgb_dir)
    mask_paths = None
    if mask_dir is not None:
        mask_paths = list_images(mask_dir)
        if len(mask_paths) != len(rgb_paths):
            raise SaftInputError(mask_dir, f"has {len(mask_paths)} masks but {rgb_dir} has {len(rgb_paths)} frames")
    first = read_image(rgb_paths[0])
    height, width = first.shape[:2]
    if size is not None and (width, height) != tuple(size):
        raise SaftInputError(rgb_paths[0], f"image is {width}x{height} but {size_source or 'the camera'} says "
                                           f"{size[0]}x{size[1]}")
    seq = FrameSequence(tuple(rgb_paths), tuple(mask_paths) if mask_paths else None, width, height)
    seq[0]   # the first mask: readable, of the frame's size, not empty
    return seq


def check_all_frames(seq: FrameSequence, decode: bool = False) -> None:
    """Read the header of every frame and mask to find size mismatches and unreadable files up front.

    decode=True reads every frame and mask completely (finds truncated files and empty masks, slower).
    """
    from PIL import Image

    if decode:
        for i in range(len(seq)):
            seq[i]
        return
    paths = list(seq.rgb_paths) + list(seq.mask_paths or ())
    for p in paths:
        try:
            with Image.open(p) as im:
                w, h = im.size
        except Exception:
            # PIL cannot read EXR and some TIFFs: fall back to the full decoder, which names the file.
            img = read_image(p)
            h, w = img.shape[:2]
        if (w, h) != (seq.width, seq.height):
            raise SaftInputError(p, f"image is {w}x{h} but the scene's frames are {seq.width}x{seq.height}")
