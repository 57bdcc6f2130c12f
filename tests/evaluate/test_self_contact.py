"""saft.evaluate.self_contact on a folded sheet: a clean fold, and the same fold with its flap pushed through."""

import numpy as np

from saft.evaluate.self_contact import crossing_triangles, far_pairs, layered, min_gap, side
from saft.synthetic.hanging_cloth import grid_template

N, SIZE = 25, 0.4          # the benchmark scenes' template
H = SIZE / (N - 1)


def _sheet():
    g = grid_template(N, SIZE)
    return np.asarray(g.vertices, dtype=np.float64), np.asarray(g.triangles)


def _fold(rest: np.ndarray, gap: float) -> np.ndarray:
    """The lower half folded up in front of the upper half (+z) around a half-cylinder of diameter `gap`."""
    p = rest.copy()
    low = rest[:, 1] < 0
    s, r = -rest[low, 1], gap / 2
    th = np.minimum(s / r, np.pi)
    p[low, 1] = np.where(s <= np.pi * r, -r * np.sin(th), s - np.pi * r)
    p[low, 2] = r - r * np.cos(th)
    return p


def test_flat_sheet_has_no_contact():
    rest, tri = _sheet()
    assert crossing_triangles(rest, tri) == 0
    assert len(far_pairs(rest, rest, 0.01, 2.5 * H)) == 0
    assert not layered(rest, rest, 0.01, 2.5 * H).any()
    assert min_gap(rest, rest, 6 * H) == 0.05         # none within the 5 cm reach


def test_tilted_flat_sheet_in_float32_does_not_cross():
    rest, tri = _sheet()
    p = rest.copy()  # the corners scene's rest shape: rotated 55 degrees about the top edge (float32 as gt_vertices.npy)
    drop = rest[:, 1].max() - rest[:, 1]
    p[:, 1], p[:, 2] = rest[:, 1].max() - drop * np.cos(np.radians(55)), drop * np.sin(np.radians(55))
    assert crossing_triangles(p.astype(np.float32), tri) == 0


def test_clean_fold_touches_but_does_not_cross():
    rest, tri = _sheet()
    p = _fold(rest, 0.006)
    assert crossing_triangles(p, tri) == 0
    assert min_gap(rest, p, 6 * H) < 0.02           # on the sheet: 6 mm off, up to H / 2 aside
    assert layered(rest, p, 0.02, 2.5 * H).sum() > N * N // 2


def test_flap_pushed_through_crosses_and_flips():
    rest, tri = _sheet()
    clean = _fold(rest, 0.01)
    through = clean.copy()
    far = rest[:, 1] < -0.1
    through[far, 2] -= 0.04 * (-rest[far, 1] - 0.1) / 0.1   # the flap's end tilts back through the sheet
    assert crossing_triangles(through, tri) > 0
    pairs = far_pairs(rest, clean, 0.015, 2.5 * H)
    assert len(pairs)
    a, b = side(clean, tri, pairs), side(through, tri, pairs)
    both = (a != 0) & (b != 0)
    assert ((a != b) & both).all(1).any()              # some layer pairs change order
    assert not ((a != b) & both).all(1).all()          # not those near the crease
