"""mp4 videos of a result (H.264 via imageio-ffmpeg's bundled ffmpeg, yuv420p so every player opens them).

* comparison.mp4 — renders/frame_*.png as labelled panels "rendered | target | |difference|", the
  difference as a colour map on one scale for the whole video (named in its label), at the scene's frame
  rate 1/frame_dt; small frames are enlarged (whole pixels) so that the labels are legible.
* appearance.mp4 — material/renders/frame_*.png (the appearance phase's re-renders) the same way, when present.
* orbit.mp4 — a novel view: a camera circling the cloth about the world's up axis, starting from the
  working camera, while the sequence plays (slowed to last at least `min_seconds`; at most 30 fps). Rendered with
  saft.render.render_cloth (the textured cloth, simple headlight shading); if that renderer cannot be
  loaded, a matplotlib Poly3DCollection drawing is used instead.

Frame sizes are padded to even numbers (libx264 with yuv420p needs them).
"""

from __future__ import annotations

import logging
import math
from pathlib import Path
from typing import Iterable, Iterator

import numpy as np

from saft.errors import SaftInputError
from saft.export.figures import abs_difference, difference_scale, split_panels
from saft.io_utils import atomic_path, read_image
from saft.render import render_cloth
from saft.result import Result, list_render_files, read_result
from saft.scene.camera import Camera, orbit_cameras

log = logging.getLogger("saft")

BACKGROUND = np.array([0.93, 0.93, 0.95], dtype=np.float32)


def _to_uint8_even(img: np.ndarray) -> np.ndarray:
    img = np.asarray(img)
    if img.ndim == 2:
        img = img[:, :, None]
    if img.shape[2] == 1:
        img = np.repeat(img, 3, axis=2)
    img = img[:, :, :3]
    if img.dtype != np.uint8:
        img = (np.clip(img, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
    h, w = img.shape[:2]
    if h % 2 or w % 2:
        img = np.pad(img, ((0, h % 2), (0, w % 2), (0, 0)), mode="edge")
    return np.ascontiguousarray(img)


def write_mp4(path: str | Path, frames: Iterable[np.ndarray], fps: float, quality: float = 8.0) -> tuple[Path, int]:
    """Write frames (H×W×3 float in [0, 1] or uint8, all of one size) as H.264 mp4, atomically.
    Returns (path, number of frames written)."""
    import imageio_ffmpeg

    path = Path(path)
    count = 0
    with atomic_path(path) as tmp:
        writer = None
        try:
            for frame in frames:
                img = _to_uint8_even(frame)
                if writer is None:
                    size = (img.shape[1], img.shape[0])
                    writer = imageio_ffmpeg.write_frames(
                        str(tmp), size, fps=float(fps), codec="libx264", pix_fmt_in="rgb24", pix_fmt_out="yuv420p",
                        quality=quality, macro_block_size=1, ffmpeg_log_level="error")
                    writer.send(None)
                elif (img.shape[1], img.shape[0]) != size:
                    raise ValueError(f"frame {count} is {img.shape[1]}x{img.shape[0]}, the video is {size[0]}x{size[1]}")
                writer.send(img.tobytes())
                count += 1
        finally:
            if writer is not None:
                writer.close()
        if count == 0:
            raise ValueError("no frames to write")
    return path, count


def count_video_frames(path: str | Path) -> int:
    """Frames in a video file, as ffmpeg decodes them."""
    import imageio_ffmpeg

    return int(imageio_ffmpeg.count_frames_and_secs(str(path))[0])


def fps_of(res: Result) -> float:
    """The scene's frame rate 1/frame_dt (25 fps when a result does not say)."""
    return 1.0 / res.frame_dt if res.frame_dt > 0 else 25.0


MIN_PANEL_WIDTH = 320   # px; smaller panels are enlarged by a whole factor


def _font(size: int):
    from PIL import ImageFont

    return ImageFont.load_default(size=size)


def _labelled(panel: np.ndarray, text: str, scale: int) -> np.ndarray:
    """A panel (H×W×3 float) enlarged `scale` times, under a header bar with its label."""
    from PIL import Image, ImageDraw

    img = _to_uint8_even(panel)
    if scale > 1:
        img = np.repeat(np.repeat(img, scale, axis=0), scale, axis=1)
    w = img.shape[1]
    size = max(11, min(18, w // 22))
    head = Image.new("RGB", (w, size + 10), (36, 52, 77))
    ImageDraw.Draw(head).text((6, 4), text, fill=(255, 255, 255), font=_font(size))
    return np.concatenate([np.asarray(head), img], axis=0)


def comparison_frames(paths: list[Path], frame_dt: float, material: bool = False) -> list[np.ndarray]:
    """renders/ (rendered | target | …) or material/renders/ (re-render | target) frames as labelled panels
    "rendered | target | |difference|", the difference coloured (magma) on one scale for all frames."""
    import matplotlib

    pairs = []
    shape = None
    for p in paths:
        img = read_image(p)
        if shape is None:
            shape = img.shape
        elif img.shape != shape:
            raise SaftInputError(p, f"is {img.shape[1]}x{img.shape[0]}, the first frame is {shape[1]}x{shape[0]}")
        pairs.append(split_panels(img, 2 if material else 3)[:2])
    diffs = [abs_difference(r, t) for r, t in pairs]
    vmax = difference_scale(diffs)
    cmap = matplotlib.colormaps["magma"]
    w = pairs[0][0].shape[1]
    scale = max(1, -(-MIN_PANEL_WIDTH // w))
    first = "re-render" if material else "rendered"
    out = []
    for k, ((rendered, target), diff) in enumerate(zip(pairs, diffs)):
        coloured = cmap(np.clip(diff / vmax, 0.0, 1.0))[:, :, :3]
        out.append(np.concatenate([
            _labelled(rendered, f"{first}  frame {k}, t = {k * frame_dt:.2f} s", scale),
            _labelled(target, "target", scale),
            _labelled(coloured, f"|difference|  black 0 .. white {vmax:.2f}", scale)], axis=1))
    return out


def comparison_video(result: str | Path | Result, out: str | Path, material: bool = False) -> tuple[Path, int]:
    """renders/ (or material/renders/) frames as a labelled mp4 at the scene's frame rate 1/frame_dt."""
    res = result if isinstance(result, Result) else read_result(result)
    files = list_render_files(res.folder, material=material)
    if not files:
        raise SaftInputError(res.folder / ("material/renders" if material else "renders"), "no frame_*.png renders")
    path, n = write_mp4(out, comparison_frames(files, res.frame_dt, material), fps_of(res))
    log.info("wrote %s (%d frames at %.4g fps)", path, n, fps_of(res))
    return path, n


# ---------------------------------------------------------------------------- orbit
def _orbit_texture(res: Result) -> np.ndarray:
    p = res.material_path("diffuse.png")
    if p is not None:
        return read_image(p)[:, :, :3]
    if res.texture is not None:
        return res.texture
    return np.full((4, 4, 3), 0.7, np.float32)


def _render_saft(res: Result, verts: np.ndarray, cam: Camera, tex: np.ndarray) -> np.ndarray:
    import torch

    with torch.no_grad():
        out = render_cloth(torch.as_tensor(verts, dtype=torch.float32), torch.as_tensor(res.template.triangles),
                           torch.as_tensor(res.template.uvs, dtype=torch.float32),
                           torch.as_tensor(tex, dtype=torch.float32), cam)
    rgb = out.rgb[0].numpy()
    mask = out.mask[0].numpy()[:, :, None]
    n = out.normals[0].numpy()
    shade = 0.35 + 0.65 * np.abs(n @ cam.forward)[:, :, None]  # two-sided headlight
    shade = np.where(np.linalg.norm(n, axis=2, keepdims=True) > 0.5, shade, 1.0)
    return rgb * shade + (1.0 - mask) * BACKGROUND


class _MatplotlibOrbit:
    """Fallback drawing: shaded, textured-per-face Poly3DCollection in a fixed figure."""

    def __init__(self, res: Result, width: int, height: int, tex: np.ndarray):
        import matplotlib

        matplotlib.use("Agg", force=True)
        import matplotlib.pyplot as plt
        from mpl_toolkits.mplot3d.art3d import Poly3DCollection

        self.plt = plt
        self.tris = res.template.triangles
        uv = res.template.uvs[self.tris].mean(axis=1)
        th, tw = tex.shape[:2]
        rows = np.clip(((1.0 - uv[:, 1]) * th).astype(int), 0, th - 1)
        cols = np.clip((uv[:, 0] * tw).astype(int), 0, tw - 1)
        self.face_rgb = tex[rows, cols, :3]
        self.fig = plt.figure(figsize=(width / 100, height / 100), dpi=100)
        self.ax = self.fig.add_axes([0, 0, 1, 1], projection="3d")
        self.ax.set_axis_off()
        self.ax.set_box_aspect((1, 1, 1))
        self.fig.patch.set_facecolor(BACKGROUND)
        self.ax.set_facecolor(BACKGROUND)
        self.coll = Poly3DCollection([], linewidths=0)
        self.ax.add_collection3d(self.coll)
        self.size = (width, height)

    def draw(self, verts: np.ndarray, cam: Camera) -> np.ndarray:
        # camera frame (OpenCV) → matplotlib axes (x = right, y = forward/depth, z = up); the default
        # viewer at azim −90°, elev 0° then sees exactly the camera's view (orthographic)
        pc = cam.world_to_cam_points(verts)
        local = np.stack([pc[:, 0], pc[:, 2], -pc[:, 1]], axis=1)
        tri = local[self.tris]
        n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-20)
        shade = 0.35 + 0.65 * np.abs(n[:, 1])
        self.coll.set_verts(tri)
        self.coll.set_facecolor(np.clip(self.face_rgb * shade[:, None], 0, 1))
        c = 0.5 * (local.min(axis=0) + local.max(axis=0))
        r = float(np.abs(local - c).max()) * 1.1 + 1e-6
        self.ax.set_xlim(c[0] - r, c[0] + r)
        self.ax.set_ylim(c[1] - r, c[1] + r)
        self.ax.set_zlim(c[2] - r, c[2] + r)
        self.ax.view_init(elev=0, azim=-90)
        self.fig.canvas.draw()
        img = np.asarray(self.fig.canvas.buffer_rgba())[:, :, :3]
        return img[: self.size[1], : self.size[0]]

    def close(self):
        self.plt.close(self.fig)


def orbit_frames(res: Result, width: int = 480, height: int = 360, fps: float | None = None,
                 min_seconds: float = 4.0, renderer: str = "auto") -> tuple[Iterator[np.ndarray], int, float, str]:
    """(frame iterator, frame count, fps, renderer used) of the orbiting novel view."""
    fps = min(fps_of(res), 30.0) if fps is None else float(fps)
    n_out = max(res.num_frames, int(math.ceil(min_seconds * fps)))
    cams = orbit_cameras(res.vertices, res.camera, res.up_direction(), n_out, width, height)
    tex = _orbit_texture(res)
    use = renderer
    if renderer == "auto":
        try:
            _render_saft(res, res.vertices[0], cams[0], tex)
            use = "saft.render"
        except Exception as exc:  # a renderer under development must not stop the export
            log.warning("saft.render unavailable for the orbit video (%s); drawing with matplotlib", exc)
            use = "matplotlib"

    def gen() -> Iterator[np.ndarray]:
        mpl = _MatplotlibOrbit(res, width, height, tex) if use == "matplotlib" else None
        try:
            for i, cam in enumerate(cams):
                verts = res.vertices[min(res.num_frames - 1, i * res.num_frames // n_out)]
                yield mpl.draw(verts, cam) if mpl is not None else _render_saft(res, verts, cam, tex)
        finally:
            if mpl is not None:
                mpl.close()

    return gen(), n_out, fps, use


def orbit_video(result: str | Path | Result, out: str | Path, width: int = 480, height: int = 360,
                min_seconds: float = 4.0, renderer: str = "auto") -> tuple[Path, int]:
    res = result if isinstance(result, Result) else read_result(result)
    frames, _, fps, used = orbit_frames(res, width + width % 2, height + height % 2, min_seconds=min_seconds,
                                        renderer=renderer)
    path, n = write_mp4(out, frames, fps)
    log.info("wrote %s (%d frames, novel view drawn with %s)", path, n, used)
    return path, n
