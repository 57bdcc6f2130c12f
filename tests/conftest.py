"""Shared test fixtures: the location of ../shared and a small native scene written on the fly."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]
# Test this checkout's sources even when another checkout is the pip-installed (editable) one.
sys.path.insert(0, str(REPO / "src"))
SHARED = (REPO / ".." / "shared").resolve()
PHI_SFT = SHARED / "data" / "phi_sft"


@pytest.fixture(scope="session")
def phi_sft_dir() -> Path:
    if not (PHI_SFT / "data" / "scenes" / "R1.json").is_file():
        pytest.skip(f"real-scene data not found at {PHI_SFT} (the shared/ folder beside the repository)")
    return PHI_SFT


def grid_quad_obj(n: int = 4, size: float = 0.4, z: float = 1.0) -> str:
    """OBJ text of an n×n-vertex flat grid facing the camera at depth z (metres), one vt per vertex."""
    lines = []
    for i in range(n):
        for j in range(n):
            lines.append(f"v {(j / (n - 1) - 0.5) * size} {(i / (n - 1) - 0.5) * size} {z}")
    for i in range(n):
        for j in range(n):
            lines.append(f"vt {j / (n - 1)} {i / (n - 1)}")
    for i in range(n - 1):
        for j in range(n - 1):
            a = i * n + j + 1
            b, c, d = a + 1, a + n + 1, a + n
            lines.append(f"f {a}/{a} {b}/{b} {c}/{c} {d}/{d}")
    return "\n".join(lines) + "\n"


def write_image(path: Path, img: np.ndarray) -> None:
    import imageio.v3 as iio

    path.parent.mkdir(parents=True, exist_ok=True)
    iio.imwrite(path, img)


@pytest.fixture
def native_scene(tmp_path: Path) -> Path:
    """A minimal valid native scene: 4×4 grid, 3 frames of 40×32 px with masks, scene.json."""
    return make_native_scene(tmp_path / "scene")


@pytest.fixture(scope="session")
def native_scene_factory():
    """make_native_scene, for fixtures of a wider scope than native_scene's."""
    return make_native_scene


def make_native_scene(folder: Path) -> Path:
    """Write the scene of the `native_scene` fixture into `folder` (for fixtures of other scopes)."""
    folder.mkdir(parents=True)
    (folder / "template.obj").write_text(grid_quad_obj())
    cam = {"width": 40, "height": 32, "K": [[40, 0, 19.5], [0, 40, 15.5], [0, 0, 1]],
           "world_to_camera": np.eye(4).tolist(), "distortion": [0, 0, 0, 0], "note": "extra keys are ignored"}
    (folder / "camera.json").write_text(json.dumps(cam))
    for i in range(3):
        img = np.zeros((32, 40, 3), np.uint8)
        img[8:24, 12:28] = 120 + 20 * i
        write_image(folder / "rgb" / f"{i:03d}.png", img)
        write_image(folder / "mask" / f"{i:03d}.png", (img[:, :, 0] > 0).astype(np.uint8) * 255)
    (folder / "scene.json").write_text(json.dumps({"fps": 25, "pinned_vertices": [12, 13, 14, 15],
                                                   "gravity": [0, 9.81, 0], "unknown": 1}))
    return folder
