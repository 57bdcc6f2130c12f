"""Shape accuracy on cloth that saft's model did not make (issue 29): Newton VBD scenes and their model-matched twins.

    pip install -e ".[bench]"          # newton + warp-lang (CPU), for the independent simulator
    python benchmarks/bench_independent.py [--scenes-dir DIR] [--scenarios gust,flag,...] [--variants pinned,unpinned]
                                           [--simulators independent,matched] [--out DIR] [--noise-seed K[,K...]]
                                           [--frames N] [--spp N] [--start N] [--set key=value ...]

The scenes (saft.synthetic.independent_scenes: a late gust, a flag, a cloth held at two corners, at one
corner, a folded corner, a gust from the side) are generated into --scenes-dir (default
/tmp/saft-scenes/independent) when missing or made from another spec: once by NVIDIA Newton's VBD solver on a
40 × 40 ground-truth mesh ("independent"), once by saft's own simulator on the 25 × 25 template ("matched"),
both path-traced by Mitsuba at 320 × 240. Each is reconstructed with the default config (shape phases only,
as bench_scenes.py) and scored against its ground truth: CD2 as the paper defines it (both directions summed),
1e-4 m². Prints one line per scene, then the table (static template, independent, matched, their ratio) and
the per-frame curves; writes OUT/bench_independent.json. --start N > 0 reconstructs each scene without its
first N frames instead (saft.synthetic.mid_motion, written to SCENES-DIR/mid_motion_N/): a clip that starts
mid-motion, its template the ground truth of the new frame 0. The last line is
`independent_cd2_median=<median over the independent scenes> matched_cd2_median=<...>`.

--noise-seed K moves the template by 1e-9 m of seeded noise (0 = as given): a perturbation that should not
matter. A list (--noise-seed 0,1,2) runs every scene once per seed (OUT/seedK/SCENE) and scores each scene by
the median over its seeds (the issue's "median of perturbed runs"): some of these scenes move by 2-3x under
such a perturbation (BENCHMARKS.md, "Nineteenth session"), so one run of them says little.
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from dataclasses import asdict, replace
from pathlib import Path

from bench_scenes import run_scene

from saft.io_utils import atomic_write_json
from saft.synthetic.independent_scenes import (SCENARIOS, SIMULATORS, VARIANTS, IndependentSceneSpec, scene_names,
                                               write_independent_scenes)
from saft.synthetic.mid_motion import write_mid_motion_scene


def _list(value: str, known, what: str) -> list[str]:
    items = [v for v in value.split(",") if v]
    unknown = sorted(set(items) - set(known))
    if unknown:
        raise SystemExit(f"--{what}: unknown {', '.join(unknown)} (known: {', '.join(known)})")
    return items


def median_rows(rows: list[dict]) -> list[dict]:
    """One row per scene: its mean, last-frame and per-frame CD2 the medians over its seeds (the runs listed)."""
    by: dict[str, list[dict]] = {}
    for r in rows:
        by.setdefault(r["scene"], []).append(r)
    out = []
    for name, runs in by.items():
        row = dict(runs[0])
        if len(runs) > 1:
            row.pop("noise_seed")
            row.update(cd2_mean=statistics.median(r["cd2_mean"] for r in runs),
                       cd2_last=statistics.median(r["cd2_last"] for r in runs),
                       cd2_per_frame=[statistics.median(f) for f in zip(*(r["cd2_per_frame"] for r in runs))],
                       cd2_mean_runs=[r["cd2_mean"] for r in runs], noise_seeds=[r["noise_seed"] for r in runs])
        out.append(row)
    return out


def print_tables(rows: list[dict]) -> None:
    by = {r["scene"]: r for r in rows}
    print("\n| scene | static template | independent (Newton) | model-matched (saft) | ratio |")
    print("|---|---|---|---|---|")
    for name in dict.fromkeys(r["scene"].replace("_independent_", "|").replace("_matched_", "|") for r in rows):
        scenario, variant = name.split("|")
        ind, mat = by.get(f"{scenario}_independent_{variant}"), by.get(f"{scenario}_matched_{variant}")
        cell = lambda r: "" if r is None else f"{r['cd2_mean']:.3f} (last {r['cd2_last']:.2f})"  # noqa: E731
        ratio = f"{ind['cd2_mean'] / mat['cd2_mean']:.1f}" if ind and mat else ""
        static = ind or mat
        print(f"| {scenario} {variant} | {static['static_cd2_mean']:.2f} | {cell(ind)} | {cell(mat)} | {ratio} |")
    print("\nper-frame CD2 (1e-4 m²):")
    for r in rows:
        print(f"{r['scene']:30s} " + " ".join(f"{c:.2f}" for c in r["cd2_per_frame"]))


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--scenes-dir", type=Path, default=Path("/tmp/saft-scenes/independent"))
    p.add_argument("--scenarios", default=",".join(SCENARIOS))
    p.add_argument("--variants", default="pinned")
    p.add_argument("--simulators", default=",".join(SIMULATORS))
    p.add_argument("--out", type=Path, default=Path("bench-independent"))
    p.add_argument("--device", default="cpu")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    d = IndependentSceneSpec()
    p.add_argument("--frames", type=int, default=d.frames)
    p.add_argument("--spp", type=int, default=d.spp)
    p.add_argument("--noise-seed", default="0",
                   help="move the template by 1e-9 m noise of this seed (0 = no); a list 0,1,2: the median of the runs")
    p.add_argument("--start", type=int, default=0, help="drop the first N frames: a clip starting mid-motion")
    p.add_argument("--generate-only", action="store_true", help="write the scenes and stop")
    args = p.parse_args()
    try:
        seeds = [int(k) for k in args.noise_seed.split(",") if k]
    except ValueError:
        raise SystemExit(f"--noise-seed: integers separated by commas, got {args.noise_seed!r}") from None
    if not seeds or min(seeds) < 0:
        raise SystemExit(f"--noise-seed: seeds >= 0, got {args.noise_seed!r}")
    scenarios = _list(args.scenarios, SCENARIOS, "scenarios")
    names = scene_names(scenarios, _list(args.simulators, SIMULATORS, "simulators"),
                        _list(args.variants, VARIANTS, "variants"))
    spec = replace(d, frames=args.frames, spp=args.spp)
    t0, c0 = time.perf_counter(), time.process_time()
    write_independent_scenes(args.scenes_dir, spec, scenarios)
    print(f"scenes ready in {args.scenes_dir} ({time.perf_counter() - t0:.0f} s wall, "
          f"{time.process_time() - c0:.0f} s CPU)", flush=True)
    folders = [args.scenes_dir / n for n in names]
    if args.start > 0:
        folders = [write_mid_motion_scene(f, args.scenes_dir / f"mid_motion_{args.start}" / f.name, args.start)
                   for f in folders]
    if args.generate_only:
        return
    rows = []
    for folder in folders:
        for k in seeds:
            out = args.out / folder.name if len(seeds) == 1 else args.out / f"seed{k}" / folder.name
            rows.append({**run_scene(folder, out, args.device, args.set, k), "noise_seed": k})
            atomic_write_json(args.out / "bench_independent.json",
                              {"spec": json.loads(json.dumps(asdict(spec))), "start": args.start,
                               "overrides": args.set, "noise_seeds": seeds, "runs": rows,
                               "scenes": median_rows(rows)})
    rows = median_rows(rows)
    print_tables(rows)
    med = {m: statistics.median(r["cd2_mean"] for r in rows if f"_{m}_" in r["scene"])
           for m in SIMULATORS if any(f"_{m}_" in r["scene"] for r in rows)}
    print(" ".join(f"{m}_cd2_median={v:.4f}" for m, v in med.items()))


if __name__ == "__main__":
    main()
