"""OBJ / PLY sequence export: one file per frame, read back and compared with the result."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from saft.errors import SaftInputError
from saft.export import export_command
from saft.result import read_result
from saft.scene.mesh import read_obj


def test_obj_sequence(result_dir, tmp_path):
    res = read_result(result_dir)
    written = export_command(result_dir, sequence="obj", out_dir=tmp_path / "out")
    folder = tmp_path / "out" / "obj"
    objs = sorted(folder.glob("frame_*.obj"))
    assert len(objs) == res.num_frames and set(objs) <= set(written)
    assert (folder / "cloth.mtl").read_text().strip().endswith("map_Kd texture.png")
    # the appearance phase's diffuse map wins over the phase-1 texture
    assert (folder / "texture.png").read_bytes() == (result_dir / "material" / "diffuse.png").read_bytes()
    for i, p in enumerate(objs):
        m = read_obj(p)
        assert np.abs(m.vertices - res.vertices[i]).max() < 1e-6
        np.testing.assert_array_equal(m.quads, res.template.quads)
        np.testing.assert_allclose(m.uvs, res.template.uvs, atol=1e-6)
    tm = trimesh.load(objs[0], process=False)  # another reader finds the texture through the .mtl
    assert tm.visual.material.image is not None


def test_ply_sequence(bare_result_dir, tmp_path):
    res = read_result(bare_result_dir)
    export_command(bare_result_dir, sequence="ply")  # default OUT_DIR = DIR/export
    plys = sorted((bare_result_dir / "export" / "ply").glob("frame_*.ply"))
    assert len(plys) == res.num_frames
    for i, p in enumerate(plys):
        m = trimesh.load(p, process=False)
        assert len(m.faces) == 2 * len(res.template.quads)  # quads, triangulated by trimesh
        assert np.abs(m.vertices - res.vertices[i]).max() < 1e-6
        np.testing.assert_allclose(m.visual.uv, res.template.uvs, atol=1e-6)
    head = plys[0].read_bytes()[:400]
    assert b"property list uchar int vertex_indices" in head and b"property float s" in head


def test_bad_sequence_and_nothing_to_do(result_dir):
    with pytest.raises(SaftInputError, match="obj or ply"):
        export_command(result_dir, sequence="stl")
    with pytest.raises(SaftInputError, match="nothing to export"):
        export_command(result_dir)
    with pytest.raises(SaftInputError, match="result folder not found"):
        export_command(result_dir / "missing", sequence="obj")
