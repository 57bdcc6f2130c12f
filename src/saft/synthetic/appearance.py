"""Synthetic appearance scenes (like the paper's SR scenes) for tests and the benchmark.

A hanging 16×16-quad sheet with travelling sine waves (a stand-in until `saft.physics.rollout` drives the
benchmark), known SVBRDF maps and a known coloured environment map, rendered through Mitsuba at many spp.
World frame: y UP (Mitsuba's env-map up axis), the sheet hangs in the x-y plane, the camera looks along +z.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, replace
from functools import lru_cache
from pathlib import Path
from typing import Literal

import numpy as np
import torch

from saft.appearance.params import linear_to_srgb
from saft.appearance.renderer import ClothRenderer
from saft.evaluate.appearance import APPEARANCE_GT_DIR, GT_MESH_FILE, write_appearance_ground_truth
from saft.evaluate.metrics import sample_surface
from saft.scene.camera import Camera, look_at
from saft.scene.frames import FrameSequence
from saft.scene.mesh import QuadMesh, quad_triangles, write_obj
from saft.scene.scene import Scene
from saft.synthetic.benchmark_scenes import DONE_FILE, GRAVITY, BenchSceneSpec, write_scene_folder, path_trace, simulate
from saft.synthetic.fabrics import environment_map, fabric_maps
from saft.synthetic.hanging_cloth import grid_template
from saft.synthetic.independent_scenes import (IndependentSceneSpec, grid_indices, meshes, resample_grid, scenario,
                                               simulate_independent)
from saft.synthetic.newton_cloth import NewtonClothParams

TEMPLATE_MOTION_FILE = "gt_vertices_template.npy"  # Newton's motion resampled to the template (phase 3's truth)
RUN_SCENE_FILE = "scene_generator.json"  # a cached run's copy of its scene's DONE_FILE (the scene it was made of)


@dataclass
class SyntheticScene:
    vertices: np.ndarray      # (F, V, 3)
    triangles: np.ndarray     # (T, 3)
    quads: np.ndarray         # (Q, 4)
    uvs: np.ndarray           # (V, 2) OBJ convention
    camera: Camera
    diffuse: np.ndarray       # (S, S, 3) linear
    roughness: np.ndarray     # (S, S)
    metallic: np.ndarray      # (S, S)
    envmap: np.ndarray        # (He, We, 3) linear
    rgb: np.ndarray | None = None    # (F, H, W, 3) sRGB renders
    mask: np.ndarray | None = None   # (F, H, W)


def grid_sheet(n_quads: int = 16, size: float = 1.0):
    """A square sheet of n×n quads in the x-y plane centred at the origin, row 0 at the top; returns
    vertices, quads, uvs (saft.synthetic.hanging_cloth.grid_template)."""
    mesh = grid_template(n_quads + 1, size)
    return mesh.vertices, mesh.quads, mesh.uvs


def wave_motion(verts: np.ndarray, n_frames: int = 20, amplitude: float = 0.12, dt: float = 0.04) -> np.ndarray:
    """Travelling sine waves on a sheet hanging from its top edge (amplitude grows downwards)."""
    y = verts[:, 1]
    x = verts[:, 0]
    hang = (y.max() - y) / max(y.max() - y.min(), 1e-9)
    out = []
    for f in range(n_frames):
        t = f * dt
        dz = amplitude * hang * (np.sin(2 * np.pi * (1.1 * hang - 1.5 * t)) + 0.5 * np.sin(2 * np.pi * (0.8 * x + 0.9 * t)))
        dx = 0.05 * hang ** 2 * np.sin(2 * np.pi * 0.7 * t)
        v = verts.copy()
        v[:, 2] += dz
        v[:, 0] += dx
        v[:, 1] -= 0.5 * amplitude * hang * np.abs(np.sin(2 * np.pi * (1.1 * hang - 1.5 * t))) * 0.3
        out.append(v)
    return np.stack(out)


def ground_truth_maps(size: int = 128, seed: int = 0):
    """Diffuse with coloured checks and stripes, roughness and metallic with their own patterns."""
    rng = np.random.default_rng(seed)
    u, v = np.meshgrid(np.linspace(0, 1, size), np.linspace(0, 1, size))
    checks = ((np.floor(u * 6) + np.floor(v * 6)) % 2)[..., None]
    c1, c2 = np.array([0.65, 0.18, 0.12]), np.array([0.15, 0.35, 0.6])
    diffuse = checks * c1 + (1 - checks) * c2
    stripe = (np.sin(2 * np.pi * 14 * (u + 0.3 * v)) > 0.6)[..., None]
    diffuse = np.where(stripe, np.array([0.8, 0.75, 0.3]), diffuse)
    diffuse = np.clip(diffuse + 0.02 * rng.standard_normal(diffuse.shape), 0.02, 0.95)
    roughness = 0.35 + 0.4 * (0.5 + 0.5 * np.sin(2 * np.pi * 2 * v))
    metallic = np.where((u - 0.7) ** 2 + (v - 0.3) ** 2 < 0.03, 0.6, 0.0)
    return diffuse.astype(np.float32), roughness.astype(np.float32), metallic.astype(np.float32)


def ground_truth_envmap(height: int = 256, width: int = 512) -> np.ndarray:
    """A coloured sky: bluish top, warm ground, a bright sun-like blob (linear radiance)."""
    th = (np.arange(height) + 0.5) / height * np.pi          # 0 = +y (up)
    ph = (np.arange(width) + 0.5) / width * 2 * np.pi
    TH, PH = np.meshgrid(th, ph, indexing="ij")
    up = np.cos(TH)[..., None]
    sky = np.array([0.35, 0.5, 0.9]) * np.clip(up, 0, 1) + np.array([0.5, 0.4, 0.3]) * np.clip(-up, 0, 1) + 0.25
    d = np.stack([np.sin(TH) * np.cos(PH), np.cos(TH), np.sin(TH) * np.sin(PH)], -1)
    for direction, colour, sharp in (([0.3, 0.6, -0.75], [6.0, 5.0, 3.5], 40.0), ([-0.8, 0.2, -0.5], [1.0, 1.5, 2.5], 12.0)):
        s = np.asarray(direction) / np.linalg.norm(direction)
        sky = sky + np.asarray(colour) * np.exp(sharp * ((d @ s)[..., None] - 1))
    return sky.astype(np.float32)


def make_scene(n_frames: int = 20, image_size: int = 200, map_size: int = 128, n_quads: int = 16,
               env_shape=(256, 512), render_spp: int = 128, render: bool = True, device="cpu",
               seed: int = 0) -> SyntheticScene:
    """Build (and by default render) the synthetic scene; the images are sRGB, the masks exact coverage."""
    verts0, quads, uvs = grid_sheet(n_quads)
    motion = wave_motion(verts0, n_frames)
    tri = quad_triangles(quads)
    f = 1.25 * image_size
    K = np.array([[f, 0, (image_size - 1) / 2], [0, f, (image_size - 1) / 2], [0, 0, 1.0]])
    cam = look_at([0.35, 0.25, -1.7], [0.0, -0.05, 0.0], [0, 1, 0], K, image_size, image_size)
    diffuse, rough, metal = ground_truth_maps(map_size, seed)
    env = ground_truth_envmap(*env_shape)
    scene = SyntheticScene(motion, tri, quads, uvs, cam, diffuse, rough, metal, env)
    if render:
        scene.rgb, scene.mask = render_targets(scene, render_spp, device=device)
    return scene


def render_targets(scene: SyntheticScene, spp: int = 128, device="cpu", camera: Camera | None = None,
                   vertices: np.ndarray | None = None):
    """sRGB renders (F, H, W, 3) of the scene's ground-truth appearance and coverage masks (F, H, W)."""
    cam = camera or scene.camera
    verts = scene.vertices if vertices is None else vertices
    r = ClothRenderer(scene.triangles, scene.uvs, cam, device=device, map_shape=scene.roughness.shape,
                      env_shape=scene.envmap.shape[:2])
    white = np.ones_like(scene.diffuse)
    rgbs, masks = [], []
    for f in range(verts.shape[0]):
        r.set_vertices(verts[f])
        img = r.render_numpy(scene.diffuse, scene.roughness, scene.metallic, scene.envmap, spp=spp, seed=f)
        rgbs.append(linear_to_srgb(torch.as_tensor(img)).numpy())
        # coverage: a white, rough, non-metal cloth under a constant bright env → any hit is > 0
        cov = r.render_numpy(white, np.ones_like(scene.roughness), np.zeros_like(scene.metallic),
                             np.full_like(scene.envmap, 10.0), spp=16, seed=f)
        masks.append((cov.max(axis=2) > 1e-3).astype(np.float32))
    return np.stack(rgbs).astype(np.float32), np.stack(masks).astype(np.float32)


# ---------------------------------------------------------------------- benchmark scenes with appearance GT
@dataclass(frozen=True)
class AppearanceSceneSpec:
    """A cloth in wind path-traced with a fabric's maps under the "video" environment; see
    write_appearance_scene. The motion is saft's simulator's (benchmark_scenes scenario "a", on the
    template's own mesh) or, with motion = "newton", NVIDIA Newton's (independent_scenes scenario "gust":
    hanging from its top edge, a late gust from behind billows it towards the camera; on a `gt_grid`-sided
    mesh finer than the template, at the scenario's 30 fps, so `frame_dt` is not used). start > 0 drops the
    first `start` simulated frames: frame 0 (and the template) is then the cloth already moved by the wind,
    curved and shaded across (issue 28: a frame 0 whose folds the frame-0 irradiance has to divide out)."""

    fabric: str = "plaid"
    frames: int = 16
    width: int = 160
    height: int = 120
    grid: int = 17                 # template vertices per side
    size: float = 0.4              # metres
    frame_dt: float = 0.02         # saft's motion only (Newton's keeps its scenario's 1/30 s)
    spp: int = 64                  # samples per pixel of the video
    max_depth: int = 3             # direct light with shadows + one indirect bounce
    map_size: int = 512
    env_height: int = 64
    env_width: int = 128
    seed: int = 0
    start: int = 0                 # simulated frames before frame 0 (0: frame 0 is the flat rest shape)
    motion: Literal["saft", "newton"] = "saft"   # which simulator moves the cloth
    gt_grid: int = 40              # motion "newton": ground-truth mesh vertices per side
    # motion "newton": Newton's own self-contact (as the shape benchmark's scenes, IndependentSceneSpec.newton);
    # without it the gust's hem crease passes through the cloth in frames 13-20, which no real cloth does
    self_contact: bool = True


def appearance_camera(spec: AppearanceSceneSpec) -> Camera:
    """The scenes' camera: in front of the cloth (+z), a little to the right and above (square pixels)."""
    k = spec.size / 0.4
    f = 2.2 * spec.height
    K = np.array([[f, 0, (spec.width - 1) / 2], [0, f, (spec.height - 1) / 2], [0, 0, 1.0]])
    return look_at((0.3 * k, 0.12 * k, 1.1 * k), (0.0, -0.04 * k, 0.06 * k), (0.0, 1.0, 0.0), K, spec.width,
                   spec.height)


def appearance_motion(spec: AppearanceSceneSpec, device="cpu") -> tuple[QuadMesh, np.ndarray, np.ndarray]:
    """(template, vertices (frames, V, 3) on the template, held vertices) of the scene: its simulator run for
    start + frames frames, the first `start` dropped; the template is frame 0's shape (the rest shape itself
    when start = 0; else the moved cloth, as a real video's template is its first frame). With Newton's
    motion the vertices are the ground truth resampled to the template (newton_motion)."""
    if spec.motion == "newton":
        return newton_motion(spec)[:3]
    if spec.motion != "saft":
        raise ValueError(f"unknown motion {spec.motion!r} (saft or newton)")
    sim = BenchSceneSpec(grid=spec.grid, size=spec.size, frames=spec.start + spec.frames, frame_dt=spec.frame_dt,
                         seed=spec.seed)
    template, positions, held = simulate("a", sim, device)
    positions = positions[spec.start:]
    if spec.start:
        template = template.with_vertices(positions[0].copy())
    return template, positions, held


def newton_motion(spec: AppearanceSceneSpec) -> tuple[QuadMesh, np.ndarray, np.ndarray, QuadMesh, np.ndarray, float]:
    """Newton's cloth for the scene (independent_scenes: scenario "gust", its `simulate_independent` on a
    spec.gt_grid² mesh, the template spec.grid²; both grids over the same material square and UV layout):
    (template, the ground truth resampled to the template's vertices (frames, V, 3) (the same material
    points, as independent_scenes builds its template; the "true motion" phase 3 is fitted on), held
    template vertices (the top edge), the ground-truth mesh, its positions (frames, V_gt, 3), frame_dt).
    Both meshes are frame 0's shape (after `start` dropped frames)."""
    ind = IndependentSceneSpec(gt_grid=spec.gt_grid, grid=spec.grid, size=spec.size, frames=spec.start + spec.frames,
                               seed=spec.seed, newton=newton_params(spec))
    sc = scenario("gust", ind)
    gt, template = meshes(sc, ind)
    truth = _newton_gust(ind)[spec.start:]
    n = spec.gt_grid
    on_template = np.stack([resample_grid(p.reshape(n, n, 3), spec.grid) for p in truth])
    return (template.with_vertices(on_template[0].copy()), on_template, grid_indices(sc.held, spec.grid, sc.clip),
            gt.with_vertices(truth[0].copy()), truth, 1.0 / sc.fps)


@lru_cache(maxsize=1)
def _newton_gust(ind: IndependentSceneSpec) -> np.ndarray:
    """Newton's gust on ind's ground-truth mesh (F, V_gt, 3), kept for the next fabric (the same motion; read-only)."""
    sc = scenario("gust", ind)
    truth = simulate_independent(sc, meshes(sc, ind)[0], ind)
    truth.setflags(write=False)
    return truth


def newton_params(spec: AppearanceSceneSpec) -> NewtonClothParams:
    """Newton's cloth parameters for motion "newton": the shape benchmark's (IndependentSceneSpec.newton), with
    self-contact as spec.self_contact says."""
    return replace(IndependentSceneSpec().newton, self_contact=spec.self_contact)


def scene_info(spec: AppearanceSceneSpec) -> dict:
    """The identity written into a scene folder's DONE_FILE: a folder with the same one is kept. The fields
    added later are left out at their old value, so that the folders written before them stay valid; with
    Newton's motion it also holds every Newton parameter (self-contact among them), so that a clip simulated
    otherwise (the clips made before, without self-contact, recorded none) is made again."""
    info = {"kind": "appearance", "spec": asdict(spec)}
    if not spec.start:
        del info["spec"]["start"]
    if spec.motion == "saft":
        del info["spec"]["motion"], info["spec"]["gt_grid"], info["spec"]["self_contact"]
    else:
        info["newton"] = asdict(newton_params(spec))
    return json.loads(json.dumps(info))


def write_appearance_scene(folder, spec: AppearanceSceneSpec = AppearanceSceneSpec(), device="cpu"):
    """Simulate, render and write one scene folder with appearance ground truth (native layout, README
    "Scene format", plus ``appearance_gt/``: base_color.png (sRGB), roughness.png, metallic.png (linear),
    envmap_video.exr, envmap_unseen.exr (linear radiance), appearance_gt.json; gt_vertices.npy (F, V, 3);
    gt/frame_*.npy surface samples, so that `saft evaluate` scores the geometry too).
    With Newton's motion the video is rendered from the fine ground-truth mesh, whose rest topology and UVs
    are written as gt_mesh.obj (gt_vertices.npy and gt/ are that mesh's), and the truth resampled to the
    template as gt_vertices_template.npy (TEMPLATE_MOTION_FILE).
    A folder already written from this very spec is kept. Returns the folder."""
    folder = Path(folder)
    info = scene_info(spec)
    try:
        if json.loads((folder / DONE_FILE).read_text()) == info:
            return folder
    except (OSError, ValueError):
        pass
    if spec.motion == "newton":
        template, on_template, held, truth_mesh, truth, frame_dt = newton_motion(spec)
    else:
        template, truth, held = appearance_motion(spec, device)
        truth_mesh, on_template, frame_dt = template, None, spec.frame_dt
    camera = appearance_camera(spec)
    base, rough, metal = fabric_maps(spec.fabric, spec.map_size, spec.seed)
    env = environment_map("video", spec.env_height, spec.env_width)
    rgb, mask = path_trace(truth_mesh, truth, camera, (base, rough, metal), env, spec.spp, spec.max_depth, spec.seed,
                           device)
    scene = Scene(name=f"appearance_{spec.fabric}", template=template, camera=camera,
                  frames=FrameSequence((), None, spec.width, spec.height), texture=None, pinned=held,
                  frame_dt=frame_dt, gravity=GRAVITY)
    unseen = environment_map("unseen", spec.env_height, spec.env_width)

    def extra(tmp: Path) -> None:
        write_appearance_ground_truth(tmp / APPEARANCE_GT_DIR, base, rough, metal, env, unseen,
                                      {"fabric": spec.fabric, "max_depth": spec.max_depth})
        if on_template is not None:
            write_obj(tmp / GT_MESH_FILE, truth_mesh, comment="the ground-truth mesh at frame 0 (gt_vertices.npy's)")
            np.save(tmp / TEMPLATE_MOTION_FILE, on_template.astype(np.float32))

    rng = np.random.default_rng(spec.seed + 1)
    gt_points = [sample_surface(p, truth_mesh.triangles, 4000, rng) for p in truth]
    write_scene_folder(folder, scene, rgb, mask, gt_points, truth, info, extra=extra)
    return folder


def true_motion_on_template(folder) -> np.ndarray:
    """(F, V, 3) float64: the scene's true motion on the template's vertices (what phase 3 is fitted on in
    the "true motion" row): gt_vertices_template.npy where the truth has its own finer mesh, else
    gt_vertices.npy (the truth is the template's)."""
    folder = Path(folder)
    path = folder / TEMPLATE_MOTION_FILE
    return np.load(path if path.is_file() else folder / "gt_vertices.npy").astype(np.float64)


def run_is_current(run_dir, scene_dir, last_file: str) -> bool:
    """Whether a cached run of a scene (bench_appearance's texture and shape runs, `last_file` written last) was
    made from the scene folder as it is now: the scene's identity (DONE_FILE) copied into the run by mark_run is
    the scene's. A scene made again from another spec (e.g. Newton's clips, with self-contact) has a new one."""
    run_dir, scene_dir = Path(run_dir), Path(scene_dir)
    try:
        return ((run_dir / last_file).is_file()
                and (run_dir / RUN_SCENE_FILE).read_text() == (scene_dir / DONE_FILE).read_text())
    except OSError:
        return False


def mark_run(run_dir, scene_dir) -> None:
    """Record in a finished run which scene it was made of (run_is_current)."""
    (Path(run_dir) / RUN_SCENE_FILE).write_text((Path(scene_dir) / DONE_FILE).read_text())
