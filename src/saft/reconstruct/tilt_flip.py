"""A second start with the out-of-plane motion mirrored: escaping the wrong sign of a tilt.

A cloth that tilts out of its plane looks nearly the same in the first frames whether it tilts towards the
camera or away from it (the projections differ only by perspective), and the shape phase settles the sign
before the images can tell it; nothing later undoes it (the independent flag scene: its free half moved
towards the camera where the true one moved away, BENCHMARKS.md "Why saft loses the independent scenes").

For a flat template, mirroring every external acceleration through the template's plane mirrors the whole
simulated motion (the rest shape, the pins and the soft anchors lie on the plane: the physics is symmetric),
so the other sign is one reflection of the parameters away. When the schedule first has
`shape.flip_probe_frames` frames in use, both branches are optimised for `shape.flip_probe_epochs` full
epochs from the same state, the current one and its mirror image (the constant, per-vertex and field
accelerations reflected, with Adam's first moments), and the run goes on with the branch of the lower
loss (the mirror only when it is lower by more than `flip_probe_margin`, relative). A template that is not
flat is mirrored through its best-fit plane, where the symmetry is only approximate: the loss decides.
"""

from __future__ import annotations

import copy
import logging
from typing import Callable

import torch

from saft.reconstruct.optim import ClippedAdam

log = logging.getLogger("saft")

# the parameters that are accelerations (their last axis is x, y, z in the world)
ACCELERATIONS = ("const_accel", "vertex_accel", "field_accel")


def plane_normal(template: torch.Tensor) -> torch.Tensor:
    """Unit normal (3,) of the template's best-fit plane (the direction of least spread of its vertices)."""
    centred = template - template.mean(dim=0)
    _, _, vh = torch.linalg.svd(centred, full_matrices=False)
    return vh[-1]


def mirror(tensors: dict[str, torch.Tensor], optimizer: ClippedAdam, normal: torch.Tensor) -> None:
    """Reflect the accelerations (and Adam's first moments of them) through the plane of `normal`, in place:
    a ↦ a − 2 (a·n) n. The second moments are left as they are (exact for a plane normal to an axis)."""
    with torch.no_grad():
        for name in ACCELERATIONS:
            t = tensors.get(name)
            if t is None:
                continue
            n = normal.to(t)
            t.sub_(2.0 * (t * n).sum(dim=-1, keepdim=True) * n)
            for state in optimizer.optims[name].state.values():
                m = state.get("exp_avg")
                if m is not None:
                    m.sub_(2.0 * (m * n).sum(dim=-1, keepdim=True) * n)


def snapshot(tensors: dict[str, torch.Tensor], optimizer: ClippedAdam) -> dict:
    """A copy of the parameters and the optimizer's state, to come back to with restore()."""
    return {"params": {k: v.detach().clone() for k, v in tensors.items()},
            "optimizer": copy.deepcopy(optimizer.state_dict())}


def restore(tensors: dict[str, torch.Tensor], optimizer: ClippedAdam, saved: dict) -> None:
    with torch.no_grad():
        for k, v in saved["params"].items():
            tensors[k].copy_(v)
    optimizer.load_state_dict(copy.deepcopy(saved["optimizer"]))


def probe_flip(tensors: dict[str, torch.Tensor], optimizer: ClippedAdam, normal: torch.Tensor,
               run_epochs: Callable[[], float], margin: float) -> str:
    """Optimise the current parameters and their mirror image with `run_epochs` (which returns the last
    epoch's loss) and keep the better; returns what was kept and the two losses ("kept 0.01 / 0.02",
    "mirrored 0.02 / 0.01"). The parameters and the optimizer are left in the state of the branch kept."""
    start = snapshot(tensors, optimizer)
    loss_kept = run_epochs()
    kept = snapshot(tensors, optimizer)
    restore(tensors, optimizer, start)
    mirror(tensors, optimizer, normal)
    loss_mirror = run_epochs()
    flipped = loss_mirror < (1.0 - margin) * loss_kept
    log.info("tilt probe: loss %.6g as it was, %.6g mirrored: %s", loss_kept, loss_mirror,
             "mirrored" if flipped else "kept")
    if not flipped:
        restore(tensors, optimizer, kept)
    return f"{'mirrored' if flipped else 'kept'} {loss_kept:.6g} / {loss_mirror:.6g}"


__all__ = ["plane_normal", "mirror", "probe_flip", "snapshot", "restore"]
