"""Does a cloth sequence interpenetrate or pass through itself? Counts per frame, for saft's meshes and the truth.

    python benchmarks/diagnose_self_contact.py SCENE_DIR [RESULT_DIR ...] [--distance 0.004] [--rest-min 2.5]

SCENE_DIR: a scene with gt_vertices.npy (an independent-simulator scene: its n × n ground truth, row-major,
is scored both on its own grid and resampled onto the template's grid, as diagnose_independent.py reads
it); RESULT_DIR: saft results of it (meshes/frame_XXX.obj). Per frame and sequence:

- close: pairs of vertices further apart than --rest-min template grid spacings on the rest (flat)
  cloth, i.e. not neighbours, closer than --distance (m) in 3-D: layers touching or interpenetrating;
- gap: the smallest distance, mm, between vertices further than --gap-rest spacings apart at rest (two
  layers approaching; 50 = none within 5 cm);
- x-tri: pairs of triangles sharing no vertex that intersect (an edge of one crosses the other):
  the surface passes through itself;
- flipped (results only): of the pairs of vertices that are close in the truth (non-neighbours within
  --layer m: a flap lying on the cloth), those whose layer order in the result is the reverse of the
  truth's (the sign of (x_i - x_j) · n_j differs, both pairs at least 1 mm off the other's tangent
  plane): the result's flap lies on the wrong side, i.e. it passed through.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from saft.evaluate.self_contact import crossing_triangles, far_pairs, min_gap, side
from saft.scene import read_obj
from saft.synthetic.hanging_cloth import grid_template
from saft.synthetic.independent_scenes import resample_grid


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("scene", type=Path)
    p.add_argument("results", type=Path, nargs="*")
    p.add_argument("--distance", type=float, default=0.004, help="m: closer than this counts as touching")
    p.add_argument("--rest-min", type=float, default=2.5, help="template grid spacings apart at rest: not neighbours")
    p.add_argument("--gap-rest", type=float, default=6.0, help="template spacings apart at rest for the gap row")
    p.add_argument("--layer", type=float, default=0.015, help="m: truth pairs this close are a flap on the cloth")
    p.add_argument("--json", type=Path, help="write the per-frame counts here")
    args = p.parse_args()
    spec = json.loads((args.scene / "generator.json").read_text())["spec"]
    size, m = spec["size"], spec["grid"]
    gt = np.load(args.scene / "gt_vertices.npy")
    n = round(gt.shape[1] ** 0.5)   # the model-matched twins' truth is on the template's own grid
    tpl = grid_template(m, size)
    tri_m, rest_m = np.asarray(tpl.triangles), np.asarray(tpl.vertices)
    g = grid_template(n, size)
    tri_n, rest_n = np.asarray(g.triangles), np.asarray(g.vertices)
    rest_min = args.rest_min * size / (m - 1)
    gap_rest = args.gap_rest * size / (m - 1)
    truth = np.stack([resample_grid(f.reshape(n, n, 3), m) for f in gt])
    rows = {"truth (n x n)": [], "truth (template)": []}
    for f in range(len(gt)):
        rows["truth (n x n)"].append((len(far_pairs(rest_n, gt[f], args.distance, rest_min)),
                                      crossing_triangles(gt[f], tri_n), None, min_gap(rest_n, gt[f], gap_rest)))
        rows["truth (template)"].append((len(far_pairs(rest_m, truth[f], args.distance, rest_min)),
                                         crossing_triangles(truth[f], tri_m), None,
                                         min_gap(rest_m, truth[f], gap_rest)))
    for r in args.results:
        out = []
        for f in range(len(gt)):
            pos = np.asarray(read_obj(r / "meshes" / f"frame_{f:03d}.obj").vertices, dtype=np.float64)
            layer = far_pairs(rest_m, truth[f], args.layer, rest_min)
            flipped = None
            if len(layer):
                st, sr = side(truth[f], tri_m, layer), side(pos, tri_m, layer)
                both = (st != 0) & (sr != 0)
                flipped = (int(((st != sr) & both).all(1).sum()), int(both.all(1).sum()))
            out.append((len(far_pairs(rest_m, pos, args.distance, rest_min)), crossing_triangles(pos, tri_m), flipped,
                        min_gap(rest_m, pos, gap_rest)))
        rows[str(r)] = out
    print(f"{args.scene.name}: close = non-neighbour vertex pairs < {1000 * args.distance:.1f} mm "
          f"(> {args.rest_min} spacings apart at rest), x-tri = intersecting triangle pairs, "
          f"flipped = truth-layer pairs (< {1000 * args.layer:.0f} mm in the truth) on the wrong side / scored")
    for name, out in rows.items():
        print(f"== {name}")
        print("  close  " + " ".join(f"{c:4d}" for c, _, _, _ in out) + f"   frames>0: {sum(c > 0 for c, _, _, _ in out)}")
        print("  x-tri  " + " ".join(f"{x:4d}" for _, x, _, _ in out) + f"   frames>0: {sum(x > 0 for _, x, _, _ in out)}")
        print("  gap mm " + " ".join(f"{1000 * g:4.0f}" for _, _, _, g in out))
        if any(fl is not None for _, _, fl, _ in out):
            print("  flipped " + " ".join("   -" if fl is None else f"{fl[0]}/{fl[1]}" for _, _, fl, _ in out))
    if args.json:
        args.json.write_text(json.dumps({k: [list(x) for x in v] for k, v in rows.items()}, default=list))


if __name__ == "__main__":
    main()
