"""saft.physics: the differentiable mass-spring cloth simulator (paper section 3.1, REFERENCE.md).

Public API
----------
``ClothTopology.from_quads(vertices, quads, density=0.1, *, device=None, dtype=torch.float64, rest_shape="template")``
``ClothTopology.from_mesh(quad_mesh, density=0.1)``; ``topology.to(device, dtype)``
    Stretch springs on the unique quad edges (rest lengths L0); a hinge (n1, v, n2) for every vertex v and
    every pair of its quad-edge neighbours, rest angle theta0 = arccos(0.99 e1_hat . e2_hat) with
    e1 = v - n1, e2 = n2 - v, bending if theta0 < 45 deg else shearing; lumped masses area/3 * density
    from the quads split (a,b,c), (a,c,d); the fixed CSR pattern of the 3V x 3V system matrix.
    rest_shape="flat": the rest angles of the template flattened (each hinge's edges projected on the
    tangent plane at its vertex: straight bend hinges, in-surface shear angles); rest lengths unchanged.

``deformation_energy(x, topology, log10_Y, log10_B, log10_S, per_term=False)``
    E_Y + E_B + E_S (or the three terms) for x of shape (..., V, 3); plain autograd, batched over frames;
    differentiable in x and the log-stiffnesses (detach them for the regularizer R_E).

``PhysicsParams(log10_Y, log10_B, log10_S, damping, a_const, a_vert=None, anchor=None)``;
``PhysicsParams.default(num_frames, num_vertices, device=..., requires_grad=...)``
    Paper defaults: Y = 200, B = 1e-3, S = 1e-4, damping d = 0.9 (v <- d v before every substep),
    a_const = gravity (0, -9.81, 0), a_vert (N - 1, V, 3) = 0; f_ext = m (a_const + a_vert[k]) during the
    substeps from frame k to k + 1. anchor (V,): soft pins, a zero-length spring of stiffness m_i w_i (w in
    s^-2) from each vertex to its anchor position, treated implicitly (w h^2 >> 1 holds the vertex).

``rollout(topology, x0, v0=None, params=None, *, num_frames, substeps=4, frame_dt=0.02, pinned=None,
          pinned_positions=None, hessian="projected", solver="auto", tol=1e-6, stats=None,
          anchor_positions=None, factor_cache=None, first_step=0)``
    -> positions (num_frames, V, 3), positions[0] = x0. Linearised backward Euler
    (M + h^2 K) v1 = M d v + h (f + M a_ext), x1 = x + h v1. Gradients (one custom adjoint backward, no
    unrolled solver) reach x0, v0, log10 Y/B/S, damping, a_const, a_vert, anchor (the anchors pull towards
    anchor_positions, default x0, which get no gradient). Pinned vertices stay exactly at
    x0 or at pinned_positions (N, P, 3) (linear within a frame). NaN/inf raises
    ``saft.errors.SimulationError`` naming the frame and substep. ``factor_cache`` (a ``FactorCache``,
    saft.physics.factor_cache): the CPU solver's preconditioner factors kept across rollouts of the same
    frames, by absolute substep (``first_step`` = the rollout's first); the shape phase keeps one per run.

``ElementEval`` - closed-form per-element gradients / Hessians (elements-last), for advanced use.

Hessian modes: "projected" (default) clamps each spring's transverse stiffness at zero under compression
and keeps the Gauss-Newton part of each hinge, so M + h^2 K is always SPD (the reference's exact Hessian
becomes indefinite after a few mm of compression); "exact" uses the true Hessian with an LU-based solve.
Solvers: CPU - CG preconditioned by a reused incomplete LU factorisation (SuperLU's ILU, "lu", the default
whatever is installed), refactorised when CG needs more than 15 iterations; the opt-in "cholmod" uses a
CHOLMOD Cholesky factor instead (scikit-sparse; its numbers differ within the tolerance); other devices -
"densebf16": CG preconditioned by the bfloat16 inverse of a reused dense float32 Cholesky factor (cuSOLVER), in
torch, with the set-up, the CG blocks and the element kernels recorded as CUDA graphs (solver_dense,
cuda_graphs; "dense" (a float32 inverse), "dense64", "densechol", "direct" and the old Jacobi CG "cg" stay
selectable). The CPU default is
deterministic: the same bits on every run and with any torch thread count.
"""

from saft.physics.energy import ElementEval, deformation_energy
from saft.physics.simulation import (DEFAULT_DAMPING, DEFAULT_LOG10_B, DEFAULT_LOG10_S, DEFAULT_LOG10_Y,
                                     DEFAULT_SUBSTEPS, GRAVITY, LOG10_LIMITS, PhysicsParams, rollout)
from saft.physics.topology import DEFAULT_DENSITY, ClothTopology

__all__ = [
    "ClothTopology",
    "DEFAULT_DAMPING",
    "DEFAULT_DENSITY",
    "DEFAULT_LOG10_B",
    "DEFAULT_LOG10_S",
    "DEFAULT_LOG10_Y",
    "DEFAULT_SUBSTEPS",
    "ElementEval",
    "GRAVITY",
    "LOG10_LIMITS",
    "PhysicsParams",
    "deformation_energy",
    "rollout",
]
