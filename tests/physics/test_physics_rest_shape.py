"""ClothTopology's rest_shape="flat": the template flattened as the cloth's rest shape (issue 29)."""

import math
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from physics_helpers import grid_mesh  # noqa: E402

from saft.physics import ClothTopology, PhysicsParams, deformation_energy, rollout  # noqa: E402


def _no_gravity():
    p = PhysicsParams.default()
    p.a_const = torch.zeros(3, dtype=torch.float64)
    return p


def _out_of_plane(x) -> float:
    """RMS distance of the vertices from their best-fitting plane."""
    x = np.asarray(x)
    c = x - x.mean(0)
    return float(np.linalg.svd(c, compute_uv=False)[-1] / math.sqrt(len(x)))


def test_flat_template_same_rest_angles_and_stays_still():
    v, q = grid_mesh(6)
    tmpl = ClothTopology.from_quads(v, q)
    flat = ClothTopology.from_quads(v, q, rest_shape="flat")
    assert np.allclose(flat.rest_angle.numpy(), tmpl.rest_angle.numpy(), atol=1e-12)
    assert torch.equal(flat.is_bend, tmpl.is_bend)
    assert torch.equal(flat.rest_len, tmpl.rest_len)
    pos = rollout(flat, flat.template, None, _no_gravity(), num_frames=6)
    assert (pos - flat.template).abs().max() < 1e-9


def test_curved_template_flat_rest_angles():
    v, q = grid_mesh(8, wave=0.03)  # a wave along x: the x-lines curve out of the plane
    tmpl = ClothTopology.from_quads(v, q)
    flat = ClothTopology.from_quads(v, q, rest_shape="flat")
    bend = tmpl.is_bend.numpy()
    assert tmpl.rest_angle.numpy()[bend].max() > math.acos(0.99) + 0.04  # the template is curved
    assert np.allclose(flat.rest_angle.numpy()[bend], math.acos(0.99), atol=1e-9)  # flattened: straight
    assert np.allclose(flat.rest_angle.numpy()[~bend], math.pi / 2, atol=1e-9)  # in-surface right angles
    assert torch.equal(flat.rest_len, tmpl.rest_len)
    # the curved template is at rest in its own shape, not in the flat one
    args = (torch.tensor(2.3), torch.tensor(-3.0), torch.tensor(-4.0))
    assert deformation_energy(tmpl.template, tmpl, *args).item() < 1e-12
    assert deformation_energy(flat.template, flat, *args).item() > 1e-6


def test_curved_template_relaxes_towards_flat_only_with_a_flat_rest_shape():
    v, q = grid_mesh(8, wave=0.03)
    tmpl = ClothTopology.from_quads(v, q)
    flat = ClothTopology.from_quads(v, q, rest_shape="flat")
    p = _no_gravity()
    p.log10_B = torch.tensor(-1.0, dtype=torch.float64)  # stiffer bending: a visible relaxation in 40 frames
    still = rollout(tmpl, tmpl.template, None, p, num_frames=40)
    assert (still - tmpl.template).abs().max() < 1e-9
    relaxed = rollout(flat, flat.template, None, p, num_frames=40)
    before, after = _out_of_plane(v), _out_of_plane(relaxed[-1].numpy())
    assert after < 0.5 * before


def test_unknown_rest_shape_is_refused():
    v, q = grid_mesh(2)
    with pytest.raises(ValueError, match="rest_shape"):
        ClothTopology.from_quads(v, q, rest_shape="curved")
