"""Deformation energies of the mass-spring cloth (paper eq. 4-5) and their closed-form derivatives.

E_Y = 1/2 Y (|x_j - x_i| - L0)^2 per quad edge;
E_B, E_S = 1/2 k (theta - theta0)^2 per hinge (n1, v, n2), theta = arccos(0.99 * e1_hat . e2_hat),
e1 = v - n1, e2 = n2 - v, k = B for bending hinges and S for shearing hinges.

Two flavours:
* ``deformation_energy`` - plain autograd-friendly torch, batched over leading dims ((F, V, 3) ok);
  used as the regularizer R_E and as the reference for the tests.
* ``ElementEval`` - closed-form per-element gradients, Hessian blocks, Hessian-vector products and the
  third-derivative contraction d/dx (lam^T K(x) w) needed by the adjoint, all elements-last ((3, n)).

Hessian modes: ``"exact"`` is the true Hessian (may be indefinite under compression); ``"projected"``
(default of the rollout) clamps each spring's transverse stiffness (1 - L0/l) at 0 and keeps only the
Gauss-Newton part k * theta'^2 * grad q grad q^T of each hinge, so every element Hessian is PSD and
M + h^2 K is SPD.
"""

from __future__ import annotations

import math

import torch

from saft.physics.topology import ARCCOS_GUARD, ClothTopology

LN10 = math.log(10.0)
_C = ARCCOS_GUARD
_EPS_LEN = 1e-12
HESSIAN_MODES = ("projected", "exact")


def stiffnesses(log10_Y, log10_B, log10_S):
    return 10.0 ** log10_Y, 10.0 ** log10_B, 10.0 ** log10_S


def deformation_energy(x, topology: ClothTopology, log10_Y, log10_B, log10_S, per_term: bool = False):
    """Total deformation energy of positions ``x`` (..., V, 3) (joules); differentiable in x and the
    log10 stiffnesses. Returns a tensor of shape x.shape[:-2], or (E_Y, E_B, E_S) with ``per_term``."""
    Y, B, S = stiffnesses(_as_t(log10_Y, x), _as_t(log10_B, x), _as_t(log10_S, x))
    t = topology
    e = x[..., t.edges[:, 1], :] - x[..., t.edges[:, 0], :]
    length = torch.linalg.vector_norm(e, dim=-1)
    E_Y = 0.5 * Y * ((length - t.rest_len) ** 2).sum(-1)
    e1 = x[..., t.hinges[:, 1], :] - x[..., t.hinges[:, 0], :]
    e2 = x[..., t.hinges[:, 2], :] - x[..., t.hinges[:, 1], :]
    l1 = torch.linalg.vector_norm(e1, dim=-1).clamp_min(_EPS_LEN)
    l2 = torch.linalg.vector_norm(e2, dim=-1).clamp_min(_EPS_LEN)
    q = (e1 * e2).sum(-1) / (l1 * l2)
    theta = torch.arccos((_C * q).clamp(-_C, _C))
    d2 = (theta - t.rest_angle) ** 2
    E_B = 0.5 * B * (d2 * t.bend_w).sum(-1)
    E_S = 0.5 * S * (d2 * (1.0 - t.bend_w)).sum(-1)
    if per_term:
        return E_Y, E_B, E_S
    return E_Y + E_B + E_S


def _hess_q(u1, u2, q, l1, l2, a1, a2):
    """(grad^2 q) of q = û1·û2 (e-space, elements-last) applied to the vector (a1, a2)."""
    u1a1, u2a1, u1a2, u2a2 = _dot(u1, a1), _dot(u2, a1), _dot(u1, a2), _dot(u2, a2)
    r1 = (-u2a1 * u1 - u1a1 * u2 - q * a1 + 3.0 * q * u1a1 * u1) / (l1 * l1) + (
        a2 - u1a2 * u1 - u2a2 * u2 + q * u2a2 * u1
    ) / (l1 * l2)
    r2 = (-u1a2 * u2 - u2a2 * u1 - q * a2 + 3.0 * q * u2a2 * u2) / (l2 * l2) + (
        a1 - u1a1 * u1 - u2a1 * u2 + q * u1a1 * u2
    ) / (l1 * l2)
    return r1, r2


def _as_t(v, like):
    if isinstance(v, torch.Tensor):
        return v.to(dtype=like.dtype)
    return torch.tensor(float(v), dtype=like.dtype, device=like.device)


def _dot(a, b):
    return (a * b).sum(0)


def _outer(a, b):
    return a[:, None, :] * b[None, :, :]


def _parts(S, P1, P2):
    """Per-element vector pieces from edge-space ones: springs (i, j) = (-S, S), hinges (n1, v, n2) =
    (-P1, P1 - P2, P2) (e = x_j - x_i, e1 = v - n1, e2 = n2 - v), aligned with topology.scatter_idx."""
    return torch.cat([-S, S, -P1, P1 - P2, P2], dim=1)


class ElementEval:
    """Closed-form element quantities at one configuration (x: (V, 3)), elements-last.

    Y, B, S are plain floats (or 0-dim tensors) - the actual stiffnesses, not their logs.
    """

    def __init__(self, topology: ClothTopology, x, Y, B, S, mode: str = "projected"):
        if mode not in HESSIAN_MODES:
            raise ValueError(f"hessian mode must be one of {HESSIAN_MODES}, got {mode!r}")
        t = topology
        self.t = t
        self.mode = mode
        self.Y = Y
        self.xT = x.T
        # every element end in one gather: (3, 2E + 3H), springs (i, j) then hinges (n1, v, n2)
        self.nE = t.edges.shape[0]
        self.nH = t.hinges.shape[0]
        xi, xj, xn1, xv, xn2 = self._ends(x)
        # --- springs
        e = xj - xi
        ls = torch.sqrt(_dot(e, e)).clamp_min(_EPS_LEN)
        u = e / ls
        s = 1.0 - t.rest_len / ls
        if mode == "projected":
            sp = s.clamp_min(0.0)
            dsp = (s > 0).to(s.dtype) * t.rest_len / (ls * ls)
        else:
            sp = s
            dsp = t.rest_len / (ls * ls)
        self.ls, self.us, self.s, self.sp, self.dsp = ls, u, s, sp, dsp
        self.stretch = ls - t.rest_len
        # --- hinges
        e1 = xv - xn1
        e2 = xn2 - xv
        l1 = torch.sqrt(_dot(e1, e1)).clamp_min(_EPS_LEN)
        l2 = torch.sqrt(_dot(e2, e2)).clamp_min(_EPS_LEN)
        u1, u2 = e1 / l1, e2 / l2
        q = _dot(u1, u2)
        cq = (_C * q).clamp(-_C, _C)
        s2 = 1.0 - cq * cq
        theta = torch.arccos(cq)
        dth = -_C / torch.sqrt(s2)  # d theta / d q
        kh = B * t.bend_w + S * (1.0 - t.bend_w)
        self.kh = kh
        self.dtheta = theta - t.rest_angle
        self.phi_q = kh * self.dtheta * dth
        tau = dth * dth  # theta'^2 = c^2 / (1 - c^2 q^2)
        self.tau = tau
        d2th = -_C**3 * q / (s2 * torch.sqrt(s2))
        self.phi_qq_exact = kh * (tau + self.dtheta * d2th)
        self.phi_qq = self.phi_qq_exact if mode == "exact" else kh * tau
        self.l1, self.l2, self.u1, self.u2, self.q, self.s2 = l1, l2, u1, u2, q, s2
        self.g1 = (u2 - q * u1) / l1
        self.g2 = (u1 - q * u2) / l2

    def _ends(self, w):
        """(spring i, spring j, hinge n1, hinge v, hinge n2) values of a (V, 3) field, each (3, n)."""
        g = torch.index_select(w.reshape(-1), 0, self.t.gather_idx).view(3, -1)
        E, H = self.nE, self.nH
        return g[:, :E], g[:, E:2 * E], g[:, 2 * E:2 * E + H], g[:, 2 * E + H:2 * E + 2 * H], g[:, 2 * E + 2 * H:]

    # ------------------------------------------------------------------ energy gradient
    def grad_parts(self):
        """(3, 2E + 3H) per-element contributions to dE/dx, aligned with topology.scatter_idx."""
        Gs = (self.Y * self.stretch) * self.us
        return _parts(Gs, self.phi_q * self.g1, self.phi_q * self.g2)

    def grad(self):
        """dE/dx as (3, V)."""
        return self.scatter(self.grad_parts())

    # ------------------------------------------------------------------ Hessian assembly
    def hessian_values(self):
        """K = d2E/dx2 data in the topology's CSR pattern (flat (nnz,) tensor)."""
        if self.mode == "projected":
            return torch.index_select(self.hessian_upper(), 0, self.t.up_of)
        return self._hessian_values_blocks()

    def system_values(self, hh, mass_diag):
        """Data of A = M + hh K in the CSR pattern (mass_diag: (3V,), the diagonal of M)."""
        t = self.t
        if self.mode == "projected":
            A = (hh * self.hessian_upper()).index_add_(0, t.diag_up_idx, mass_diag)
            return torch.index_select(A, 0, t.up_of)
        return (hh * self._hessian_values_blocks()).index_add_(0, t.diag_idx, mass_diag)

    def _spring_K(self):
        us = self.us
        I3 = torch.eye(3, dtype=us.dtype, device=us.device)[:, :, None]
        return self.Y * ((1.0 - self.sp) * _outer(us, us) + self.sp * I3)  # (3, 3, E)

    def hessian_upper(self):
        """Projected K in the upper-triangle storage (topology.up_of): each element contributes only the
        unique entries of its symmetric Hessian (21 per spring, 45 per Gauss-Newton hinge), about half the
        products and scattered values of the full blocks."""
        t = self.t
        Ks = self._spring_K().reshape(9, -1)
        spring_vals = torch.index_select(torch.cat([Ks, -Ks]), 0, t.spring_up_rows)
        G = torch.cat([-self.g1, self.g1 - self.g2, self.g2])  # (9, H): rows (n1, v, n2) x dims
        ra, rb = t.hinge_up_rows[0], t.hinge_up_rows[1]
        hinge_vals = torch.index_select(self.phi_qq * G, 0, ra) * torch.index_select(G, 0, rb)
        out = torch.zeros(t.nnz_up, dtype=G.dtype, device=G.device)
        out.index_add_(0, t.spring_up_idx, spring_vals.reshape(-1))
        return out.index_add_(0, t.hinge_up_idx, hinge_vals.reshape(-1))

    def _hessian_values_blocks(self):
        t = self.t
        us = self.us
        I3 = torch.eye(3, dtype=us.dtype, device=us.device)[:, :, None]
        Ks = self._spring_K()
        spring_blocks = torch.stack([Ks, -Ks, -Ks, Ks])  # (4, 3, 3, E)
        g1, g2 = self.g1, self.g2
        a = self.phi_qq
        out = torch.zeros(t.nnz, dtype=us.dtype, device=us.device)
        out.index_add_(0, t.spring_idx, spring_blocks.reshape(-1))
        if self.mode == "projected":
            # Gauss-Newton hinge Hessian a * G G^T with G = (-g1, g1 - g2, g2) (rows n1, v, n2): one
            # outer product in (vertex r, dim i, vertex c, dim j, hinge) order, scattered with the matching
            # permutation of hinge_idx
            G = torch.stack([-g1, g1 - g2, g2])  # (3, 3, H)
            vals = (a * G)[:, :, None, None, :] * G[None, None, :, :, :]
            return out.index_add_(0, t.hinge_idx_outer, vals.reshape(-1))
        H11 = a * _outer(g1, g1)
        H12 = a * _outer(g1, g2)
        H22 = a * _outer(g2, g2)
        if self.mode == "exact":
            u1, u2, q, l1, l2 = self.u1, self.u2, self.q, self.l1, self.l2
            b = self.phi_q
            u1u2 = _outer(u1, u2)
            u2u1 = _outer(u2, u1)
            u1u1 = _outer(u1, u1)
            u2u2 = _outer(u2, u2)
            H11 = H11 + (b / (l1 * l1)) * (-u1u2 - u2u1 - q * I3 + 3.0 * q * u1u1)
            H22 = H22 + (b / (l2 * l2)) * (-u2u1 - u1u2 - q * I3 + 3.0 * q * u2u2)
            H12 = H12 + (b / (l1 * l2)) * (I3 - u1u1 - u2u2 + q * u1u2)
        H21 = H12.transpose(0, 1)
        # x-space blocks, rows/cols ordered (n1, v, n2): e1 = v - n1, e2 = n2 - v
        n1v = H12 - H11
        vn2 = H12 - H22
        vv = H11 + H22 - H12 - H21
        hinge_blocks = torch.stack(
            [H11, n1v, -H12, n1v.transpose(0, 1), vv, vn2, -H21, vn2.transpose(0, 1), H22]
        )  # (9, 3, 3, H)
        return out.index_add_(0, t.hinge_idx, hinge_blocks.reshape(-1))

    # ------------------------------------------------------------------ adjoint helpers
    def _to_e(self, wT):
        wi, wj, wn1, wv, wn2 = self._ends(wT.T)
        return wj - wi, wv - wn1, wn2 - wv

    def _hess_q(self, a1, a2):
        """(grad^2 q) applied to the e-space vector (a1, a2)."""
        return _hess_q(self.u1, self.u2, self.q, self.l1, self.l2, a1, a2)

    def exact_hvp_parts(self, lamT):
        """Per-element pieces of (d2E/dx2) lam with the TRUE Hessian (whatever the mode), aligned with
        topology.scatter_idx; the adjoint needs it for d/dx (lam . f(x))."""
        lams, lam1, lam2 = self._to_e(lamT)
        ul = _dot(self.us, lams)
        gl = _dot(self.g1, lam1) + _dot(self.g2, lam2)
        Ks, H1, H2 = self._exact_hvp(lams, ul, gl, *self._hess_q(lam1, lam2))
        return _parts(Ks, H1, H2)

    def _exact_hvp(self, lams, ul, gl, hl1, hl2):
        """Edge-space pieces of the true-Hessian product from lam's edge vectors and contractions."""
        us, s = self.us, self.s
        Ks = self.Y * ((1.0 - s) * ul * us + s * lams)
        a = self.phi_qq_exact * gl
        return Ks, a * self.g1 + self.phi_q * hl1, a * self.g2 + self.phi_q * hl2

    def adjoint_increment(self, lamT, wT, h):
        """Everything one implicit step's adjoint needs from the elements, sharing the work of
        ``exact_hvp_parts`` and ``adjoint_terms``: (parts, gY, hinge_c) where parts (3, 2E + 3H) are the
        per-element pieces of -h (d2E/dx2) lam - h^2 d/dx (lam^T K(x) w) (true Hessian in the first term),
        gY = -h lam . dE_Y/dx - h^2 lam^T K_Y w (summed) and hinge_c the same per hinge (bend and shear)."""
        adj = self.adjoint_terms(lamT, wT, hvp=True)
        Ks, H1, H2 = adj["hvp"]
        Ts, T1, T2 = adj["third"]
        hh = h * h
        parts = _parts(-h * Ks - hh * Ts, -h * H1 - hh * T1, -h * H2 - hh * T2)
        gY = -h * adj["spring_lg"].sum() - hh * adj["spring_lKw"].sum()
        return parts, gY, -h * adj["hinge_lg"] - hh * adj["hinge_lKw"]

    def adjoint_terms(self, lamT, wT, need_third: bool = True, hvp: bool = False):
        """For the adjoint of one implicit step.

        Returns (third (3, V), c_Y, c_B, c_S, lamK_parts) where
          third = d/dx (lam^T K(x) w) (the third-derivative contraction), and
          c_k = dk-weighted pieces: c_Y = lam . dE_Y/dx (with Y), kY = lam^T K_Y w (with Y), etc.
        Only the "projected" mode is closed form here; "exact" falls back to autograd for the hinges.
        With ``hvp`` the dict also holds the edge-space pieces of ``exact_hvp_parts`` ("hvp") and of the
        third-derivative contraction ("third"), each (springs, hinge e1, hinge e2), instead of "third_parts".
        """
        ls_, us, sp, dsp = self.ls, self.us, self.sp, self.dsp
        lams, lam1, lam2 = self._to_e(lamT)
        ws, w1, w2 = self._to_e(wT)
        Y = self.Y
        # springs: lam^T K w = Y [sp (lam.w) + (1 - sp)(u.lam)(u.w)]
        ul, uw, lw = _dot(us, lams), _dot(us, ws), _dot(lams, ws)
        spring_lKw = Y * (sp * lw + (1.0 - sp) * ul * uw)
        spring_lg = Y * self.stretch * ul  # lam . dE/de
        P_l = (lams - ul * us) / ls_
        P_w = (ws - uw * us) / ls_
        Ts = Y * ((1.0 - sp) * (uw * P_l + ul * P_w) + (lw - ul * uw) * dsp * us)
        # hinges
        g1, g2 = self.g1, self.g2
        gl = _dot(g1, lam1) + _dot(g2, lam2)
        gw = _dot(g1, w1) + _dot(g2, w2)
        hinge_lg = self.phi_q * gl
        hinge_lKw = self.phi_qq * gl * gw
        projected = self.mode == "projected"
        hl = self._hess_q(lam1, lam2) if hvp or (need_third and projected) else None
        hw = self._hess_q(w1, w2) if not projected or need_third else None
        if not projected:
            hinge_lKw = hinge_lKw + self.phi_q * (_dot(lam1, hw[0]) + _dot(lam2, hw[1]))
        T1 = T2 = None
        if need_third or hvp:
            if projected:
                kh, q = self.kh, self.q
                dtau = 2.0 * _C**4 * q / (self.s2 * self.s2)
                a = kh * dtau * gl * gw
                b = kh * self.tau
                T1 = a * g1 + b * (gw * hl[0] + gl * hw[0])
                T2 = a * g2 + b * (gw * hl[1] + gl * hw[1])
            else:
                T1, T2 = self._third_exact_hinge(lam1, lam2, w1, w2)
        out = dict(spring_lKw=spring_lKw, spring_lg=spring_lg, hinge_lKw=hinge_lKw, hinge_lg=hinge_lg)
        if hvp:
            out["hvp"] = self._exact_hvp(lams, ul, gl, *hl)
            out["third"] = (Ts, T1, T2)
        else:
            out["third_parts"] = None if T1 is None else _parts(Ts, T1, T2)
        return out

    def _third_exact_hinge(self, lam1, lam2, w1, w2):
        """d/de (lam^T K_hinge(e) w) for the exact hinge Hessian, by autograd on the closed form."""
        t = self.t
        h = t.hinges
        with torch.enable_grad():
            xT = self.xT.detach()
            e1 = (xT[:, h[:, 1]] - xT[:, h[:, 0]]).requires_grad_(True)
            e2 = (xT[:, h[:, 2]] - xT[:, h[:, 1]]).requires_grad_(True)
            l1 = torch.linalg.vector_norm(e1, dim=0).clamp_min(_EPS_LEN)
            l2 = torch.linalg.vector_norm(e2, dim=0).clamp_min(_EPS_LEN)
            u1, u2 = e1 / l1, e2 / l2
            q = _dot(u1, u2)
            cq = (_C * q).clamp(-_C, _C)
            s2 = 1.0 - cq * cq
            theta = torch.arccos(cq)
            dth = -_C / torch.sqrt(s2)
            d2th = -_C**3 * q / (s2 * torch.sqrt(s2))
            dt = theta - t.rest_angle
            kh = self.kh
            phi_q = kh * dt * dth
            phi_qq = kh * (dth * dth + dt * d2th)
            g1 = (u2 - q * u1) / l1
            g2 = (u1 - q * u2) / l2
            gl = _dot(g1, lam1) + _dot(g2, lam2)
            gw = _dot(g1, w1) + _dot(g2, w2)
            r1, r2 = _hess_q(u1, u2, q, l1, l2, w1, w2)  # differentiable in e1, e2 here
            s = (phi_qq * gl * gw + phi_q * (_dot(lam1, r1) + _dot(lam2, r2))).sum()
            T1, T2 = torch.autograd.grad(s, (e1, e2))
        return T1, T2

    def scatter(self, parts):
        """Sum per-element (3, 2E + 3H) pieces onto their vertices: (3, V)."""
        out = torch.zeros_like(self.xT)
        return out.index_add_(1, self.t.scatter_idx, parts)
