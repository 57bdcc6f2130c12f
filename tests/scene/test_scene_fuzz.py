"""Property-based: random mutations of valid scene JSONs, camera JSONs and OBJ templates end in a scene
(or mesh, or camera) or in SaftInputError, never in any other exception (a traceback for the user)."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from saft.errors import SaftInputError
from saft.io_utils import write_image
from saft.scene import load_scene, read_obj
from saft.scene.mesh import obj_text
from saft.scene.native import read_camera_json
from saft.synthetic.hanging_cloth import grid_template

_GRID = grid_template(4, 0.4)
TEMPLATE_OBJ = obj_text(_GRID.with_vertices(_GRID.vertices + [0.0, 0.0, 1.0]))   # 1 m in front of the camera

FUZZ = settings(max_examples=40, deadline=None, derandomize=True,
                suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])

CAMERA = {"width": 40, "height": 32, "K": [[40, 0, 19.5], [0, 40, 15.5], [0, 0, 1]],
          "world_to_camera": np.eye(4).tolist()}
NATIVE_META = {"fps": 25, "pinned_vertices": [12, 13, 14, 15], "gravity": [0, 9.81, 0],
               "crop": {"top": 0, "left": 0, "height": 32, "width": 40}, "ground_truth": {"dir": "gt", "frame": "world"}}
# A SAFT/PG-SfT scene JSON whose paths are relative to its own folder (one of the places the reader looks).
PHI_SFT = {"scene": "fuzz", "mesh_file": "template.obj", "image_files": "rgb", "mask_files": "mask", "n_images": 3,
           "camera_positions": [[0, 0, 0]], "camera_directions": [[0, 0, 1]], "camera_ups": [[0, -1, 0]],
           "optical_centers": [[15.5, 19.5]], "focal_lengths": [[40, 40]], "image_size": [[32, 40]],
           "lower_left_corners": [[0, 0]], "upper_right_corners": [[32, 40]], "ground_truth_dir": "gt"}

def _text(max_size: int):
    return st.text(st.characters(blacklist_categories=("Cs",)), max_size=max_size)


json_values = st.recursive(
    st.none() | st.booleans() | st.integers(-10**6, 10**20) | st.floats(allow_nan=True, allow_infinity=True)
    | _text(8),
    lambda inner: st.lists(inner, max_size=5) | st.dictionaries(_text(6), inner, max_size=4),
    max_leaves=12)


def _paths(obj, prefix=()):
    """Every path into a nested JSON value (dict keys and list indices)."""
    yield prefix
    if isinstance(obj, dict):
        for k, v in obj.items():
            yield from _paths(v, prefix + (k,))
    elif isinstance(obj, list):
        for i, v in enumerate(obj):
            yield from _paths(v, prefix + (i,))


@st.composite
def mutated_json(draw, base: dict) -> str:
    """The base object with a few values replaced or keys deleted, or its text cut or garbled."""
    data = json.loads(json.dumps(base))
    for _ in range(draw(st.integers(1, 3))):
        paths = [p for p in _paths(data) if p]
        if not paths:
            break
        path = draw(st.sampled_from(paths))
        node = data
        for k in path[:-1]:
            node = node[k]
        if draw(st.booleans()) and isinstance(node, dict):
            del node[path[-1]]
        else:
            node[path[-1]] = draw(json_values)
    text = json.dumps(data)
    cut = draw(st.sampled_from(["none", "truncate", "garble"]))
    if cut == "truncate":
        text = text[: draw(st.integers(0, len(text)))]
    elif cut == "garble":
        i = draw(st.integers(0, len(text)))
        text = text[:i] + draw(_text(4)) + text[i:]
    return text


@st.composite
def mutated_obj(draw) -> str:
    """The grid template with lines dropped, duplicated, truncated or with a token replaced."""
    lines = TEMPLATE_OBJ.splitlines()
    for _ in range(draw(st.integers(1, 4))):
        i = draw(st.integers(0, len(lines) - 1))
        kind = draw(st.sampled_from(["drop", "dup", "token", "cut", "insert"]))
        if kind == "drop" and len(lines) > 1:
            del lines[i]
        elif kind == "dup":
            lines.insert(i, lines[i])
        elif kind == "cut":
            lines[i] = lines[i][: draw(st.integers(0, len(lines[i])))]
        elif kind == "insert":
            lines.insert(i, draw(st.sampled_from(["v", "vt", "f", "v 1", "f 1 1 2 2", "vt 0.5", "f 1/1 2/2 3/3 4/4",
                                                  "v nan 0 1", "f 0 1 2 3", "f -1 -2 -3 -4", "g x", "#"])))
        else:
            tokens = lines[i].split() or [""]
            j = draw(st.integers(0, len(tokens) - 1))
            tokens[j] = draw(st.sampled_from(["0", "-1", "1e400", "nan", "x", "1/1/1", "//", "99", "3.5", ""]) | _text(4))
            lines[i] = " ".join(tokens)
    return "\n".join(lines) + "\n"


def _only_input_errors(fn) -> None:
    try:
        fn()
    except SaftInputError as exc:
        assert "\n" not in str(exc) and str(exc)


@pytest.fixture(scope="module")
def scene_parts(tmp_path_factory) -> Path:
    """rgb/, mask/, gt/ and template.obj of a valid 3-frame scene, copied into each example's folder."""
    folder = tmp_path_factory.mktemp("fuzz_parts")
    (folder / "template.obj").write_text(TEMPLATE_OBJ)
    for i in range(3):
        img = np.zeros((32, 40, 3), np.float32)
        img[8:24, 12:28] = 0.5
        write_image(folder / "rgb" / f"{i:03d}.png", img)
        write_image(folder / "mask" / f"{i:03d}.png", img[:, :, 0] > 0)
        (folder / "gt").mkdir(exist_ok=True)
        np.save(folder / "gt" / f"frame_{i:03d}.npy", np.zeros((5, 3)))
    return folder


def _scene_folder(parts: Path, tmp_path: Path) -> Path:
    folder = tmp_path / "scene"
    if not folder.exists():
        shutil.copytree(parts, folder)
        (folder / "camera.json").write_text(json.dumps(CAMERA))
    return folder


@FUZZ
@given(text=mutated_json(CAMERA))
def test_camera_json_mutations(tmp_path, text):
    path = tmp_path / "camera.json"
    path.write_text(text)
    _only_input_errors(lambda: read_camera_json(path))


SCENE_FILES = [("scene.json", NATIVE_META), ("R0.json", PHI_SFT)]   # native folder, SAFT/PG-SfT JSON


@settings(FUZZ, max_examples=80)
@given(case=st.sampled_from(SCENE_FILES).flatmap(lambda c: st.tuples(st.just(c[0]), mutated_json(c[1]))))
def test_scene_json_mutations(scene_parts, tmp_path, case):
    name, text = case
    folder = _scene_folder(scene_parts, tmp_path)
    (folder / name).write_text(text)
    _only_input_errors(lambda: load_scene(folder if name == "scene.json" else folder / name))


@FUZZ
@given(text=mutated_obj())
def test_obj_mutations(tmp_path, text):
    path = tmp_path / "template.obj"
    path.write_text(text)
    _only_input_errors(lambda: read_obj(path))


def test_unmutated_files_are_valid(scene_parts, tmp_path):
    folder = _scene_folder(scene_parts, tmp_path)
    (folder / "scene.json").write_text(json.dumps(NATIVE_META))
    (folder / "R0.json").write_text(json.dumps(PHI_SFT))
    assert load_scene(folder).num_frames == 3
    assert load_scene(folder / "R0.json").num_frames == 3
