"""Issue 14: every bad input ends in one line naming the file or key (exit 2), nothing is destroyed, resume
is checked; legitimate variants (0/1 masks, alpha masks) read exactly like the canonical input.

Reconstructions here are 1-2 epochs on the 40×32, 3-frame scene of conftest.native_scene.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import stat
import threading
import time
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest
import torch

from saft.cli import main
from saft.reconstruct.checkpoint import checkpoint_path
from saft.result import read_result
from saft.scene import load_scene

TINY = ["--device", "cpu", "--quiet", "--set", "texture.epochs=1", "--set", "texture.size=16",
        "--set", "shape.final_epochs=1", "--set", "appearance.enabled=false"]


def run(capsys, *argv):
    code = main([str(a) for a in argv])
    cap = capsys.readouterr()
    return code, cap.out, cap.err.strip()


def one_line_error(capsys, *argv, needles=()):
    """Run the CLI; assert exit 2 with a single stderr line containing every needle; return that line."""
    code, _, err = run(capsys, *argv)
    assert code == 2, err
    assert len(err.splitlines()) == 1 and "Traceback" not in err, err
    for n in needles:
        assert str(n) in err, err
    return err


def reconstruct_error(capsys, scene, out, *extra, needles=()):
    err = one_line_error(capsys, "reconstruct", scene, "--out", out, *TINY, *extra, needles=needles)
    return err


@pytest.fixture(scope="module")
def made_result(tmp_path_factory, native_scene_factory):
    """(scene folder, result folder) of one tiny reconstruction, made once; copy the result to change it."""
    root = tmp_path_factory.mktemp("made")
    scene = native_scene_factory(root / "scene")
    assert main(["reconstruct", str(scene), "--out", str(root / "result"), *TINY]) == 0
    return scene, root / "result"


@pytest.fixture
def result_copy(made_result, tmp_path):
    scene, result = made_result
    shutil.copytree(result, tmp_path / "result")
    return scene, tmp_path / "result"


def update_json(path: Path, **changes) -> Path:
    data = json.loads(path.read_text())
    data.update(changes)
    path.write_text(json.dumps(data))
    return path


def scene_meta(scene: Path, **changes) -> Path:
    return update_json(scene / "scene.json", **changes)


# ---------------------------------------------------------------------------------------------- masks
def test_zero_one_and_alpha_masks_read_like_0_255_masks(native_scene):
    canonical = load_scene(native_scene).frames.load()[1]
    for i in range(3):
        m = iio.imread(native_scene / "mask" / f"{i:03d}.png")
        iio.imwrite(native_scene / "mask" / f"{i:03d}.png", (m > 0).astype(np.uint8))      # 0/1
    assert np.array_equal(load_scene(native_scene).frames.load()[1], canonical)
    for i in range(3):
        m = iio.imread(native_scene / "mask" / f"{i:03d}.png")
        rgba = np.zeros(m.shape + (4,), np.uint8)
        rgba[..., 3] = m * 255                                                              # alpha only
        iio.imwrite(native_scene / "mask" / f"{i:03d}.png", rgba)
    assert np.array_equal(load_scene(native_scene).frames.load()[1], canonical)


def test_empty_mask_names_the_frame(native_scene, tmp_path, capsys):
    bad = native_scene / "mask" / "001.png"
    iio.imwrite(bad, np.zeros((32, 40), np.uint8))
    one_line_error(capsys, "inspect", native_scene, "--all-frames", needles=(bad, "frame 1", "empty"))
    reconstruct_error(capsys, native_scene, tmp_path / "out", needles=(bad, "empty"))
    assert not (tmp_path / "out").exists()
    iio.imwrite(native_scene / "mask" / "000.png", np.zeros((32, 40), np.uint8))   # frame 0: found on loading
    one_line_error(capsys, "inspect", native_scene, needles=(native_scene / "mask" / "000.png", "empty"))


def test_wrong_sized_first_rgb_frame_is_blamed(native_scene, capsys):
    bad = native_scene / "rgb" / "000.png"
    iio.imwrite(bad, np.full((30, 40, 3), 100, np.uint8))
    one_line_error(capsys, "inspect", native_scene, needles=(bad, "40x30", "40x32"))


def test_inspect_all_frames_finds_a_truncated_frame(native_scene, capsys):
    bad = native_scene / "rgb" / "002.png"
    data = bad.read_bytes()
    bad.write_bytes(data[: len(data) // 2])
    one_line_error(capsys, "inspect", native_scene, "--all-frames", needles=(bad,))


# ---------------------------------------------------------------------------------------------- camera
def _camera(scene: Path, **changes) -> Path:
    return update_json(scene / "camera.json", **changes)


def test_all_zero_K(native_scene, capsys):
    path = _camera(native_scene, K=np.zeros((3, 3)).tolist())
    err = one_line_error(capsys, "inspect", native_scene, needles=(path, "all zeros"))
    assert "skew" not in err


def test_principal_point_far_outside_the_image(native_scene, capsys):
    path = _camera(native_scene, K=[[40, 0, 400], [0, 40, 15.5], [0, 0, 1]])
    one_line_error(capsys, "inspect", native_scene, needles=(path, "principal point"))


def test_template_projecting_off_screen(native_scene, capsys):
    _camera(native_scene, K=[[40, 0, 55], [0, 40, 15.5], [0, 0, 1]])   # inside the bound, cloth at u = 47..63
    one_line_error(capsys, "inspect", native_scene, needles=(native_scene, "projects entirely outside"))


# ---------------------------------------------------------------------------------------------- scene.json
@pytest.mark.parametrize("changes, needle", [
    ({"frame_dt": 1e6}, "frame_dt"),
    ({"fps": 1e-6}, "frame_dt"),
    ({"pinned_vertices": [12.0, 13.5]}, "pinned_vertices"),
    ({"pinned_vertices": True}, "pinned_vertices"),
    ({"pinned_vertices": [True, 3]}, "pinned_vertices"),
    ({"crop": {"top": 10, "left": 10, "height": 2, "width": 2}}, "2x2"),
])
def test_implausible_scene_values(native_scene, capsys, changes, needle):
    meta = scene_meta(native_scene, **changes)
    if "frame_dt" in changes:
        data = json.loads(meta.read_text())
        data.pop("fps")
        meta.write_text(json.dumps(data))
    one_line_error(capsys, "inspect", native_scene, needles=(meta, needle))


# ---------------------------------------------------------------------------------------------- template
def _append(path: Path, line: str) -> Path:
    path.write_text(path.read_text() + line + "\n")
    return path


def test_obj_vertex_with_two_coordinates(native_scene, capsys):
    obj = _append(native_scene / "template.obj", "v 0.1 0.0")
    one_line_error(capsys, "inspect", native_scene, needles=(obj, "'v 0.1 0.0'"))


def test_degenerate_face_with_repeated_vertices(native_scene, capsys):
    obj = _append(native_scene / "template.obj", "f 1/1 1/1 2/2 2/2")
    one_line_error(capsys, "inspect", native_scene, needles=(obj, "face 10", "vertex twice"))


def test_zero_area_quad_is_found_before_any_phase(native_scene, tmp_path, capsys):
    obj = native_scene / "template.obj"
    lines = obj.read_text().splitlines()
    lines[1] = lines[0]      # vertex 2 on top of vertex 1: quad 1 has a zero-area triangle
    obj.write_text("\n".join(lines) + "\n")
    reconstruct_error(capsys, native_scene, tmp_path / "out", needles=(obj, "face 1", "zero area"))
    assert not (tmp_path / "out").exists()


# ---------------------------------------------------------------------------------------------- options and config
@pytest.mark.parametrize("argv, needle", [
    (["--frames", "0"], "--frames"),
    (["--frames", "-2"], "--frames"),
    (["--set", "texture.epochs=-1"], "texture.epochs"),
    (["--set", "shape.final_epochs=-5"], "shape.final_epochs"),
    (["--set", "render.scale=0"], "render.scale"),
    (["--set", "render.scale=0.01"], "render.scale"),
    (["--set", "shape.add_frame_every=0"], "shape.add_frame_every"),
    (["--set", "physics.damping=1.5"], "physics.damping"),
])
def test_out_of_range_options(native_scene, tmp_path, capsys, argv, needle):
    reconstruct_error(capsys, native_scene, tmp_path / "out", *argv, needles=(needle,))
    assert not (tmp_path / "out").exists()


def test_missing_ground_truth_is_found_before_the_reconstruction(native_scene, tmp_path, capsys):
    gt = tmp_path / "no-such-gt"
    reconstruct_error(capsys, native_scene, tmp_path / "out", "--gt", gt, needles=(gt, "not found"))
    assert not (tmp_path / "out").exists()


# ---------------------------------------------------------------------------------------------- --out safety
def test_out_is_a_file_or_under_a_file(native_scene, tmp_path, capsys):
    f = tmp_path / "file.txt"
    f.write_text("x")
    reconstruct_error(capsys, native_scene, f, needles=(f, "is a file"))
    reconstruct_error(capsys, native_scene, f / "sub", needles=(f, "is a file"))
    assert f.read_text() == "x"


def test_out_on_a_file_system_that_refuses_writing(native_scene, tmp_path, capsys):
    if os.geteuid() != 0:
        ro = tmp_path / "ro"
        ro.mkdir()
        ro.chmod(stat.S_IRUSR | stat.S_IXUSR)
        target = ro / "out"
    elif Path("/sys").is_dir():   # root may write anywhere except kernel file systems
        target = Path("/sys/saft-test-out")
    else:
        pytest.skip("no folder that refuses writing")
    reconstruct_error(capsys, native_scene, target, needles=(target, "cannot be"))


def test_out_that_is_or_contains_the_scene(native_scene, capsys):
    before = (native_scene / "scene.json").read_text()
    reconstruct_error(capsys, native_scene, native_scene, needles=(native_scene, "contains the scene"))
    reconstruct_error(capsys, native_scene, native_scene.parent, needles=("contains the scene",))
    assert (native_scene / "scene.json").read_text() == before
    assert not (native_scene / "config.toml").exists()


def test_non_empty_folder_that_is_no_result(native_scene, tmp_path, capsys):
    out = tmp_path / "mine"
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    reconstruct_error(capsys, native_scene, out, needles=(out, "not empty"))
    assert sorted(p.name for p in out.iterdir()) == ["notes.txt"]


def test_rerun_into_a_result_needs_overwrite_which_clears_stale_frames(result_copy, capsys):
    scene, out = result_copy
    assert (out / "meshes" / "frame_002.obj").is_file()
    reconstruct_error(capsys, scene, out, needles=(out, "--overwrite", "--resume"))
    code, _, err = run(capsys, "reconstruct", scene, "--out", out, *TINY, "--frames", "2", "--overwrite")
    assert code == 0, err
    assert not (out / "meshes" / "frame_002.obj").exists()
    assert read_result(out).num_frames == 2


# ---------------------------------------------------------------------------------------------- resume
def test_resume_refuses_another_config_or_scene(result_copy, capsys):
    scene, out = result_copy
    ckpt = checkpoint_path(out)
    reconstruct_error(capsys, scene, out, "--resume", "--set", "texture.lr=0.01",
                      needles=(ckpt, "texture.lr"))
    reconstruct_error(capsys, scene, out, "--resume", "--frames", "2", needles=(ckpt, "scene.frames"))
    scene_meta(scene, gravity=[0, 9.0, 0])
    try:
        reconstruct_error(capsys, scene, out, "--resume", needles=(ckpt, "scene.gravity"))
    finally:
        scene_meta(scene, gravity=[0, 9.81, 0])
    code, _, err = run(capsys, "reconstruct", scene, "--out", out, *TINY, "--resume",
                       "--set", "run.checkpoint_seconds=5")   # when to save does not change the result
    assert code == 0, err


@pytest.mark.parametrize("damage", ["truncate", "foreign", "incomplete"])
def test_damaged_checkpoint(result_copy, capsys, damage):
    scene, out = result_copy
    ckpt = checkpoint_path(out)
    if damage == "truncate":
        data = ckpt.read_bytes()
        ckpt.write_bytes(data[: len(data) // 2])
    elif damage == "foreign":
        torch.save([1, 2, 3], ckpt)
    else:
        state = torch.load(ckpt, weights_only=False)
        del state["positions"]
        torch.save(state, ckpt)
    reconstruct_error(capsys, scene, out, "--resume", needles=(ckpt,))


def test_interrupt_prints_the_resume_hint(native_scene, tmp_path, capsys):
    out = tmp_path / "out"

    def interrupt_once_a_checkpoint_exists():
        deadline = time.monotonic() + 120
        while not checkpoint_path(out).is_file() and time.monotonic() < deadline:
            time.sleep(0.01)
        os.kill(os.getpid(), signal.SIGINT)

    threading.Thread(target=interrupt_once_a_checkpoint_exists, daemon=True).start()
    code, _, err = run(capsys, "reconstruct", native_scene, "--out", out, *TINY, "--set", "texture.epochs=100000",
                       "--set", "run.checkpoint_seconds=0")
    assert code == 130
    assert len(err.splitlines()) == 1 and "continue with --resume" in err and str(out) in err, err


# ---------------------------------------------------------------------------------------------- readers of results
def test_readers_refuse_a_result_with_a_missing_frame(result_copy, tmp_path, capsys):
    scene, out = result_copy
    gone = out / "meshes" / "frame_001.obj"
    gone.unlink()
    gt = tmp_path / "gt"
    gt.mkdir()
    for i in range(3):
        np.save(gt / f"frame_{i:03d}.npy", np.random.default_rng(i).normal(size=(50, 3)))
    one_line_error(capsys, "report", out, needles=(gone, "missing"))
    one_line_error(capsys, "export", out, "--sequence", "obj", needles=(gone, "missing"))
    one_line_error(capsys, "evaluate", out, "--gt", gt, needles=(gone, "missing"))


@pytest.mark.parametrize("content", [None, "{\n", "42\n"])
def test_readers_refuse_a_result_without_proper_params(result_copy, capsys, content):
    _, out = result_copy
    params = out / "params.json"
    if content is None:
        params.unlink()
    else:
        params.write_text(content)
    one_line_error(capsys, "report", out, needles=(params,))
    one_line_error(capsys, "export", out, "--sequence", "obj", needles=(params,))


def test_evaluate_warns_in_one_line_without_python_source(result_copy, tmp_path, capsys):
    _, out = result_copy
    gt = tmp_path / "gt"
    gt.mkdir()
    for i in range(2):
        np.save(gt / f"frame_{i:03d}.npy", np.random.default_rng(i).normal(size=(50, 3)) * 0.1 + [0, 0, 1])
    code, stdout, err = run(capsys, "evaluate", out, "--gt", gt, "--allow-partial")
    assert code == 0, err
    text = stdout + err
    assert "evaluating the first 2" in text
    assert "UserWarning" not in text and "warnings.warn" not in text


# ---------------------------------------------------------------------------------------------- files and estimate
def test_result_files_respect_the_umask(made_result):
    _, out = made_result
    old = os.umask(0o022)
    os.umask(old)
    for name in ("config.toml", "params.json", "meshes/frame_000.obj", "texture.png", "checkpoint/state.pt"):
        mode = stat.S_IMODE((out / name).stat().st_mode)
        assert mode == 0o666 & ~old, (name, oct(mode))


def test_estimate_is_logged_before_the_first_epoch(native_scene, tmp_path, caplog, monkeypatch):
    from saft.reconstruct import estimate, reconstruct
    from saft.reconstruct.config import load_saft_config

    monkeypatch.setattr(estimate, "LARGE_TEMPLATE", 10)   # the 16-vertex template counts as large here
    cfg = load_saft_config(None, TINY[4::2] + ['run.device="cpu"'])
    with caplog.at_level("INFO", logger="saft"):
        reconstruct(load_scene(native_scene), cfg, tmp_path / "out", quiet=True)
    messages = [r.getMessage() for r in caplog.records]
    first_phase = next(i for i, m in enumerate(messages) if m.startswith("phase "))
    est = next(i for i, m in enumerate(messages) if m.startswith("estimate: "))
    assert est < first_phase and " MB" in messages[est]
    assert any(m.startswith("large template: 16 vertices") for m in messages)


def test_estimate_leaves_out_one_off_first_call_costs(native_scene, tmp_path, caplog, monkeypatch):
    # the first rollout of a process compiles (or loads) the numba kernels: seconds that do not recur and
    # must not be multiplied by every substep of the run (R1 was estimated at 4.3 h for a 10-minute run)
    import time as _time

    from saft.reconstruct import estimate, reconstruct
    from saft.reconstruct.config import load_saft_config

    calls = []
    real = estimate.rollout

    def slow_first(*args, **kw):
        if not calls:
            _time.sleep(1.0)
        calls.append(1)
        return real(*args, **kw)

    monkeypatch.setattr(estimate, "rollout", slow_first)
    seen = {}
    real_measure = estimate.measure_run
    monkeypatch.setattr(estimate, "measure_run", lambda *a, **k: seen.setdefault("est", real_measure(*a, **k)))
    cfg = load_saft_config(None, TINY[4::2] + ['run.device="cpu"'])
    reconstruct(load_scene(native_scene), cfg, tmp_path / "out", quiet=True)
    assert len(calls) >= 2 and seen["est"].transition_seconds < 0.5


def test_estimate_times_a_substep_that_reuses_the_factor(native_scene, tmp_path, monkeypatch):
    # the run's substeps reuse factors kept across epochs: the timed substep must not factorise afresh
    from saft.reconstruct import estimate, reconstruct
    from saft.reconstruct.config import load_saft_config

    stats = []
    real = estimate.rollout

    def counted(*args, **kw):
        stats.append({})
        return real(*args, stats=stats[-1], **kw)

    monkeypatch.setattr(estimate, "rollout", counted)
    cfg = load_saft_config(None, TINY[4::2] + ['run.device="cpu"'])
    reconstruct(load_scene(native_scene), cfg, tmp_path / "out", quiet=True)
    assert len(stats) == 2 and stats[0]["factorizations"] >= 1 and stats[1]["factorizations"] == 0, stats


def test_appearance_interrupt_keeps_every_finished_epoch(native_scene, tmp_path, capsys):
    from saft.reconstruct import reconstruct
    from saft.reconstruct.checkpoint import load_checkpoint
    from saft.reconstruct.config import load_saft_config

    cfg = load_saft_config(None, TINY[4:9:2] + ['run.device="cpu"', "appearance.epochs=6", "appearance.render_spp=2",
                                                "appearance.frames_per_epoch=2", "appearance.checkpoint_every=25"])
    scene, out = load_scene(native_scene), tmp_path / "out"

    def stop(phase, epochs_done):
        return phase == "appearance" and epochs_done == 4

    with pytest.raises(KeyboardInterrupt, match="continue with --resume"):
        reconstruct(scene, cfg, out, quiet=True, on_epoch=stop)
    saved = load_checkpoint(out)
    assert saved["phase"] == "appearance" and saved["appearance_state"]["epoch"] == 4   # not 0: nothing lost
    reconstruct(scene, cfg, out, resume=True, quiet=True)
    epochs = [int(r["epoch"]) for r in read_result(out).log_rows if r["phase"] == "appearance"]
    assert epochs == list(range(6))          # each appearance epoch ran exactly once
