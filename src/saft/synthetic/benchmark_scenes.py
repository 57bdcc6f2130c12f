"""Benchmark scenes with ground truth: cloth simulated by saft's simulator and path-traced with shading.

Three scenarios (issue 11, item 4), each written twice as a native scene folder (README, "Scene format"):
``<name>_pinned`` with the held vertices in scene.json and ``<name>_unpinned`` without them (the paper's
setting); both hold the same video, template and ground truth.

* ``a``: a cloth hanging from its top edge (top row held), blown by wind that varies in time and space;
* ``b``: a cloth held at its two top corners, released from a pose tilted 55° towards the camera, so it
  swings down through the vertical to the far side (less damping than a and c), with a light lateral breeze;
* ``c``: a cloth hanging from its top edge whose free bottom-left corner is grabbed and pulled up towards
  the camera, so that the cloth folds over and shows its back (the grabbed corner is a kinematic vertex in
  the simulation and is not in ``pinned_vertices``: it moves).

The video is rendered by Mitsuba 3 (``saft.appearance.renderer.ClothRenderer``: two-sided principled BSDF,
rough and non-metallic with the procedural texture as base colour, under a coloured sky with a sun on the
camera's side, one indirect bounce, black background), so folds are shaded and the shading moves with the
cloth. The simulation uses a different substep count, stiffnesses and damping than saft's defaults.
Frame 0 is the template (the rest shape), at rest. Ground truth: gt/frame_*.npy surface samples (world
frame) and gt_vertices.npy, the simulated vertices (F, V, 3).

Usage: ``write_benchmark_scenes("/tmp/saft-bench-scenes", BenchSceneSpec())`` (benchmarks/bench_scenes.py
does this, then reconstructs and scores every scene).
"""

from __future__ import annotations

import json
import os
import shutil
import tempfile
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch

from saft.appearance.irradiance import env_direction
from saft.appearance.params import linear_to_srgb, srgb_to_linear
from saft.appearance.renderer import ClothRenderer
from saft.evaluate.metrics import sample_surface
from saft.io_utils import atomic_save_npy, atomic_write_json
from saft.physics import ClothTopology, PhysicsParams, rollout
from saft.render import render_cloth
from saft.scene.camera import Camera, look_at
from saft.scene.frames import FrameSequence
from saft.scene.mesh import QuadMesh
from saft.scene.native import write_native_scene
from saft.scene.scene import Scene
from saft.synthetic.hanging_cloth import grid_template, procedural_texture

SCENARIOS = {
    "a": "hanging from its top edge (top row held), blown by wind varying in time and space",
    "b": "held at its two top corners, released tilted 55 deg towards the camera: swings through the vertical to "
         "the far side, light lateral breeze",
    "c": "hanging from its top edge; the free bottom-left corner is grabbed and pulled up towards the camera, "
         "the cloth folds over and shows its back",
}
VARIANTS = ("pinned", "unpinned")
GRAVITY = np.array([0.0, -9.81, 0.0])
DONE_FILE = "generator.json"  # written last: a folder without it is incomplete


@dataclass(frozen=True)
class BenchSceneSpec:
    grid: int = 20                 # template vertices per side
    size: float = 0.4              # metres
    frames: int = 30
    frame_dt: float = 0.02
    image_size: int = 256          # square image, pixels
    spp: int = 64                  # Mitsuba samples per pixel
    max_depth: int = 3             # path length: 3 = direct light with shadows plus one indirect bounce
    texture_size: int = 512
    gt_points: int = 4000          # surface points per ground-truth frame
    substeps: int = 8              # simulator substeps per frame (saft reconstructs with 4)
    log10_Y: float = 2.5
    log10_B: float = -3.4
    log10_S: float = -3.5
    damping: float = 0.97          # per substep
    swing_damping: float = 0.995   # per substep, scene b (so that it swings past the vertical)
    wind: float = 14.0             # peak wind acceleration of scene a, m/s²
    seed: int = 0


def scene_names(scenarios=tuple(SCENARIOS)) -> list[str]:
    """Folder names: a_pinned, a_unpinned, b_pinned, ..."""
    return [f"{s}_{v}" for s in scenarios for v in VARIANTS]


# --------------------------------------------------------------------------------------------- motion
def smooth_ramp(t: np.ndarray, rise: float) -> np.ndarray:
    """0 → 1 smoothly (smootherstep) over [0, rise] seconds."""
    s = np.clip(t / rise, 0.0, 1.0)
    return s * s * s * (s * (6 * s - 15) + 10)


def wind_field(vertices: np.ndarray, frames: int, frame_dt: float, peak: float, seed: int) -> np.ndarray:
    """(frames-1, V, 3) wind accelerations: mostly along +z (towards the camera) with a travelling
    wave across the cloth, gusts in time and a lateral part that changes sign; ramped in from zero."""
    rng = np.random.default_rng(seed)
    t = (np.arange(frames - 1) + 0.5)[:, None] * frame_dt
    x, y = vertices[None, :, 0], vertices[None, :, 1]
    span = float(np.ptp(vertices[:, :2], axis=0).max())
    ph = rng.uniform(0, 2 * np.pi, 4)
    ramp = smooth_ramp(t, 0.12)
    gust = 0.75 + 0.25 * np.sin(2 * np.pi * t / 0.45 + ph[0])
    wave = np.sin(2 * np.pi * (1.6 * t - x / (1.3 * span)) + ph[1]) * np.cos(np.pi * y / span + ph[2])
    a = np.zeros((frames - 1, len(vertices), 3))
    a[..., 2] = peak * ramp * gust * (0.6 + 0.8 * wave)
    a[..., 0] = 0.5 * peak * ramp * np.sin(2 * np.pi * t / 0.5 + ph[3]) * (0.6 - y / span)
    return a


def _tilted(template: QuadMesh, degrees: float) -> QuadMesh:
    """The template rotated about its top edge so that its lower part comes towards the camera (+z)."""
    v = template.vertices.copy()
    top = v[:, 1].max()
    th = np.radians(degrees)
    drop = top - v[:, 1]
    v[:, 1] = top - drop * np.cos(th)
    v[:, 2] = drop * np.sin(th)
    return QuadMesh(v, template.quads, template.uvs)


def bezier(p0, p1, p2, s: np.ndarray) -> np.ndarray:
    s = s[:, None]
    return (1 - s) ** 2 * p0 + 2 * (1 - s) * s * p1 + s * s * p2


def simulate(scenario: str, spec: BenchSceneSpec, device="cpu") -> tuple[QuadMesh, np.ndarray, np.ndarray]:
    """Simulate one scenario: (template, vertices (F, V, 3) with vertices[0] = template, held vertices
    (the static ones, for scene.json))."""
    if scenario not in SCENARIOS:
        raise ValueError(f"unknown scenario {scenario!r} (one of {', '.join(SCENARIOS)})")
    n, F, dt = spec.grid, spec.frames, spec.frame_dt
    template = grid_template(n, spec.size)
    top_row = np.arange(n)
    wind = np.zeros((F - 1, n * n, 3))
    sim_pins, targets = top_row, None
    if scenario == "a":
        wind = wind_field(template.vertices, F, dt, spec.wind, spec.seed)
        held = top_row
    elif scenario == "b":
        template = _tilted(template, 55.0)
        held = np.array([0, n - 1])
        sim_pins = held
        wind = wind_field(template.vertices, F, dt, 1.0, spec.seed + 1) * np.array([5.0, 0.0, 0.8])
    else:
        held = top_row
        corner = (n - 1) * n  # bottom-left
        sim_pins = np.append(top_row, corner)
        h = spec.size / 2
        t = np.arange(F) * dt
        s = smooth_ramp(t - 0.06, 0.8 * (F - 1) * dt)
        path = bezier(np.array([-h, -h, 0.0]), np.array([-h, -0.5 * h, 1.4 * h]),
                      np.array([0.1 * h, 0.45 * h, 0.9 * h]), s)
        targets = np.repeat(template.vertices[sim_pins][None], F, axis=0)
        targets[:, -1] = path
    f64 = dict(dtype=torch.float64, device=device)
    topo = ClothTopology.from_quads(template.vertices, template.quads, device=device, dtype=torch.float64)
    damping = spec.swing_damping if scenario == "b" else spec.damping
    params = PhysicsParams(*(torch.tensor(v, **f64) for v in (spec.log10_Y, spec.log10_B, spec.log10_S, damping)),
                           torch.tensor(GRAVITY, **f64), torch.tensor(wind, **f64))
    with torch.no_grad():
        positions = rollout(topo, torch.tensor(template.vertices, **f64), None, params, num_frames=F,
                            substeps=spec.substeps, frame_dt=dt, pinned=torch.as_tensor(sim_pins, device=device),
                            pinned_positions=None if targets is None else torch.tensor(targets, **f64))
    return template, positions.cpu().numpy(), held


# ------------------------------------------------------------------------------------------ rendering
def bench_camera(spec: BenchSceneSpec) -> Camera:
    k = spec.size / 0.4
    f = 1.6 * spec.image_size
    c = (spec.image_size - 1) / 2
    K = np.array([[f, 0, c], [0, f, c], [0, 0, 1.0]])
    return look_at((0.3 * k, 0.12 * k, 1.1 * k), (0.0, -0.04 * k, 0.06 * k), (0.0, 1.0, 0.0), K,
                   spec.image_size, spec.image_size)


def sky_with_sun(height: int = 128, width: int = 256, sun=(-0.45, 0.65, 0.62)) -> np.ndarray:
    """A lat-long environment map (linear radiance, Mitsuba's convention: row 0 looks along +y, column u
    along (-sin φ, ·, cos φ) with φ = (2u - 1)π): a dim bluish sky, a darker warm ground and a small
    bright sun in direction `sun` (world frame; by default above, left and in front of the cloth, on the
    camera's side, so that it lights the cloth at a grazing angle and folds cast shading)."""
    th = (np.arange(height) + 0.5) / height * np.pi
    d = env_direction(th[:, None], ((np.arange(width) + 0.5) / width)[None, :])
    up = d[..., 1:2]
    env = 0.06 + np.array([0.08, 0.12, 0.24]) * np.clip(up, 0, 1) + np.array([0.10, 0.07, 0.04]) * np.clip(-up, 0, 1)
    s = np.asarray(sun, dtype=np.float64) / np.linalg.norm(sun)
    env = env + np.array([160.0, 145.0, 120.0]) * np.exp(300.0 * ((d @ s)[..., None] - 1))
    return env.astype(np.float32)


def render_video(template: QuadMesh, positions: np.ndarray, camera: Camera, spec: BenchSceneSpec,
                 device="cpu") -> tuple[np.ndarray, np.ndarray]:
    """sRGB frames (F, H, W, 3) path-traced by Mitsuba and coverage masks (F, H, W) from saft's rasterizer."""
    tex = procedural_texture(spec.texture_size, spec.seed)
    albedo = 0.85 * srgb_to_linear(torch.as_tensor(tex)).numpy()
    rough = np.full(tex.shape[:2], 0.75, np.float32)
    metal = np.zeros(tex.shape[:2], np.float32)
    return path_trace(template, positions, camera, (albedo, rough, metal), sky_with_sun(), spec.spp, spec.max_depth,
                      spec.seed, device)


def path_trace(template: QuadMesh, positions: np.ndarray, camera: Camera, maps, env: np.ndarray, spp: int,
               max_depth: int, seed: int = 0, device="cpu") -> tuple[np.ndarray, np.ndarray]:
    """sRGB frames (F, H, W, 3) of the cloth with maps (base colour linear, roughness, metallic) under the
    env map, path-traced by Mitsuba, and coverage masks (F, H, W) from saft's rasterizer."""
    albedo, rough, metal = maps
    renderer = ClothRenderer(template.triangles, template.uvs, camera, device=device, max_depth=max_depth,
                             map_shape=rough.shape[:2], env_shape=env.shape[:2])
    rgb = []
    for i, v in enumerate(positions):
        renderer.set_vertices(v)
        img = renderer.render_numpy(albedo, rough, metal, env, spp=spp, seed=seed * 1000 + i)
        rgb.append(linear_to_srgb(torch.as_tensor(img)).clamp(0, 1).numpy())
    with torch.no_grad():
        out = render_cloth(torch.tensor(positions, dtype=torch.float32), torch.as_tensor(template.triangles),
                           torch.as_tensor(template.uvs, dtype=torch.float32), torch.zeros(4, 4, 3), camera)
    mask = (out.mask > 0.5).to(torch.float32).numpy()
    return np.stack(rgb).astype(np.float32), mask.reshape(len(positions), camera.height, camera.width)


# ------------------------------------------------------------------------------------------- writing
def write_scene_folder(final: Path, scene: Scene, rgb, mask, gt_points, positions, info: dict, extra=None) -> None:
    """Write one scene folder into a temporary sibling and move it into place (no half-written folder);
    extra(tmp_folder), if given, writes more files into it first."""
    final.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{final.name}-", dir=final.parent))
    try:
        write_native_scene(tmp, scene, rgb, mask, ground_truth=gt_points)
        atomic_save_npy(tmp / "gt_vertices.npy", positions.astype(np.float32))
        if extra is not None:
            extra(tmp)
        atomic_write_json(tmp / DONE_FILE, info)
        if final.exists():
            shutil.rmtree(final)
        os.replace(tmp, final)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp)


def write_scenario(root: str | Path, scenario: str, spec: BenchSceneSpec = BenchSceneSpec(), device="cpu") -> list[Path]:
    """Simulate and render one scenario and write ``root/<scenario>_pinned`` and ``root/<scenario>_unpinned``."""
    root = Path(root)
    template, positions, held = simulate(scenario, spec, device)
    camera = bench_camera(spec)
    rgb, mask = render_video(template, positions, camera, spec, device)
    rng = np.random.default_rng(spec.seed + 1)
    gt_points = [sample_surface(p, template.triangles, spec.gt_points, rng) for p in positions]
    frames = FrameSequence((), None, spec.image_size, spec.image_size)
    written = []
    for variant in VARIANTS:
        name = f"{scenario}_{variant}"
        scene = Scene(name=name, template=template, camera=camera, frames=frames, texture=None,
                      pinned=held if variant == "pinned" else None, frame_dt=spec.frame_dt, gravity=GRAVITY)
        info = {"scenario": scenario, "variant": variant, "description": SCENARIOS[scenario], "spec": asdict(spec)}
        write_scene_folder(root / name, scene, rgb, mask, gt_points, positions, info)
        written.append(root / name)
    return written


def is_complete(folder: str | Path, spec: BenchSceneSpec) -> bool:
    """Whether `folder` holds a finished scene generated from this very spec."""
    path = Path(folder) / DONE_FILE
    try:
        return json.loads(path.read_text()).get("spec") == json.loads(json.dumps(asdict(spec)))
    except (OSError, ValueError):
        return False


def write_benchmark_scenes(root: str | Path, spec: BenchSceneSpec = BenchSceneSpec(), scenarios=tuple(SCENARIOS),
                           device="cpu", only_missing: bool = True) -> list[Path]:
    """Write both variants of every scenario under `root` (skipping those already made from `spec`)."""
    root = Path(root)
    out = []
    for s in scenarios:
        folders = [root / n for n in scene_names((s,))]
        if only_missing and all(is_complete(f, spec) for f in folders):
            out += folders
        else:
            out += write_scenario(root, s, spec, device)
    return out
