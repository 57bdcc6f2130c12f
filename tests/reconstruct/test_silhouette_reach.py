"""The silhouette pull that grows with the gap to the mask's border (saft.reconstruct.silhouette_reach):
distances, weights, the memo, the weighted loss, the gradient on a rendered edge, the config."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from saft.reconstruct.losses import silhouette_loss
from saft.reconstruct.silhouette_reach import (inside_distance, reach_distances, reach_px, reach_weights,
                                               silhouette_weights)
from saft.render import render_cloth
from saft.scene.camera import Camera


def test_inside_distance_of_a_square():
    m = np.zeros((9, 9))
    m[2:7, 2:7] = 1.0
    d = inside_distance(m, cap=100.0)
    assert d[4, 4] == 3.0          # the centre: 3 pixels to the first off-mask pixel
    assert d[2, 4] == 1.0 and d[3, 3] == 2.0
    assert (d[m == 0] == 0).all()
    assert inside_distance(m, cap=1.5)[4, 4] == 1.5


def test_inside_distance_counts_the_image_outside_as_off_the_mask():
    d = inside_distance(np.ones((5, 7)), cap=100.0)
    assert d[0, 3] == 1.0 and d[2, 0] == 1.0 and d[2, 3] == 3.0


def test_reach_weights_are_one_off_the_mask_and_saturate_at_the_reach():
    d = torch.tensor([0, 2, 4, 8, 20], dtype=torch.uint8)
    w = reach_weights(d, reach_px=8.0, gain=16.0)
    assert torch.allclose(w, torch.tensor([1.0, 2.0, 5.0, 17.0, 17.0]))


def test_off_gives_none_and_the_distances_are_memoised():
    mask = torch.zeros(3, 12, 12)
    mask[:, 3:9, 2:10] = 1.0
    assert silhouette_weights(mask, 0, 3, 0.0, 16.0) is None
    assert silhouette_weights(mask, 0, 3, 4.0, 0.0) is None
    w = silhouette_weights(mask, 1, 3, 4.0, 16.0)
    assert w.shape == (2, 12, 12) and w.dtype == mask.dtype
    assert (w[mask[1:] == 0] == 1).all() and w.max() == 10.0   # 6 rows: at most 3 px inside
    assert reach_distances(mask, 4.0) is reach_distances(mask, 4.0)
    assert int(reach_distances(mask, 2.0).max()) == 2   # another reach: computed again
    other = mask.clone()
    assert reach_distances(other, 4.0) is not reach_distances(mask, 4.0)


def test_weighted_silhouette_loss():
    g = torch.Generator().manual_seed(0)
    m, t = torch.rand(2, 5, 6, generator=g), (torch.rand(2, 5, 6, generator=g) > 0.5).float()
    assert silhouette_loss(m, t) == F.mse_loss(m, t)
    assert torch.allclose(silhouette_loss(m, t, torch.ones_like(m)), F.mse_loss(m, t))
    w = 1.0 + 3.0 * t
    assert torch.allclose(silhouette_loss(m, t, w), (w * (m - t) ** 2).mean())


def _camera(size=64, f=80.0):
    K = np.array([[f, 0, (size - 1) / 2], [0, f, (size - 1) / 2], [0, 0, 1.0]])
    return Camera(K, np.eye(4), size, size)


def _sheet():
    """A 3 × 3-vertex square sheet facing the camera at z = 1, about 32 px wide, its left edge 0.3 px left
    of the midpoint between two pixel centres (on the midpoint the antialiasing blends the covered pixel,
    whose residual is 0 here, and the plain term has no gradient at all)."""
    xs = np.linspace(-0.2, 0.2, 3)
    X, Y = np.meshgrid(xs - 0.3 / 80.0, xs)
    v = np.stack([X.ravel(), Y.ravel(), np.ones(9)], axis=1)
    tris = np.array([[i * 3 + j, i * 3 + j + 1, i * 3 + j + 4] for i in range(2) for j in range(2)]
                    + [[i * 3 + j, i * 3 + j + 4, i * 3 + j + 3] for i in range(2) for j in range(2)])
    uvs = np.stack([(X.ravel() - X.min()) / 0.4, (Y.ravel() + 0.2) / 0.4], axis=1)
    return v, tris, uvs


def _left_edge_grad(gap_px: int, reach: float, gain: float) -> float:
    """x-gradient (summed over the left column's vertices) of the silhouette loss of the sheet against a
    mask that reaches `gap_px` pixels beyond the sheet's left edge."""
    cam = _camera()
    v, tris, uvs = _sheet()
    verts = torch.tensor(v, dtype=torch.float32, requires_grad=True)
    tex = torch.full((4, 4, 3), 0.5)
    out = render_cloth(verts[None], torch.as_tensor(tris, dtype=torch.int32), torch.as_tensor(uvs, dtype=torch.float32),
                       tex, cam)
    covered = (out.mask.detach() > 0.5)[0]
    cols = torch.nonzero(covered.any(dim=0))[:, 0]
    target = covered.clone()
    target[:, int(cols.min()) - gap_px:int(cols.min())] = covered[:, int(cols.min()):int(cols.min()) + 1]
    target = target.float()[None]
    w = silhouette_weights(target, 0, 1, reach, gain)
    silhouette_loss(out.mask, target, w).backward()
    return float(verts.grad[[0, 3, 6], 0].sum())


def test_the_pull_on_a_short_edge_points_outwards_and_grows_with_the_gap():
    plain_near, plain_far = _left_edge_grad(2, 0.0, 16.0), _left_edge_grad(10, 0.0, 16.0)
    reach_near, reach_far = _left_edge_grad(2, 12.0, 16.0), _left_edge_grad(10, 12.0, 16.0)
    # a positive x-gradient: descent moves the left edge to -x, out towards the mask's border
    assert plain_near > 0 and plain_far > 0 and reach_near > 0 and reach_far > 0
    assert plain_far == pytest.approx(plain_near, rel=0.05)   # the coverage MSE: the same pull at any gap
    assert reach_far > 5.0 * plain_far                        # here it grows with the gap
    assert reach_near < 1.5 * plain_near                      # and stays near 1x for a small one


def test_the_reach_acts_only_where_the_scene_pins_vertices():
    from saft.reconstruct.config import ShapeConfig

    cfg = ShapeConfig(sil_reach_px=24.0)
    assert reach_px(cfg, None) == 0.0 and reach_px(cfg, torch.zeros(0, dtype=torch.long)) == 0.0
    assert reach_px(cfg, torch.tensor([0, 5])) == 24.0
    assert reach_px(ShapeConfig(sil_reach_px=0.0), torch.tensor([0])) == 0.0


def test_config_range_checked():
    from saft.errors import SaftInputError
    from saft.reconstruct.config import load_saft_config

    assert load_saft_config(None, ["shape.sil_reach_px=12"]).shape.sil_reach_px == 12.0
    with pytest.raises(SaftInputError, match="shape.sil_reach_px must lie in"):
        load_saft_config(None, ["shape.sil_reach_px=-1"])
    with pytest.raises(SaftInputError, match="shape.sil_reach_px must lie in"):
        load_saft_config(None, ["shape.sil_reach_px=300"])
    with pytest.raises(SaftInputError, match="shape.sil_reach_gain must lie in"):
        load_saft_config(None, ["shape.sil_reach_gain=-2"])


def test_a_pinned_reconstruction_moves_with_it(tiny_reconstruction):
    import shutil

    from saft.result import read_result

    out = tiny_reconstruction(["shape.sil_reach_px=0"])
    off = read_result(out).vertices.copy()
    shutil.rmtree(out)
    on = read_result(tiny_reconstruction(["shape.sil_reach_px=6"])).vertices
    assert on.shape == off.shape and not np.allclose(on, off)   # the hanging cloth is pinned: the term acts
