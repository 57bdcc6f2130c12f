"""Benchmark scenes without the inverse crime: cloth simulated by NVIDIA Newton (VBD, FEM membrane) on a mesh
finer than the template, path-traced by the Mitsuba renderer of ``benchmark_scenes`` (issue 29).

Each scenario is simulated twice:

* ``independent``: Newton's VBD (``saft.synthetic.newton_cloth``) on a 40 × 40 ground-truth mesh (the
  template is 25 × 25), Neo-Hookean membrane, dihedral bending, aerodynamic pressure and air drag, and VBD
  self-contact (4 mm margin) in every scenario: without it the truth of the one corner, the flag, both gusts
  and the corners passes through itself (a flap or a tight crease crosses the cloth: 5 to 23 of 32 frames,
  benchmarks/diagnose_self_contact.py), i.e. is not the motion of a real cloth. Nothing of saft's model made
  these.
* ``matched`` (the model-matched twin): saft's own simulator on the template's own mesh, driven by the same
  pins, the same grabbed corner and the aerodynamic accelerations that the independent cloth felt (per
  frame, resampled to the template's vertices), as ``benchmark_scenes`` does.

Scenarios (positions in metres; the camera looks at the cloth from +z):

* ``gust``: hanging from its top edge in a light breeze; at 0.5 s a gust from behind makes it billow towards
  the camera, a wave travelling along it ripples the hem; 30 fps.
* ``flag``: held along its left edge, falls under gravity while a wind along +x with a turbulent part makes
  the free edge flutter and curl; 60 fps.
* ``corners``: held at its two top corners, released tilted 55° towards the camera: swings through the
  vertical, its top edge sags between the corners; lateral breeze; 30 fps.
* ``one_corner``: held at its top-left corner only, swings down and sideways; light breeze; 30 fps.
* ``fold``: hanging from its top edge, the free bottom-left corner is grabbed and carried up and across
  towards the camera: the cloth folds over and shows its back; 30 fps.
* ``gust_side``: hanging from its top edge, a gust from the side and behind arrives late (0.45 s) and turns
  and lifts the free bottom-right corner; 30 fps.

Each simulation is written as ``<scenario>_<simulator>_pinned`` (held template vertices in scene.json) and
``..._unpinned`` (the paper's setting), both with the same video; the kinematic grabbed corner is never
listed (it moves). Corners are held by clips of 3 cm (every vertex within ``Scenario.clip``), not by one
vertex, whose point load stretched the membrane beside it 3×.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np
import torch
from scipy.interpolate import RegularGridInterpolator

from saft.evaluate.metrics import sample_surface
from saft.physics import ClothTopology, PhysicsParams, rollout
from saft.scene.camera import Camera, look_at
from saft.scene.frames import FrameSequence
from saft.scene.mesh import QuadMesh
from saft.scene.scene import Scene
from saft.synthetic.benchmark_scenes import DONE_FILE, bezier, smooth_ramp, write_scene_folder, render_video
from saft.synthetic.hanging_cloth import grid_template
from saft.synthetic.newton_cloth import NewtonClothParams, aero_forces, simulate_newton_cloth

SCENARIOS = {
    "gust": "hanging from its top edge; a late gust from behind billows it towards the camera, the hem ripples (30 fps)",
    "flag": "held along its left edge, falls while a turbulent wind along it makes the free edge flutter and curl "
            "(60 fps)",
    "corners": "held at its two top corners, released tilted 55 deg towards the camera, swings; lateral breeze (30 fps)",
    "one_corner": "held at its top-left corner only, swings down and sideways in a light breeze (30 fps)",
    "fold": "hanging from its top edge; the free bottom-left corner is grabbed and carried up across towards the "
            "camera, the cloth folds over and shows its back (30 fps)",
    "gust_side": "hanging from its top edge; a late gust from the side and behind turns and lifts the free "
                 "bottom-right corner (30 fps)",
}
SIMULATORS = ("independent", "matched")
VARIANTS = ("pinned", "unpinned")
GRAVITY = np.array([0.0, -9.81, 0.0])
FPS = {"flag": 60}


@dataclass(frozen=True)
class IndependentSceneSpec:
    gt_grid: int = 40              # ground-truth (Newton) vertices per side
    grid: int = 25                 # template vertices per side
    size: float = 0.4              # metres
    frames: int = 32
    width: int = 320               # image, pixels
    height: int = 240
    spp: int = 64                  # Mitsuba samples per pixel
    max_depth: int = 3             # direct light with shadows plus one indirect bounce
    texture_size: int = 512
    gt_points: int = 4000          # surface points per ground-truth frame
    # Newton's own self-contact in every scenario (issue 29): with it off the one corner, flag, gusts and corners
    # cross themselves; the fold, which never comes near itself, is the same either way
    newton: NewtonClothParams = NewtonClothParams(self_contact=True)
    # the model-matched twin: saft's simulator (as benchmark_scenes.BenchSceneSpec)
    substeps: int = 8
    log10_Y: float = 2.5
    log10_B: float = -3.4
    log10_S: float = -3.5
    damping: float = 0.995          # per substep (saft's 0.97 overdamps a swing)
    seed: int = 0


def scene_names(scenarios=tuple(SCENARIOS), simulators=SIMULATORS, variants=VARIANTS) -> list[str]:
    """Folder names: gust_independent_pinned, gust_independent_unpinned, gust_matched_pinned, ..."""
    return [f"{s}_{m}_{v}" for s in scenarios for m in simulators for v in variants]


def split_name(name: str) -> tuple[str, str, str]:
    """(scenario, simulator, variant) of a folder name."""
    for m in SIMULATORS:
        for v in VARIANTS:
            suffix = f"_{m}_{v}"
            if name.endswith(suffix) and name[: -len(suffix)] in SCENARIOS:
                return name[: -len(suffix)], m, v
    raise ValueError(f"not an independent-scene name: {name!r}")


# ------------------------------------------------------------------------------------------- scenarios
@dataclass(frozen=True)
class Scenario:
    rest: np.ndarray                      # (n, n, 3) rest (and start) positions on the unit material grid
    held: list[tuple[float, float]]       # (row, col) of the static points in material units (0..1)
    grab: tuple[float, float] | None      # (row, col) of the grabbed vertex, or None
    grab_path: object                     # t -> (3,) position of the grabbed vertex
    wind: object                          # (points (N, 3), t) -> wind velocity (N, 3), m/s
    fps: int
    clip: float = 0.0                     # radius (material units) held around each point


def _wind_gust(late: float, peak: float, lateral: float, direction=(0.0, 0.0, 1.0)):
    d = np.asarray(direction, dtype=np.float64) / np.linalg.norm(direction)

    def wind(p: np.ndarray, t: float) -> np.ndarray:
        x, y = p[:, 0:1], p[:, 1:2]
        breeze = 0.35 * (1 + 0.3 * np.sin(2 * np.pi * (1.3 * t - 2.5 * x)))
        g = smooth_ramp(np.asarray(t - late), 0.15)
        wave = 1 + 0.35 * np.sin(2 * np.pi * (3.0 * t - 4.0 * x + 1.5 * y))
        w = (breeze + peak * g * wave) * d[None]
        w[:, 0:1] += lateral * g * np.sin(2 * np.pi * 2.2 * t)
        return w
    return wind


def scenario(name: str, spec: IndependentSceneSpec) -> Scenario:
    """The rest shape (on a 2-D material grid), held points, grabbed corner and wind of one scenario."""
    h = spec.size / 2
    n = 64  # rest-shape grid resolution, resampled to both meshes
    flat = grid_template(n, spec.size).vertices.reshape(n, n, 3)
    top = [(0.0, c) for c in np.linspace(0, 1, 2 * spec.gt_grid)]
    still = lambda t: None  # noqa: E731
    if name == "gust":
        return Scenario(flat, top, None, still, _wind_gust(0.5, 1.6, 0.5), 30)
    if name == "gust_side":
        return Scenario(flat, top, None, still, _wind_gust(0.45, 1.8, 0.4, (0.8, 0.15, 0.6)), 30)
    if name == "flag":
        def wind(p, t):
            x, y = p[:, 0], p[:, 1]
            w = np.zeros_like(p)
            w[:, 0] = 3.0 * smooth_ramp(np.asarray(t), 0.1)
            w[:, 2] = 1.2 * np.sin(2 * np.pi * (4.0 * t - 5.0 * x) + 3.0 * y)
            return w
        left = [(r, 0.0) for r in np.linspace(0, 1, 2 * spec.gt_grid)]
        return Scenario(flat, left, None, still, wind, 60)
    if name == "corners":
        tilted = flat.copy()  # rotated about the top edge, the lower part towards the camera (+z)
        drop = h - flat[..., 1]
        tilted[..., 1], tilted[..., 2] = h - drop * np.cos(np.radians(55.0)), drop * np.sin(np.radians(55.0))
        breeze = lambda p, t: np.tile([1.2 * np.sin(2 * np.pi * t / 0.9), 0.0, 0.3], (len(p), 1))  # noqa: E731
        return Scenario(tilted, [(0.0, 0.0), (0.0, 1.0)], None, still, breeze, 30, 0.07)
    if name == "one_corner":
        breeze = lambda p, t: np.tile([0.0, 0.0, 0.6 + 0.3 * np.sin(2 * np.pi * t / 0.7)], (len(p), 1))  # noqa: E731
        return Scenario(flat, [(0.0, 0.0)], None, still, breeze, 30, 0.07)
    if name == "fold":
        duration = (spec.frames - 1) / 30

        def path(t):
            s = smooth_ramp(np.atleast_1d(t - 0.06), 0.8 * duration)
            return bezier(np.array([-h, -h, 0.0]), np.array([-h, -0.5 * h, 1.4 * h]),
                           np.array([0.1 * h, 0.45 * h, 0.9 * h]), s)[0]
        breeze = lambda p, t: np.tile([0.0, 0.0, 0.2], (len(p), 1))  # noqa: E731
        return Scenario(flat, top, (1.0, 0.0), path, breeze, 30)
    raise ValueError(f"unknown scenario {name!r} (one of {', '.join(SCENARIOS)})")


def resample_grid(field: np.ndarray, m: int) -> np.ndarray:
    """Resample a field given on an n×n material grid (row 0 = top) onto an m×m grid: (m*m, C)."""
    n = field.shape[0]
    s = np.linspace(0, 1, n)
    interp = RegularGridInterpolator((s, s), field)
    t = np.linspace(0, 1, m)
    rr, cc = np.meshgrid(t, t, indexing="ij")
    return interp(np.stack([rr.ravel(), cc.ravel()], axis=1))


def grid_indices(points: list[tuple[float, float]], m: int, clip: float = 0.0) -> np.ndarray:
    """Vertex indices (row-major, m per row) nearest to material points (row, col) in 0..1, and those within
    `clip` (material units) of them: a corner held by a clip, not by one vertex (a point load stretches the
    membrane around it without bound)."""
    rc = np.stack(np.meshgrid(np.linspace(0, 1, m), np.linspace(0, 1, m), indexing="ij"), -1).reshape(-1, 2)
    near = [int(round(r * (m - 1))) * m + int(round(c * (m - 1))) for r, c in points]
    d = np.linalg.norm(rc[:, None] - np.asarray(points, dtype=np.float64)[None], axis=2).min(axis=1)
    return np.unique(np.concatenate([near, np.flatnonzero(d <= clip + 1e-9)])).astype(np.int64)


def meshes(sc: Scenario, spec: IndependentSceneSpec) -> tuple[QuadMesh, QuadMesh]:
    """(ground-truth mesh, template), both at the scenario's rest pose, with matching UVs."""
    gt = grid_template(spec.gt_grid, spec.size)
    tpl = grid_template(spec.grid, spec.size)
    return (replace(gt, vertices=resample_grid(sc.rest, spec.gt_grid)),
            replace(tpl, vertices=resample_grid(sc.rest, spec.grid)))


def _vertex_masses(mesh: QuadMesh, density: float) -> np.ndarray:
    tri = mesh.triangles
    v = mesh.vertices
    area = 0.5 * np.linalg.norm(np.cross(v[tri[:, 1]] - v[tri[:, 0]], v[tri[:, 2]] - v[tri[:, 0]]), axis=1)
    m = np.zeros(len(v))
    for k in range(3):
        np.add.at(m, tri[:, k], density * area / 3)
    return m


def simulate_independent(sc: Scenario, gt: QuadMesh, spec: IndependentSceneSpec) -> np.ndarray:
    """Newton VBD positions (F, V_gt, 3)."""
    kin = grid_indices(sc.held, spec.gt_grid, sc.clip)
    path = None
    if sc.grab is not None:
        g = grid_indices([sc.grab], spec.gt_grid)
        kin = np.append(kin, g)
        fixed = gt.vertices[kin[:-1]]
        path = lambda t: np.vstack([fixed, sc.grab_path(t)])  # noqa: E731
    return simulate_newton_cloth(gt.vertices, gt.triangles, spec.frames, 1.0 / sc.fps, spec.newton, kinematic=kin,
                                 kinematic_path=path, wind=sc.wind)


def felt_accelerations(gt: QuadMesh, positions: np.ndarray, sc: Scenario, spec: IndependentSceneSpec) -> np.ndarray:
    """(F-1, V_gt, 3) aerodynamic accelerations the independent cloth felt over each frame interval (at the
    mid-frame positions, with the frame's mean velocity)."""
    dt = 1.0 / sc.fps
    mass = _vertex_masses(gt, spec.newton.density)
    out = []
    for f in range(len(positions) - 1):
        x = 0.5 * (positions[f] + positions[f + 1])
        v = (positions[f + 1] - positions[f]) / dt
        wind = sc.wind(x[gt.triangles].mean(axis=1), (f + 0.5) * dt)
        out.append(aero_forces(x, v, gt.triangles, wind, spec.newton) / mass[:, None])
    return np.stack(out)


def simulate_matched(sc: Scenario, gt: QuadMesh, tpl: QuadMesh, gt_positions: np.ndarray,
                     spec: IndependentSceneSpec) -> np.ndarray:
    """saft's simulator on the template: positions (F, V_tpl, 3), driven like the independent cloth."""
    n, m = spec.gt_grid, spec.grid
    acc = felt_accelerations(gt, gt_positions, sc, spec)
    wind = np.stack([resample_grid(a.reshape(n, n, 3), m) for a in acc])
    pins = grid_indices(sc.held, m, sc.clip)
    targets = None
    if sc.grab is not None:
        pins = np.append(pins, grid_indices([sc.grab], m))
        t = np.arange(spec.frames) / sc.fps
        targets = np.repeat(tpl.vertices[pins][None], spec.frames, axis=0)
        targets[:, -1] = np.stack([sc.grab_path(ti) for ti in t])
    f64 = dict(dtype=torch.float64)
    topo = ClothTopology.from_quads(tpl.vertices, tpl.quads, dtype=torch.float64)
    params = PhysicsParams(*(torch.tensor(v, **f64) for v in (spec.log10_Y, spec.log10_B, spec.log10_S, spec.damping)),
                           torch.tensor(GRAVITY, **f64), torch.tensor(wind, **f64))
    with torch.no_grad():
        x = rollout(topo, torch.tensor(tpl.vertices, **f64), None, params, num_frames=spec.frames,
                    substeps=spec.substeps, frame_dt=1.0 / sc.fps, pinned=torch.as_tensor(pins),
                    pinned_positions=None if targets is None else torch.tensor(targets, **f64))
    return x.numpy()


# ------------------------------------------------------------------------------------ camera, writing
def independent_camera(spec: IndependentSceneSpec) -> Camera:
    k = spec.size / 0.4
    f = 1.7 * spec.height
    K = np.array([[f, 0, (spec.width - 1) / 2], [0, f, (spec.height - 1) / 2], [0, 0, 1.0]])
    return look_at((0.3 * k, 0.1 * k, 1.1 * k), (0.0, -0.06 * k, 0.06 * k), (0.0, 1.0, 0.0), K,
                   spec.width, spec.height)


def _spec_json(spec: IndependentSceneSpec) -> dict:
    return json.loads(json.dumps(asdict(spec)))


def is_complete(folder: str | Path, spec: IndependentSceneSpec) -> bool:
    """Whether `folder` holds a finished scene generated from this very spec."""
    try:
        return json.loads((Path(folder) / DONE_FILE).read_text()).get("spec") == _spec_json(spec)
    except (OSError, ValueError):
        return False


def write_scenario(root: str | Path, name: str, spec: IndependentSceneSpec = IndependentSceneSpec(),
                   simulators=SIMULATORS) -> list[Path]:
    """Simulate, render and write ``root/<name>_<simulator>_{pinned,unpinned}``."""
    root = Path(root)
    sc = scenario(name, spec)
    gt, tpl = meshes(sc, spec)
    camera = independent_camera(spec)
    gt_positions = simulate_independent(sc, gt, spec)
    held = grid_indices(sc.held, spec.grid, sc.clip)
    frames = FrameSequence((), None, spec.width, spec.height)
    written = []
    for sim in simulators:
        mesh, positions = (gt, gt_positions) if sim == "independent" else \
            (tpl, simulate_matched(sc, gt, tpl, gt_positions, spec))
        rgb, mask = render_video(mesh, positions, camera, spec)
        rng = np.random.default_rng(spec.seed + 1)
        gt_points = [sample_surface(p, mesh.triangles, spec.gt_points, rng) for p in positions]
        for variant in VARIANTS:
            folder = f"{name}_{sim}_{variant}"
            scene = Scene(name=folder, template=tpl, camera=camera, frames=frames, texture=None,
                          pinned=held if variant == "pinned" else None, frame_dt=1.0 / sc.fps, gravity=GRAVITY)
            info = {"scenario": name, "simulator": sim, "variant": variant, "description": SCENARIOS[name],
                    "gt_mesh_grid": int(round(np.sqrt(len(mesh.vertices)))), "spec": _spec_json(spec)}
            write_scene_folder(root / folder, scene, rgb, mask, gt_points, positions, info)
            written.append(root / folder)
    return written


def write_independent_scenes(root: str | Path, spec: IndependentSceneSpec = IndependentSceneSpec(),
                             scenarios=tuple(SCENARIOS), only_missing: bool = True) -> list[Path]:
    """Write every scenario's four folders under `root` (skipping those already made from `spec`)."""
    out = []
    for s in scenarios:
        folders = [Path(root) / f for f in scene_names((s,))]
        if not (only_missing and all(is_complete(f, spec) for f in folders)):
            write_scenario(root, s, spec)
        out += folders
    return out
