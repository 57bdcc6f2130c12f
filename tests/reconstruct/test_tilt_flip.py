"""The tilt probe: the mirrored parameters simulate the mirrored motion; the branch of lower loss is kept."""

import numpy as np
import torch

from saft.reconstruct.config import PhysicsConfig, ShapeConfig
from saft.reconstruct.optim import ClippedAdam, ParamSpec
from saft.reconstruct.shape_phase import ShapeSimulator, new_shape_state
from saft.reconstruct.tilt_flip import mirror, plane_normal, probe_flip
from saft.synthetic import grid_template


def test_mirrored_accelerations_mirror_the_motion_of_a_flat_cloth():
    mesh = grid_template(5, 0.3)
    template = torch.tensor(mesh.vertices)
    normal = plane_normal(template)
    assert torch.allclose((template - template.mean(0)) @ normal, torch.zeros(len(template), dtype=template.dtype),
                          atol=1e-12)
    sim = ShapeSimulator(template, mesh.quads, PhysicsConfig(), 0.02, np.arange(5))
    state = new_shape_state(6, len(template), np.array([0.0, -9.81, 0.0]), PhysicsConfig(), ShapeConfig(), "cpu")
    with torch.no_grad():
        state.params.vertex_accel.normal_(0.0, 3.0, generator=torch.Generator().manual_seed(1))
        state.params.field_accel.normal_(0.0, 1.0, generator=torch.Generator().manual_seed(2))
        before = sim.simulate(state.params, 6)
    mirror(state.params.tensors(), state.optimizer, normal)
    with torch.no_grad():
        after = sim.simulate(state.params, 6)
    n = normal.to(before)
    c = template.mean(0)
    reflected = before - 2.0 * ((before - c) @ n)[..., None] * n
    assert float((before - c).matmul(n).abs().max()) > 1e-3          # the motion leaves the plane
    assert torch.allclose(after, reflected, atol=1e-7)


def test_probe_keeps_the_branch_of_lower_loss():
    target = torch.tensor([0.0, 0.0, -1.0], dtype=torch.float64)
    for start, expect in (([0.1, 0.2, 0.5], True), ([0.1, 0.2, -0.5], False)):
        a = torch.tensor(start, dtype=torch.float64, requires_grad=True)
        opt = ClippedAdam([ParamSpec("const_accel", a, 0.01)])

        def epochs():
            for _ in range(3):
                opt.zero_grad()
                loss = ((a - target) ** 2).sum()
                loss.backward()
                opt.step()
            return float(((a.detach() - target) ** 2).sum())

        flipped = probe_flip({"const_accel": a}, opt, torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64), epochs,
                             margin=0.02)
        assert flipped.startswith("mirrored" if expect else "kept")
        assert (float(a.detach()[2]) < 0) and abs(float(a.detach()[0]) - 0.1) < 0.05   # the kept branch's state, optimised


def test_a_reconstruction_with_the_tilt_probe_runs_and_records_it(tiny_reconstruction):
    out = tiny_reconstruction(["shape.flip_probe_frames=4", "shape.flip_probe_epochs=2"])
    saved = torch.load(out / "checkpoint" / "state.pt", weights_only=False)
    assert saved["shape_state"]["flip_probe"].split()[0] in ("kept", "mirrored")
