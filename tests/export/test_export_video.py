"""Videos: the files exist, are H.264 mp4 of even size, and hold the expected number of frames."""

from __future__ import annotations

import numpy as np
import pytest

from saft.export import commands as export_commands
from saft.export import export_command
from saft.export import video as V
from saft.result import read_result
from saft.scene.camera import orbit_cameras


def test_comparison_videos(result_dir, tmp_path):
    import imageio.v3 as iio
    import imageio_ffmpeg

    res = read_result(result_dir)
    path, n = V.comparison_video(res, tmp_path / "cmp.mp4")
    assert n == res.num_frames and V.count_video_frames(path) == res.num_frames
    # the scene's frame rate: 6 frames 0.04 s apart play in 0.24 s
    reader = imageio_ffmpeg.read_frames(str(path))
    meta = next(reader)
    reader.close()
    assert meta["fps"] == pytest.approx(25.0)
    # labelled panels: 50-px panels enlarged ×7 (≥ 320 px), each under a dark header bar with white text
    frame = iio.imread(path, plugin="FFMPEG", index=3)
    header = frame[:12]
    assert frame.shape[1] == 3 * 350 and frame.shape[0] > 7 * 40
    for j in range(3):
        bar = header[:, j * 350:(j + 1) * 350].astype(int)
        assert (np.abs(bar - [36, 52, 77]).max(axis=2) < 24).mean() > 0.6  # the bar
        assert (bar.min(axis=2) > 200).sum() > 10                            # its label's white text
    path, n = V.comparison_video(res, tmp_path / "app.mp4", material=True)
    assert V.count_video_frames(path) == res.num_frames


def test_comparison_frames_colour_the_difference(tmp_path):
    from saft.io_utils import write_image

    target = np.zeros((20, 30, 3), np.float32)
    rendered = target.copy()
    rendered[5:10, 5:10] = 0.5                                   # one wrong square
    write_image(tmp_path / "frame_000.png", np.concatenate([rendered, target, target], axis=1))
    (frame,) = V.comparison_frames([tmp_path / "frame_000.png"], 0.02)
    scale = frame.shape[1] // 3 // 30
    head = frame.shape[0] - 20 * scale
    diff = frame[head:, 2 * 30 * scale:]
    hot = diff[7 * scale, 7 * scale].astype(int)
    cold = diff[15 * scale, 20 * scale].astype(int)
    assert hot.sum() > 600 and cold.sum() < 30   # the error at the top of the colour scale, elsewhere black


def test_odd_sizes_are_padded(tmp_path):
    frames = [np.full((33, 47, 3), i / 4, np.float32) for i in range(4)]
    path, n = V.write_mp4(tmp_path / "odd.mp4", frames, fps=10)
    import imageio.v3 as iio

    back = iio.imread(path, plugin="FFMPEG")
    assert back.shape == (4, 34, 48, 3)
    assert abs(int(back[2, 10, 10, 0]) - 128) < 6


@pytest.mark.parametrize("renderer", ["auto", "matplotlib"])
def test_orbit_video(result_dir, tmp_path, renderer):
    res = read_result(result_dir)
    frames, n, fps, used = V.orbit_frames(res, 64, 48, min_seconds=0.0, renderer=renderer)
    assert n == res.num_frames and fps == pytest.approx(min(1 / res.frame_dt, 30.0))
    path, count = V.write_mp4(tmp_path / f"orbit_{renderer}.mp4", frames, fps)
    assert V.count_video_frames(path) == n
    import imageio.v3 as iio

    first = iio.imread(path, plugin="FFMPEG", index=0)
    assert first.shape == (48, 64, 3)
    assert (np.abs(first.astype(int) - 237).max(axis=2) > 40).mean() > 0.05  # the cloth covers part of it


def test_orbit_cameras_circle_the_cloth(result_dir):
    res = read_result(result_dir)
    cams = orbit_cameras(res.vertices, res.camera, res.up_direction(), 8, 64, 48)
    centre = 0.5 * (res.vertices.reshape(-1, 3).min(0) + res.vertices.reshape(-1, 3).max(0))
    d = [np.linalg.norm(c.center - centre) for c in cams]
    np.testing.assert_allclose(d, d[0], rtol=1e-9)
    # half a turn about the up axis (−y here: gravity is +y): horizontal offset reversed, height kept
    np.testing.assert_allclose(cams[4].center - centre, (cams[0].center - centre) * [-1, 1, -1], atol=1e-9)
    for c in cams:  # the whole cloth is in view from everywhere
        uv, z = c.project(res.vertices.reshape(-1, 3))
        assert (z > 0).all() and (uv >= -0.5).all() and (uv[:, 0] <= 63.5).all() and (uv[:, 1] <= 47.5).all()


def test_export_video_command(bare_result_dir, monkeypatch):
    # keep the orbit short and small in the command test
    orig = V.orbit_video
    monkeypatch.setattr(export_commands, "orbit_video",
                        lambda res, out, **kw: orig(res, out, width=64, height=48, min_seconds=0))
    written = export_command(bare_result_dir, video=True)
    names = sorted(p.name for p in written)
    assert names == ["comparison.mp4", "orbit.mp4"]  # no material/renders → no appearance video
    for p in written:
        assert p.parent == bare_result_dir / "export" and V.count_video_frames(p) == 6
