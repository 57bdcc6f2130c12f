"""OpenCV camera → Mitsuba sensor: rays and rendered pixels agree with Camera.project (crop included)."""

import numpy as np
import pytest

from saft.appearance.mitsuba_backend import load_mitsuba
from saft.appearance.renderer import ClothRenderer, mitsuba_sensor_dict
from saft.scene.camera import Crop, look_at


def _camera(W=80, H=60, f=90.0, cx=None, cy=None):
    cx = (W - 1) / 2 if cx is None else cx
    cy = (H - 1) / 2 if cy is None else cy
    K = np.array([[f, 0, cx], [0, f, cy], [0, 0, 1.0]])
    return look_at([0.4, 0.3, -2.0], [0.0, 0.0, 0.0], [0, 1, 0], K, W, H)


@pytest.mark.parametrize("crop", [None, Crop(top=7, left=19, height=40, width=50)])
def test_sensor_rays_match_projection(crop):
    mi = load_mitsuba("cpu")
    cam = _camera(cx=47.3, cy=21.8)
    if crop is not None:
        cam = cam.cropped(crop)
    sensor = mi.load_dict(mitsuba_sensor_dict(cam, mi))
    rng = np.random.default_rng(0)
    pts = rng.uniform(-0.4, 0.4, size=(20, 3))
    uv, z = cam.project(pts)
    assert (z > 0).all()
    pos = mi.Point2f((uv[:, 0] + 0.5) / cam.width, (uv[:, 1] + 0.5) / cam.height)
    ray, _ = sensor.sample_ray(0.0, 0.5, pos, mi.Point2f(0.5, 0.5))
    d = np.array(ray.d).T
    o = np.array(ray.o).T
    want = pts - cam.center
    want /= np.linalg.norm(want, axis=1, keepdims=True)
    assert np.abs(o - cam.center).max() < 3e-3  # Mitsuba starts rays at the near clip plane (1e-3)
    assert np.abs(d - want).max() < 1e-5


def _tiny_square(center, half):
    c = np.asarray(center, float)
    v = c + np.array([[-half, -half, 0], [half, -half, 0], [half, half, 0], [-half, half, 0]])
    tri = np.array([[0, 1, 2], [0, 2, 3]])
    uv = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], float)
    return v, tri, uv


def test_rendered_vertex_lands_on_projected_pixel():
    # a small square seen through a cropped camera with an off-centre principal point: the centroid of the
    # rendered pixels must coincide with the projection of its centre (and row 0 is the top of the image)
    cam = _camera(W=96, H=72, f=110.0, cx=40.2, cy=44.7).cropped(Crop(top=10, left=14, height=56, width=64))
    centre = np.array([0.12, -0.06, 0.0])
    v, tri, uv = _tiny_square(centre, 0.05)
    r = ClothRenderer(tri, uv, cam, map_shape=(4, 4), env_shape=(16, 32))
    r.set_vertices(v)
    img = r.render_numpy(np.ones((4, 4, 3)), np.ones((4, 4)), np.zeros((4, 4)), np.ones((16, 32, 3)), spp=16)
    w = img.sum(axis=2)
    assert w.max() > 0
    ii, jj = np.nonzero(w > 0.5 * w.max())
    uv_c, _ = cam.project(centre[None])
    u, vv = uv_c[0]
    # far from the image centre in both axes, so a flipped image (row 0 = bottom) would fail
    assert abs(vv - (cam.height - 1) / 2) > 5 and abs(u - (cam.width - 1) / 2) > 5
    assert abs(jj.mean() - u) < 0.6 and abs(ii.mean() - vv) < 0.6


def test_non_square_pixels_are_resampled_not_refused():
    """R1's camera has fx/fy = 1.029: the fit works on images resampled to square pixels, and
    re-renders come back on the camera's own grid, with the cloth where Camera.project puts it."""
    from saft.appearance.fit import _square_pixels
    from saft.scene.camera import Camera

    K = np.array([[971.522, 0, 962.134], [0, 944.575, 554.778], [0, 0, 1]])
    cam = Camera(K, np.diag([-1.0, -1.0, 1.0, 1.0]), 1920, 1080)
    sq = _square_pixels(cam)
    assert sq.fx == pytest.approx(sq.fy, rel=1e-3) and sq.width == 1920 and sq.height == 1111
    pts = np.array([[0.1, 0.2, 1.3], [-0.3, -0.1, 1.2]])
    uv, _ = cam.project(pts)
    uv_sq, _ = sq.project(pts)
    assert np.allclose(uv_sq[:, 0], uv[:, 0], atol=0.5)
    assert np.allclose((uv_sq[:, 1] + 0.5) * cam.height / sq.height - 0.5, uv[:, 1], atol=0.5)
