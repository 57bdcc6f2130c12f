"""Aerodynamic drag of still air on the cloth (issue 29; not in the paper): pressure along each triangle's normal.

Each triangle (area A, unit normal n, velocity u = n . (v_a + v_b + v_c) / 3 along its normal, the air at rest)
feels the force  F = -c A |u| u n,  c = rho_air C_d / 2 (kg/m^3; a flat plate broadside: rho_air 1.2,
C_d ~ 1 to 2, so c ~ 0.6 to 1.2), shared equally by its three corners. With the unnormalised normal
N = (b - a) x (c - a) = 2 A n this is  F = -c/2 N |N.w| (N.w) / |N|^2,  w the mean corner velocity: no square
root, smooth wherever the triangle has an area. Only the normal (pressure) part: skin friction along the cloth
is orders of magnitude smaller for cloth-sized speeds, and wind is the learned accelerations' job.

The rollout (simulation.py) adds it EXPLICITLY: the force of substep k is evaluated at the substep's start
(x, v) and enters the right-hand side of the implicit step like the external accelerations. So the solver,
its system matrix and the numba element kernels with their hand-written adjoints are unchanged. The adjoint
needs the vector-Jacobian product of the force with the step's adjoint (``drag_vjp``, in closed form:
autograd on these ops cost ~1.5 ms a substep). On the CPU (float64) both run as numba loops (``drag_numba``)
that give the torch ops' bits (~40 small ops a call were 4 % of a swinging cloth's reconstruction); other
devices and dtypes run the torch ops. Explicit is stable here: the linearised
rate 2 c |u| / (3 rho_s) per unit mass (rho_s the areal density) times the substep h stays far below 2
(c = 1, rho_s = 0.1 kg/m^2, |u| = 2 m/s, h = 1/120 s: 0.1).
"""

from __future__ import annotations

import torch

from saft.physics import drag_numba


def _triangle_terms(x: torch.Tensor, v: torch.Tensor, triangles: torch.Tensor):
    """Per triangle (T, ·): the edges e1 = b − a, e2 = d − a, N = e1 × e2 (|N| = 2 area), the mean corner
    velocity w, un = N·w (|N| u) and nn = N·N (floored), the last two (T, 1): what the force and its adjoint
    share."""
    i0, i1, i2 = triangles[:, 0], triangles[:, 1], triangles[:, 2]
    e1, e2 = x[i1] - x[i0], x[i2] - x[i0]
    N = torch.linalg.cross(e1, e2)
    w = (v[i0] + v[i1] + v[i2]) / 3.0
    un = (N * w).sum(dim=1, keepdim=True)
    nn = (N * N).sum(dim=1, keepdim=True).clamp_min(torch.finfo(x.dtype).tiny)
    return e1, e2, N, w, un, nn


def _numba_applies(*tensors) -> bool:
    return all(t.device.type == "cpu" for t in tensors) and tensors[0].dtype == torch.float64


def _arrays(*tensors):
    return [t.detach().contiguous().numpy() for t in tensors]


def drag_force(x: torch.Tensor, v: torch.Tensor, triangles: torch.Tensor, c: torch.Tensor) -> torch.Tensor:
    """(V, 3) drag force on every vertex at positions x, velocities v (V, 3); c: the coefficient (0-dim, kg/m^3)."""
    if _numba_applies(x, v, triangles) and not (x.requires_grad or v.requires_grad or c.requires_grad):
        drag_numba.load()
        out = torch.empty_like(x)
        drag_numba.force(*_arrays(x, v, triangles), float(c), out.numpy())
        return out
    return drag_force_torch(x, v, triangles, c)


def drag_force_torch(x: torch.Tensor, v: torch.Tensor, triangles: torch.Tensor, c: torch.Tensor) -> torch.Tensor:
    """drag_force in torch ops (any device, differentiable)."""
    _, _, N, _, un, nn = _triangle_terms(x, v, triangles)
    f = (-0.5 * c) * N * (un.abs() * un / nn)                              # (T, 3), per triangle
    share = (f / 3.0).repeat_interleave(3, dim=0)
    return torch.zeros_like(x).index_add_(0, triangles.reshape(-1), share)


def drag_vjp(x: torch.Tensor, v: torch.Tensor, triangles: torch.Tensor, c: torch.Tensor,
             lam: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """d/dx, d/dv, d/dc of lam . drag_force(x, v, c): ((V, 3), (V, 3), 0-dim), in closed form.

    Per triangle, with L = lam's corner mean, p = L.N, un = N.w, s = |un| un, nn = N.N, the term is
    -c/2 p s / nn: d/dw = -c p |un| / nn N; d/dN = -c/2 (s / nn L + 2 p |un| / nn w - 2 p s / nn^2 N); and
    N = e1 x e2 (e1 = b - a, e2 = d - a) gives d/de1 = e2 x gN, d/de2 = gN x e1."""
    if _numba_applies(x, v, triangles, lam):
        drag_numba.load()
        gx, gv = torch.empty_like(x), torch.empty_like(x)
        terms = x.new_empty(triangles.shape[0])
        drag_numba.vjp(*_arrays(x, v, triangles), float(c), *_arrays(lam), gx.numpy(), gv.numpy(), terms.numpy())
        return gx, gv, terms.sum()
    return drag_vjp_torch(x, v, triangles, c, lam)


def drag_vjp_torch(x: torch.Tensor, v: torch.Tensor, triangles: torch.Tensor, c: torch.Tensor,
                   lam: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """drag_vjp in torch ops (any device)."""
    e1, e2, N, w, un, nn = _triangle_terms(x, v, triangles)
    L = (lam[triangles[:, 0]] + lam[triangles[:, 1]] + lam[triangles[:, 2]]) / 3.0
    p = (L * N).sum(dim=1, keepdim=True)
    au = un.abs()
    s = au * un
    gc = (-0.5 * (p * s / nn)).sum()
    gw = (-c * p * au / nn) * N / 3.0                                   # per corner
    gN = (-0.5 * c) * (s / nn * L + (2.0 * p * au / nn) * w - (2.0 * p * s / (nn * nn)) * N)
    ge1 = torch.linalg.cross(e2, gN)
    ge2 = torch.linalg.cross(gN, e1)
    idx = triangles.reshape(-1)
    gv = torch.zeros_like(x).index_add_(0, idx, gw.repeat_interleave(3, dim=0))
    gx = torch.zeros_like(x).index_add_(0, idx, torch.stack([-ge1 - ge2, ge1, ge2], dim=1).reshape(-1, 3))
    return gx, gv, gc


__all__ = ["drag_force", "drag_force_torch", "drag_vjp", "drag_vjp_torch"]
