"""A cloth simulated by a model that is not saft's: NVIDIA Newton's VBD solver (warp kernels, on the CPU).

Benchmark scenes simulated by saft's own mass-spring model on the template's own mesh commit the "inverse
crime" (issue 29): the model that reconstructs made the data. This module simulates the same kinds of
scene with another model on another, finer mesh:

* a Neo-Hookean FEM membrane (Newton's ``tri_ke`` / ``tri_ka``, Lamé parameters in N/m) and dihedral bending
  (``edge_ke``) per edge, integrated by Vertex Block Descent (``newton.solvers.SolverVBD``);
* optional self-contact (vertex-triangle and edge-edge, VBD's own), so that a flap can lie on the cloth;
* aerodynamics, written here because VBD has none: each triangle feels the pressure of the wind relative to
  it, ``f = ½ ρ C_n A (v_rel·n)|v_rel·n| n`` along its normal plus a small skin friction ``C_t A v_rel,t``,
  spread over its three vertices. Still air gives air drag, a moving wind makes the cloth billow, and the
  force follows the local normal (saft's wind is a per-vertex acceleration that does not);
* kinematic vertices (pins, and a grabbed corner moved along a path): inverse mass 0, placed on their
  target before every substep.

``newton`` and ``warp`` are imported lazily (the optional ``bench`` extra: ``pip install -e .[bench]``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

AIR_DENSITY = 1.2  # kg/m³


@dataclass(frozen=True)
class NewtonClothParams:
    density: float = 0.15             # kg/m² (a light cotton)
    tri_ke: float = 1000.0            # membrane Lamé μ, N/m
    tri_ka: float = 1000.0            # membrane Lamé λ, N/m
    tri_kd: float = 2e-5              # membrane damping (Rayleigh, s)
    edge_ke: float = 2e-4             # dihedral bending stiffness
    edge_kd: float = 1e-6             # bending damping
    drag_normal: float = 1.2          # C_n: pressure coefficient along the normal
    drag_tangent: float = 0.02        # C_t: skin friction, kg/(m² s)
    substeps: int = 20                # per frame (10 leaves a 3x-stretched edge beside a held clip)
    iterations: int = 10              # VBD iterations per substep
    self_contact: bool = False
    contact_margin: float = 0.004     # m: self-contact interaction distance
    gravity: tuple[float, float, float] = (0.0, -9.81, 0.0)


# wind(points (N, 3), time s) -> wind velocity (N, 3) in m/s
WindFn = Callable[[np.ndarray, float], np.ndarray]
# kinematic(time s) -> positions (K, 3) of the kinematic vertices
KinematicFn = Callable[[float], np.ndarray]


def aero_forces(x: np.ndarray, v: np.ndarray, triangles: np.ndarray, wind: np.ndarray,
                params: NewtonClothParams) -> np.ndarray:
    """Per-vertex aerodynamic forces (V, 3) in N: x, v (V, 3) positions and velocities, wind (T, 3) the wind
    velocity at each triangle's centroid."""
    a, b, c = x[triangles[:, 0]], x[triangles[:, 1]], x[triangles[:, 2]]
    cross = np.cross(b - a, c - a)
    area2 = np.linalg.norm(cross, axis=1, keepdims=True)
    n = cross / np.maximum(area2, 1e-12)
    area = 0.5 * area2
    v_rel = wind - v[triangles].mean(axis=1)
    vn = np.sum(v_rel * n, axis=1, keepdims=True)
    f = 0.5 * AIR_DENSITY * params.drag_normal * area * vn * np.abs(vn) * n
    f += params.drag_tangent * area * (v_rel - vn * n)
    out = np.zeros_like(x)
    for k in range(3):
        np.add.at(out, triangles[:, k], f / 3.0)
    return out


def simulate_newton_cloth(vertices: np.ndarray, triangles: np.ndarray, num_frames: int, frame_dt: float,
                          params: NewtonClothParams = NewtonClothParams(), kinematic: np.ndarray | None = None,
                          kinematic_path: KinematicFn | None = None, wind: WindFn | None = None,
                          initial_velocity: np.ndarray | None = None) -> np.ndarray:
    """Simulate a triangle cloth from rest pose `vertices` (V, 3) with VBD: positions (num_frames, V, 3),
    positions[0] = vertices. `kinematic` indices are not simulated: they stay put, or follow
    `kinematic_path(t)`; `wind(points, t)` is the air's velocity (None: still air, drag only)."""
    import warp as wp  # lazy: the optional `bench` extra

    wp.config.quiet = True  # before newton's import initialises warp (else it prints its banner and every load)
    import newton

    vertices = np.asarray(vertices, dtype=np.float64)
    triangles = np.asarray(triangles, dtype=np.int64)
    builder = newton.ModelBuilder(up_axis=newton.Axis.Y, gravity=tuple(float(g) for g in params.gravity))
    builder.add_cloth_mesh(pos=wp.vec3(0.0, 0.0, 0.0), rot=wp.quat_identity(), scale=1.0, vel=wp.vec3(0.0, 0.0, 0.0),
                           vertices=[wp.vec3(*p) for p in vertices], indices=triangles.ravel().tolist(),
                           density=params.density, tri_ke=params.tri_ke, tri_ka=params.tri_ka, tri_kd=params.tri_kd,
                           edge_ke=params.edge_ke, edge_kd=params.edge_kd,
                           particle_radius=params.contact_margin)
    kin = np.zeros(0, np.int64) if kinematic is None else np.asarray(kinematic, dtype=np.int64)
    for i in kin:
        builder.particle_mass[int(i)] = 0.0
    builder.color(include_bending=True)
    model = builder.finalize(device="cpu")
    contact = {}
    if params.self_contact:
        contact = dict(particle_enable_self_contact=True, particle_self_contact_margin=params.contact_margin,
                       particle_self_contact_gap=0.5 * params.contact_margin)
    solver = newton.solvers.SolverVBD(model, iterations=params.iterations, **contact)
    state, nxt, control = model.state(), model.state(), model.control()
    if initial_velocity is not None:
        state.particle_qd.assign(np.asarray(initial_velocity, np.float32))
    dt = frame_dt / params.substeps
    out = [vertices.copy()]
    for f in range(num_frames - 1):
        for s in range(params.substeps):
            t = (f * params.substeps + s) * dt
            if kinematic_path is not None and len(kin):
                q = state.particle_q.numpy()
                q[kin] = kinematic_path(t + dt)  # where the kinematic vertices are at the end of this substep
                state.particle_q.assign(q)
            x, v = state.particle_q.numpy().astype(np.float64), state.particle_qd.numpy().astype(np.float64)
            centroids = x[triangles].mean(axis=1)
            air = np.zeros_like(centroids) if wind is None else wind(centroids, t)
            force = aero_forces(x, v, triangles, air, params)
            force[kin] = 0.0
            state.clear_forces()
            state.particle_f.assign(force.astype(np.float32))
            solver.step(state, nxt, control, None, dt)
            state, nxt = nxt, state
        x = state.particle_q.numpy().astype(np.float64)
        if not np.all(np.isfinite(x)):
            raise FloatingPointError(f"Newton VBD cloth diverged at frame {f + 1}")
        out.append(x)
    return np.stack(out)
