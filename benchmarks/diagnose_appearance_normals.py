"""How far saft's own motion is from the truth where phase 3 looks: positions and shading normals (issue 28).

For each appearance scene bench_appearance cached under --root (a scene and its ``-shape`` run), per frame:
the distance of saft's template vertices to the truth at the same material points, and the angle between
their vertex normals and the true ones. The truth is the template-topology motion (true_motion_on_template:
Newton's fine mesh resampled to the template's vertices, or the template's own truth); where the scene has
its own finer ground-truth mesh (gt_mesh.obj, a regular grid as the template's), the true normals are that
mesh's, resampled to the template's material points, and the angle of the resampled truth's own normals to
them is given too (what the "true motion" row of phase 3 starts from).

    PYTHONPATH=src python3 benchmarks/diagnose_appearance_normals.py --root /tmp/appnewton --motion newton
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from saft.evaluate.appearance import true_geometry
from saft.scene import load_scene
from saft.scene.mesh import read_obj, vertex_normals
from saft.synthetic.appearance import true_motion_on_template
from saft.synthetic.independent_scenes import resample_grid


def angles(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Per-vertex angle (degrees) between normal fields (V, 3), sign-blind (the cloth is two-sided)."""
    a = a / np.linalg.norm(a, axis=1, keepdims=True)
    b = b / np.linalg.norm(b, axis=1, keepdims=True)
    return np.degrees(np.arccos(np.clip(np.abs(np.sum(a * b, axis=1)), 0.0, 1.0)))


def true_normals(scene_dir: Path, template, on_template: np.ndarray) -> np.ndarray:
    """(F, V, 3) true vertex normals at the template's vertices."""
    verts, triangles, _ = true_geometry(scene_dir, template)
    if verts.shape[1] == template.num_vertices:
        return np.stack([vertex_normals(v, template.triangles) for v in on_template])
    n, m = int(round(np.sqrt(verts.shape[1]))), int(round(np.sqrt(template.num_vertices)))
    return np.stack([resample_grid(vertex_normals(v, triangles).reshape(n, n, 3), m) for v in verts])


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--root", required=True, help="bench_appearance's --root")
    ap.add_argument("--motion", default="saft", help="the scenes' motion suffix (saft: none)")
    args = ap.parse_args(argv)
    suffix = "" if args.motion == "saft" else f"_{args.motion}"
    print("| scene | position error, mean / last frame (cm) | normal error of saft's motion, mean / median / p90 / "
          "worst frame's mean (deg) | the resampled truth's own (deg) |")
    print("|---|---|---|---|")
    for scene_dir in sorted(Path(args.root, "scenes").glob(f"*{suffix}")):
        if not suffix and "_newton" in scene_dir.name:
            continue
        shape = Path(args.root, "results", f"{scene_dir.name}-shape", "meshes")
        if not shape.is_dir():
            continue
        template = load_scene(scene_dir).template
        truth = true_motion_on_template(scene_dir)
        own = np.stack([read_obj(p).vertices for p in sorted(shape.glob("frame_*.obj"))])
        normals = true_normals(scene_dir, template, truth)
        dist = 100 * np.linalg.norm(own - truth, axis=2).mean(axis=1)
        err = np.stack([angles(vertex_normals(v, template.triangles), n) for v, n in zip(own, normals)])
        own_err = np.stack([angles(vertex_normals(v, template.triangles), n) for v, n in zip(truth, normals)])
        print(f"| {scene_dir.name} | {dist.mean():.2f} / {dist[-1]:.2f} | {err.mean():.1f} / {np.median(err):.1f} / "
              f"{np.percentile(err, 90):.1f} / {err.mean(axis=1).max():.1f} (frame {int(err.mean(axis=1).argmax())}) "
              f"| {own_err.mean():.1f} / {np.percentile(own_err, 90):.1f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
