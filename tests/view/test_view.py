"""`saft view`: what the viewer prepares from a result folder, and the real command serving a page that
headless Chromium (WebGL on SwiftShader) loads with no console errors and a 3D canvas that is not blank."""

from __future__ import annotations

import importlib.util
import json
import math
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from _chromium import Browser, chromium_path

from saft.scene.camera import look_at
from saft.view.data import colormap_strip, distance_uvs, frustum_pose, load_view_data, target_image, vertex_distances

REPO = Path(__file__).resolve().parents[2]


def _build_result(folder: Path) -> Path:
    """The export tests' small result folder (8×8 cloth, 6 frames, renders, material maps, metrics)."""
    spec = importlib.util.spec_from_file_location("export_conftest", REPO / "tests" / "export" / "conftest.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod.build_result(folder)


@pytest.fixture(scope="module")
def result_with_gt(tmp_path_factory) -> Path:
    """A result whose scene.json names world-frame ground truth: the result's own frames shifted 1 cm."""
    folder = _build_result(tmp_path_factory.mktemp("view") / "result")
    data = load_view_data(folder)
    gt = folder.parent / "gt"
    gt.mkdir()
    for k, verts in enumerate(data.result.vertices):
        np.save(gt / f"{k:03d}.npy", verts + np.array([0.0, 0.0, 0.01]))
    info = json.loads((folder / "scene.json").read_text())
    info.update(ground_truth_dir=str(gt), ground_truth_frame="world")
    (folder / "scene.json").write_text(json.dumps(info))
    return folder


def test_view_data(result_with_gt):
    data = load_view_data(result_with_gt)
    assert data.num_frames == 6 and data.fps == pytest.approx(25.0)
    assert np.allclose(data.up, [0.0, -1.0, 0.0])  # opposite the scene's gravity (0, 9.81, 0)
    assert set(data.material) == {"diffuse", "roughness", "metallic", "envmap"}
    assert data.gt_frames is not None and len(data.gt_frames) == 6
    assert data.distances.shape == (6, 64) and np.allclose(data.distances, 0.01)
    u = distance_uvs(np.array([0.0, 0.005, 0.02, np.nan]), 0.01)[:, 0]
    assert u[0] < u[1] < u[2] and u[2] == pytest.approx(0.99) and u[3] == pytest.approx(0.01)
    strip = colormap_strip()
    assert strip.shape == (4, 256, 3) and strip[0, 0].tolist() != strip[0, -1].tolist()
    img = target_image(data.render_files[2], None)  # renders are rendered | target | |difference|, 50 px each
    assert img.shape == (40, 50, 3) and img.dtype == np.uint8


def test_vertex_distances_missing_frames():
    verts = np.zeros((3, 2, 3))
    d = vertex_distances(verts, [np.array([[0.0, 0.0, 0.5]]), np.array([[0.0, 3.0, 4.0]])])
    assert d[:2].tolist() == [[0.5, 0.5], [5.0, 5.0]] and np.isnan(d[2]).all()


def test_frustum_pose_is_opencv():
    """viser's frustum looks along its local +z with +y down: the rotation must be the camera-to-world one."""
    from scipy.spatial.transform import Rotation

    cam = look_at([1.0, 0.5, -2.0], [0.0, 0.0, 0.0], [0.0, -1.0, 0.0],
                  np.array([[100.0, 0, 63.5], [0, 100.0, 47.5], [0, 0, 1]]), 128, 96)
    wxyz, pos, fov, aspect = frustum_pose(cam)
    R = Rotation.from_quat([*wxyz[1:], wxyz[0]]).as_matrix()
    assert np.allclose(pos, [1.0, 0.5, -2.0])
    assert np.allclose(R @ [0, 0, 1], cam.forward) and np.allclose(R @ [0, -1, 0], cam.up)
    assert fov == pytest.approx(2 * math.atan(48 / 100)) and aspect == pytest.approx(128 / 96)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_view_in_headless_chromium(result_with_gt, tmp_path):
    exe = chromium_path()
    if exe is None:
        pytest.skip("chromium not installed (Debian: apt-get install -y chromium; install.sh --dev does it)")
    pytest.importorskip("viser")
    env = {**os.environ, "PYTHONPATH": str(REPO / "src")}
    # SIGINT back to its default in the child: a suite started as a background job (`cmd &` in a script)
    # ignores SIGINT, the viewer would inherit that and never see the Ctrl-C sent below
    proc = subprocess.Popen([sys.executable, "-m", "saft", "view", str(result_with_gt), "--port", str(_free_port())],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, env=env, text=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    browser = None
    try:
        url = None
        deadline = time.time() + 60
        lines = []
        while url is None and time.time() < deadline:
            line = proc.stdout.readline()
            if not line:
                break
            lines.append(line)
            if line.startswith("saft view:") and "http://" in line:
                url = line.split("http://", 1)[1].split()[0]
        assert url is not None, "".join(lines)
        assert url.startswith("localhost:")
        browser = Browser(exe, tmp_path, webgl=True)
        browser.navigate(f"http://127.0.0.1:{url.split(':')[1]}/")
        # wait until the viewer has connected and drawn: the 3D canvas shows more than its background
        variance, shot = 0.0, None
        for _ in range(60):
            time.sleep(0.5)
            box = browser.evaluate("(() => { const c = document.querySelector('canvas'); if (!c) return null;"
                                   " const r = c.getBoundingClientRect();"
                                   " return {x: r.x, y: r.y, width: r.width, height: r.height}; })()")
            if box and box["width"] > 100 and box["height"] > 100:
                shot = browser.screenshot(box)
                variance = float(shot.reshape(-1, 3).astype(np.float64).std(axis=0).mean())
                if variance > 8.0:
                    break
        assert shot is not None, "no canvas on the page"
        assert variance > 8.0, f"the 3D canvas looks blank (pixel std {variance:.2f})"
        assert browser.errors() == []
        text = browser.evaluate("document.body.innerText")
        from PIL import Image

        Image.fromarray(shot).save(tmp_path / "canvas.png")
        if os.environ.get("SAFT_VIEW_SHOT"):  # a picture of the whole page, for people
            Image.fromarray(browser.screenshot()).save(os.environ["SAFT_VIEW_SHOT"])
        for expected in ("wave", "t = 0.000 s", "CD2 (10⁻⁴ m²) 1", "per-vertex distance (mm)", "static template",
                         "ground-truth points", "Material maps (phase 3)"):
            assert expected in text, text
    finally:
        if browser is not None:
            browser.close()
        proc.send_signal(signal.SIGINT)
        try:
            # 60 s: under load (two other jobs on 2 cores) the clean stop once took more than 20
            out = proc.communicate(timeout=60)[0]
        except subprocess.TimeoutExpired:
            proc.kill()
            out = proc.communicate()[0]
    assert proc.returncode == 0, out
    assert "saft view: stopped" in out


def test_viewer_scene_every_colouring(result_with_gt):
    """The viser scene without a browser: every colouring of every frame builds its mesh, one is shown at a
    time, the ground-truth cloud follows the frame, and the timeline wraps around while playing."""
    viser = pytest.importorskip("viser")
    from saft.view.server import COLOUR_DISTANCE, COLOUR_MATERIAL, COLOUR_TEXTURE, ClothViewer

    server = viser.ViserServer(host="127.0.0.1", port=_free_port(), verbose=False)
    try:
        viewer = ClothViewer(server, load_view_data(result_with_gt))
        assert list(viewer.materials) == [COLOUR_TEXTURE, COLOUR_MATERIAL, COLOUR_DISTANCE]
        viewer.show_gt.value = True
        for colouring in viewer.materials:
            viewer.colouring.value = colouring
            for k in (0, 5):
                viewer.show(k)
                shown = [key for key, handle in viewer.meshes.items() if handle.visible]
                assert shown == [(colouring, k)]
                assert [j for j, h in viewer.clouds.items() if h.visible] == [k]
        assert viewer.time_text.content == "t = 0.200 s" and "CD2 (10⁻⁴ m²) 1.5" in viewer.metrics_text.content
        assert viewer.frustum is not None and viewer.frustum.image.shape == (40, 50, 3)
        viewer.play.value = True
        viewer.slider.value = 5
        viewer.show(5)
        viewer.step()
        time.sleep(0.3)  # the slider's callback runs on viser's thread
        assert viewer.frame == 0
    finally:
        server.stop()
