"""Aerodynamic drag of still air on the cloth (issue 29; not in the paper): pressure along each triangle's normal.

Each triangle (area A, unit normal n, velocity u = n . (v_a + v_b + v_c) / 3 along its normal, the air at rest)
feels the force  F = -c A |u| u n,  c = rho_air C_d / 2 (kg/m^3; a flat plate broadside: rho_air 1.2,
C_d ~ 1 to 2, so c ~ 0.6 to 1.2), shared equally by its three corners. With the unnormalised normal
N = (b - a) x (c - a) = 2 A n this is  F = -c/2 N |N.w| (N.w) / |N|^2,  w the mean corner velocity: no square
root, smooth wherever the triangle has an area. Only the normal (pressure) part: skin friction along the cloth
is orders of magnitude smaller for cloth-sized speeds, and wind is the learned accelerations' job.

The rollout (simulation.py) adds it EXPLICITLY: the force of substep k is evaluated at the substep's start
(x, v) and enters the right-hand side of the implicit step like the external accelerations. So the solver,
its system matrix and the numba element kernels with their hand-written adjoints are unchanged, and the term
is plain torch, one code path on every device. The adjoint needs the vector-Jacobian product of the force with
the step's adjoint (``drag_vjp``, torch autograd on these few ops). Explicit is stable here: the linearised
rate 2 c |u| / (3 rho_s) per unit mass (rho_s the areal density) times the substep h stays far below 2
(c = 1, rho_s = 0.1 kg/m^2, |u| = 2 m/s, h = 1/120 s: 0.1).
"""

from __future__ import annotations

import torch


def drag_force(x: torch.Tensor, v: torch.Tensor, triangles: torch.Tensor, c: torch.Tensor) -> torch.Tensor:
    """(V, 3) drag force on every vertex at positions x, velocities v (V, 3); c: the coefficient (0-dim, kg/m^3)."""
    a, b, d = x[triangles[:, 0]], x[triangles[:, 1]], x[triangles[:, 2]]
    N = torch.linalg.cross(b - a, d - a)                                   # (T, 3), |N| = 2 area
    w = (v[triangles[:, 0]] + v[triangles[:, 1]] + v[triangles[:, 2]]) / 3.0
    un = (N * w).sum(dim=1)                                                # |N| u
    nn = (N * N).sum(dim=1).clamp_min(torch.finfo(x.dtype).tiny)
    f = (-0.5 * c) * N * (un.abs() * un / nn)[:, None]                     # (T, 3), per triangle
    share = (f / 3.0).repeat_interleave(3, dim=0)
    return torch.zeros_like(x).index_add_(0, triangles.reshape(-1), share)


def drag_vjp(x: torch.Tensor, v: torch.Tensor, triangles: torch.Tensor, c: torch.Tensor,
             lam: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """d/dx, d/dv, d/dc of lam . drag_force(x, v, c): ((V, 3), (V, 3), 0-dim)."""
    with torch.enable_grad():
        xg = x.detach().requires_grad_(True)
        vg = v.detach().requires_grad_(True)
        cg = c.detach().requires_grad_(True)
        out = (drag_force(xg, vg, triangles, cg) * lam.detach()).sum()
        gx, gv, gc = torch.autograd.grad(out, (xg, vg, cg))
    return gx, gv, gc


__all__ = ["drag_force", "drag_vjp"]
