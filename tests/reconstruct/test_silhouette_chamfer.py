"""The chamfer silhouette term: distance maps of the target masks, the mesh border, long-range pulls."""

import numpy as np
import torch

from saft.reconstruct.silhouette_chamfer import (boundary_edges, chamfer_loss, mask_distances,
                                                 point_segment_distance)
from saft.reconstruct.tracks import project
from saft.scene.camera import look_at


def _grid(n: int = 6, size: float = 0.4):
    s = np.linspace(-size / 2, size / 2, n)
    xx, yy = np.meshgrid(s, s)
    verts = np.stack([xx.ravel(), yy.ravel(), np.zeros(n * n)], axis=1)
    tris = []
    for r in range(n - 1):
        for c in range(n - 1):
            a, b, d, e = r * n + c, r * n + c + 1, (r + 1) * n + c, (r + 1) * n + c + 1
            tris += [[a, b, e], [a, e, d]]
    return torch.as_tensor(verts), np.asarray(tris)


def _camera():
    K = np.array([[160.0, 0, 64], [0, 160.0, 48], [0, 0, 1]])
    return look_at((0.0, 0.0, 1.0), (0, 0, 0), (0, 1, 0), K, 128, 96)


def _mask_of(verts: torch.Tensor, tris: np.ndarray, cam) -> np.ndarray:
    import cv2
    uv, _ = project(verts, cam)
    mask = np.zeros((cam.height, cam.width), np.uint8)
    for t in tris:
        cv2.fillConvexPoly(mask, np.rint(uv[t].numpy()).astype(np.int32), 1)
    return mask.astype(np.float32)


def test_boundary_edges_are_the_border_of_a_grid():
    _, tris = _grid(4)
    edges = boundary_edges(tris)
    assert len(edges) == 4 * 3
    border = {0, 1, 2, 3, 4, 7, 8, 11, 12, 13, 14, 15}
    assert set(edges.ravel().tolist()) == border


def test_point_segment_distance():
    a = torch.tensor([[0.0, 0.0]])
    b = torch.tensor([[10.0, 0.0]])
    p = torch.tensor([[5.0, 3.0], [-4.0, 3.0], [12.0, 0.0]])
    assert torch.allclose(point_segment_distance(p, a, b)[:, 0], torch.tensor([3.0, 5.0, 2.0]))


def test_chamfer_is_lowest_on_the_target_and_pulls_from_afar():
    verts, tris = _grid()
    cam = _camera()
    mask = _mask_of(verts, tris, cam)[None]
    dists = mask_distances(mask)
    edges = torch.as_tensor(boundary_edges(tris))
    at_truth = float(sum(chamfer_loss(verts[None], dists, edges, cam, huber_delta=3.0)))
    grads = {}
    for shift in (0.02, 0.08):                        # about 3 and 13 px to the right
        offset = torch.tensor([shift, 0.0, 0.0], dtype=torch.float64, requires_grad=True)
        outside, cover = chamfer_loss((verts + offset)[None], dists, edges, cam, huber_delta=3.0)
        assert float(outside.detach()) > 0 and float(cover.detach()) > 0
        loss = outside + cover
        loss.backward()
        assert float(loss.detach()) > 5 * at_truth
        grads[shift] = float(offset.grad[0])
    # both pull back to the left, and the far one no less than the near one (no flat region)
    assert grads[0.02] > 0 and grads[0.08] >= 0.9 * grads[0.02]


def test_chamfer_sees_a_cloth_smaller_than_the_mask():
    verts, tris = _grid()
    cam = _camera()
    dists = mask_distances(_mask_of(verts, tris, cam)[None])
    edges = torch.as_tensor(boundary_edges(tris))
    scale = torch.tensor(0.6, dtype=torch.float64, requires_grad=True)
    outside, cover = chamfer_loss((verts * scale)[None], dists, edges, cam, huber_delta=3.0)
    assert float(outside.detach()) == 0.0             # every vertex on the mask: only the contour sees it
    cover.backward()
    assert float(scale.grad) < 0                      # the shrunken cloth inside the mask is pulled outwards
    _, off = chamfer_loss((verts * scale)[None], dists, edges, cam, huber_delta=3.0, cover=False)
    assert float(off.detach()) == 0.0


def test_a_reconstruction_with_the_chamfer_term_and_soft_track_confidence_runs(tiny_reconstruction):
    import csv

    out = tiny_reconstruction(["shape.lambda_chamfer=1e3", "shape.lambda_chamfer_cover=1e3",
                               "shape.track_drift_scale=0.03"])
    with open(out / "log.csv", newline="") as fh:
        rows = [r for r in csv.DictReader(fh) if r["phase"] == "shape"]
    assert rows and all(float(r["chamfer"]) > 0 for r in rows)
