"""Each kind of bad input ends with one line naming the file and the problem, exit code 2, no traceback."""

import json
import shutil

import numpy as np
import pytest

from saft.cli import main


def write_image(path, img):
    import imageio.v3 as iio

    iio.imwrite(path, img)


def run(capsys, *argv):
    code = main(list(argv))
    out = capsys.readouterr()
    return code, out.err.strip()


def expect_error(capsys, scene, needle_path, needle_text, all_frames=False):
    args = ["inspect", str(scene)] + (["--all-frames"] if all_frames else [])
    code, err = run(capsys, *args)
    assert code == 2, err
    assert len(err.splitlines()) == 1, err
    assert "Traceback" not in err
    assert str(needle_path) in err, err
    assert needle_text in err, err


def test_valid_scene_inspects(native_scene, capsys):
    code = main(["inspect", str(native_scene), "--all-frames"])
    out = capsys.readouterr().out
    assert code == 0 and "3 frames of 40x32" in out and "16 vertices, 9 quads" in out


def test_missing_template(native_scene, capsys):
    (native_scene / "template.obj").unlink()
    expect_error(capsys, native_scene, native_scene / "template.obj", "not found")


def test_missing_rgb_folder(native_scene, capsys):
    shutil.rmtree(native_scene / "rgb")
    expect_error(capsys, native_scene, native_scene / "rgb", "folder not found")


def test_missing_camera(native_scene, capsys):
    (native_scene / "camera.json").unlink()
    expect_error(capsys, native_scene, native_scene / "camera.json", "not found")


def test_frame_counts_differ(native_scene, capsys):
    (native_scene / "mask" / "002.png").unlink()
    expect_error(capsys, native_scene, native_scene / "mask", "2 masks but")


def test_images_of_different_sizes(native_scene, capsys):
    write_image(native_scene / "rgb" / "001.png", np.zeros((30, 40, 3), np.uint8))
    expect_error(capsys, native_scene, native_scene / "rgb" / "001.png", "40x30")


def test_non_quad_faces(native_scene, capsys):
    obj = native_scene / "template.obj"
    obj.write_text(obj.read_text() + "f 1/1 2/2 5/5\n")
    expect_error(capsys, native_scene, obj, "pure quad mesh")


def test_template_without_uvs(native_scene, capsys):
    obj = native_scene / "template.obj"
    kept = []
    for line in obj.read_text().splitlines():
        if line.startswith("vt "):
            continue
        if line.startswith("f "):
            line = "f " + " ".join(c.split("/")[0] for c in line.split()[1:])
        kept.append(line)
    obj.write_text("\n".join(kept) + "\n")
    expect_error(capsys, native_scene, obj, "texture coordinates")


def test_non_rotation_world_to_camera(native_scene, capsys):
    cam_path = native_scene / "camera.json"
    cam = json.loads(cam_path.read_text())
    cam["world_to_camera"] = (np.diag([2.0, 1.0, 1.0, 1.0])).tolist()
    cam_path.write_text(json.dumps(cam))
    expect_error(capsys, native_scene, cam_path, "not a rigid transform")


def test_pinned_out_of_range(native_scene, capsys):
    meta = native_scene / "scene.json"
    meta.write_text(json.dumps({"pinned_vertices": [0, 99]}))
    expect_error(capsys, native_scene, meta, "pinned vertex index 99 is out of range")


def test_unreadable_image(native_scene, capsys):
    bad = native_scene / "rgb" / "001.png"
    bad.write_bytes(b"this is not a png")
    expect_error(capsys, native_scene, bad, "cannot decode")


def test_bad_json(native_scene, capsys):
    (native_scene / "camera.json").write_text("{not json")
    expect_error(capsys, native_scene, native_scene / "camera.json", "not valid JSON")


def test_debug_shows_traceback(native_scene):
    (native_scene / "template.obj").unlink()
    from saft.errors import SaftInputError

    with pytest.raises(SaftInputError):
        main(["inspect", str(native_scene), "--debug"])
