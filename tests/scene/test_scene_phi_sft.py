import numpy as np
import pytest
from scipy.ndimage import distance_transform_edt

from saft.errors import SaftInputError
from saft.scene import load_scene
from saft.scene.camera import Crop


@pytest.fixture(scope="module")
def r1(phi_sft_dir):
    return load_scene(phi_sft_dir / "data" / "scenes" / "R1.json")


def test_r1_camera_and_crop(r1):
    assert (r1.camera.width, r1.camera.height) == (1920, 1080)
    assert r1.camera.fx == pytest.approx(971.522) and r1.camera.fy == pytest.approx(944.575)
    assert r1.camera.cx == pytest.approx(962.134) and r1.camera.cy == pytest.approx(554.778)
    assert np.allclose(r1.camera.world_to_camera, np.diag([-1.0, -1.0, 1.0, 1.0]))
    assert r1.crop == Crop(top=280, left=300, height=700, width=800)
    assert r1.num_frames == 50 and r1.template.num_vertices == 1024 and len(r1.template.quads) == 961
    assert r1.gravity is None and np.allclose(r1.gravity_or_default(), [0, -9.81, 0])   # none given
    assert r1.ground_truth_dir is not None and r1.ground_truth_frame == "camera"


def test_r1_template_projects_onto_frame0_mask(r1):
    uv, z = r1.camera.project(r1.template.vertices)
    assert (z > 0).all()
    # The README's numbers: rows 434–878, cols 418–851.
    assert 416 <= uv[:, 0].min() and uv[:, 0].max() <= 853
    assert 432 <= uv[:, 1].min() and uv[:, 1].max() <= 880
    # Pixel distance of every projected vertex to the mask: most land on it, boundary ones within a few px.
    dist = distance_transform_edt(r1.frames[0].mask < 0.5)
    px = np.round(uv).astype(int)
    d = dist[px[:, 1], px[:, 0]]
    assert (d == 0).mean() > 0.9 and d.max() < 10
    # the same through the crop, with the cropped camera
    uvc, _ = r1.working_camera().project(r1.template.vertices)
    dist_c = distance_transform_edt(r1.working_frames()[0].mask < 0.5)
    pxc = np.round(uvc).astype(int)
    assert np.allclose(dist_c[pxc[:, 1], pxc[:, 0]], d)


def test_explicit_root(phi_sft_dir, tmp_path):
    import shutil

    moved = tmp_path / "R1.json"
    shutil.copy(phi_sft_dir / "data" / "scenes" / "R1.json", moved)
    with pytest.raises(SaftInputError, match="code/"):
        load_scene(moved)
    s = load_scene(moved, root=phi_sft_dir)
    assert s.num_frames == 50
