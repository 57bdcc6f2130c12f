"""glTF export: re-read the .glb, rebuild every frame from base + morph deltas, compare with the result."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pygltflib
import pytest

from saft.errors import SaftInputError
from saft.export import export_command
from saft.export.gltf import read_glb_frames, write_glb
from saft.result import read_result


def test_glb_frames_match_result(result_dir, tmp_path):
    res = read_result(result_dir)
    out = export_command(result_dir, gltf=tmp_path / "cloth.glb")
    assert out == [tmp_path / "cloth.glb"]
    times, verts, tris, uvs = read_glb_frames(out[0])
    assert verts.shape == res.vertices.shape
    np.testing.assert_allclose(times, np.arange(res.num_frames) * res.frame_dt, atol=1e-7)
    for i in range(res.num_frames):  # every frame, base + weights · deltas at its keyframe
        assert np.abs(verts[i].astype(np.float64) - res.vertices[i]).max() < 1e-6, f"frame {i}"
    np.testing.assert_array_equal(tris, res.template.triangles)
    np.testing.assert_allclose(uvs[:, 0], res.template.uvs[:, 0], atol=1e-7)
    np.testing.assert_allclose(uvs[:, 1], 1.0 - res.template.uvs[:, 1], atol=1e-7)  # glTF: V from the top


def test_glb_document_structure(result_dir, tmp_path):
    res = read_result(result_dir)
    path = write_glb(res, tmp_path / "cloth.glb")
    doc = pygltflib.GLTF2().load_binary(str(path))
    assert doc.asset.version == "2.0"
    prim = doc.meshes[0].primitives[0]
    assert len(prim.targets) == res.num_frames
    assert doc.meshes[0].extras["targetNames"][0] == "frame_000"
    anim = doc.animations[0]
    assert anim.channels[0].target.path == "weights" and anim.samplers[0].interpolation == "LINEAR"
    mat = doc.materials[0]
    assert mat.doubleSided is True
    pbr = mat.pbrMetallicRoughness
    assert pbr.baseColorTexture is not None and pbr.metallicRoughnessTexture is not None
    blob = doc.binary_blob()
    # textures are embedded PNGs: decode the metallic-roughness one and check its packing (G rough, B metal)
    import io

    from PIL import Image

    mr_img = doc.images[doc.textures[pbr.metallicRoughnessTexture.index].source]
    view = doc.bufferViews[mr_img.bufferView]
    mr = np.asarray(Image.open(io.BytesIO(blob[view.byteOffset:view.byteOffset + view.byteLength])))
    assert abs(mr[..., 1].mean() / 255 - 0.7) < 0.01
    assert mr[0, 0, 2] < 5 and mr[-1, -1, 2] > 250
    base_img = doc.images[doc.textures[pbr.baseColorTexture.index].source]
    assert base_img.mimeType == "image/png" and base_img.uri is None
    # the root node turns "up" (opposite gravity +y here) into glTF +Y: a half turn about x or z
    from scipy.spatial.transform import Rotation

    R = Rotation.from_quat(doc.nodes[0].rotation).as_matrix()
    np.testing.assert_allclose(R @ np.array([0.0, -1.0, 0.0]), [0.0, 1.0, 0.0], atol=1e-9)
    assert doc.cameras and doc.cameras[0].perspective.aspectRatio == pytest.approx(64 / 48)
    assert doc.extras["saft"]["frame_dt"] == pytest.approx(res.frame_dt)


def test_glb_without_material_uses_texture(bare_result_dir, tmp_path):
    path = write_glb(bare_result_dir, tmp_path / "bare.glb", interpolation="STEP")
    doc = pygltflib.GLTF2().load_binary(str(path))
    pbr = doc.materials[0].pbrMetallicRoughness
    assert pbr.baseColorTexture is not None and pbr.metallicRoughnessTexture is None
    assert pbr.metallicFactor == 0.0
    assert doc.extras["saft"]["material"]["baseColor"] == "texture.png"
    assert doc.animations[0].samplers[0].interpolation == "STEP"


def test_glb_bad_name(result_dir, tmp_path):
    with pytest.raises(SaftInputError, match=r"\.glb"):
        export_command(result_dir, gltf=tmp_path / "cloth.gltf")


def _validator_dir() -> Path | None:
    """The gltf-validator npm package: $SAFT_GLTF_VALIDATOR, else the global npm root."""
    if shutil.which("node") is None:
        return None
    env = os.environ.get("SAFT_GLTF_VALIDATOR")
    cands = [Path(env)] if env else []
    if shutil.which("npm"):
        try:
            root = subprocess.run(["npm", "root", "-g"], capture_output=True, text=True, timeout=30).stdout.strip()
            cands.append(Path(root) / "gltf-validator")
        except (OSError, subprocess.TimeoutExpired):
            pass
    return next((c for c in cands if (c / "package.json").is_file()), None)


_VALIDATE_JS = """
const fs = require('fs'); const v = require(process.argv[2]);
v.validateBytes(new Uint8Array(fs.readFileSync(process.argv[3])), {maxIssues: 50})
  .then(r => console.log(JSON.stringify(r.issues)))
  .catch(e => { console.error(String(e)); process.exit(3); });
"""


@pytest.mark.parametrize("which", ["result_dir", "bare_result_dir"])
def test_glb_passes_khronos_validator(which, request, tmp_path):
    pkg = _validator_dir()
    if pkg is None:
        pytest.skip("Khronos glTF validator not available: needs node and `npm install -g gltf-validator` "
                    "(or SAFT_GLTF_VALIDATOR=path/to/node_modules/gltf-validator)")
    path = write_glb(request.getfixturevalue(which), tmp_path / "cloth.glb")
    script = tmp_path / "validate.js"
    script.write_text(_VALIDATE_JS)
    run = subprocess.run(["node", str(script), str(pkg), str(path)], capture_output=True, text=True, timeout=60)
    assert run.returncode == 0, run.stderr
    issues = json.loads(run.stdout)
    assert issues["numErrors"] == 0 and issues["numWarnings"] == 0, issues["messages"]
