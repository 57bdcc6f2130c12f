"""Benchmark of the differentiable cloth simulator (saft.physics).

Rollouts of the R1 template (32x32 quads, 1024 vertices; read from ../shared) and of synthetic 16x16 and
64x64 grids: 50 frames x 4 substeps, forward and forward+backward, with 1 and 2 torch threads.
Last line (machine-readable): physics_fwd_bwd_s_32x32_50f=<seconds> (median of the runs, best thread count).

    python benchmarks/bench_physics.py [--runs 3] [--frames 50] [--quick]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "src"))

from saft.physics import ClothTopology, PhysicsParams, rollout  # noqa: E402

R1 = ROOT / ".." / "shared" / "data" / "phi_sft" / "data" / "R1" / "0_R1_quad.obj"


def grid(n: int, size: float = 0.64):
    xs = np.linspace(0.0, size, n + 1)
    X, Yg = np.meshgrid(xs, xs, indexing="ij")
    verts = np.stack([X.ravel(), -Yg.ravel(), np.zeros(X.size)], axis=1)  # hanging in the x-y plane
    idx = np.arange((n + 1) ** 2).reshape(n + 1, n + 1)
    quads = np.stack([idx[:-1, :-1], idx[:-1, 1:], idx[1:, 1:], idx[1:, :-1]], axis=-1).reshape(-1, 4)
    return verts, quads


def load_case(name: str):
    if name == "32x32" and R1.is_file():
        from saft.scene.mesh import read_obj

        m = read_obj(R1)
        return "32x32 (R1)", m.vertices, m.quads
    n = int(name.split("x")[0])
    v, q = grid(n)
    return f"{name} (grid)", v, q


def run_once(topo, frames, backward: bool, seed=0):
    V = topo.num_vertices
    g = torch.Generator().manual_seed(seed)
    p = PhysicsParams.default(frames, V)
    p.a_vert = 0.5 * torch.randn(frames - 1, V, 3, generator=g, dtype=torch.float64)
    # wind-like forcing, no pins: as in the reconstruction (accelerations hold and move the cloth)
    for t_ in p.tensors():
        t_.requires_grad_(backward)
    w = torch.randn(frames, V, 3, generator=g, dtype=torch.float64)
    stats = {}
    t0 = time.perf_counter()
    pos = rollout(topo, topo.template, None, p, num_frames=frames, stats=stats)
    if backward:
        (pos * w).sum().backward()
    return time.perf_counter() - t0, stats


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--frames", type=int, default=50)
    ap.add_argument("--cases", default="16x16,32x32,64x64")
    ap.add_argument("--threads", default="1,2")
    args = ap.parse_args()
    threads = [int(t) for t in args.threads.split(",")]
    print(f"saft.physics benchmark: {args.frames} frames x 4 substeps, float64, median of {args.runs} runs")
    print(f"{'case':16s} {'V':>6s} {'thr':>3s} {'fwd_s':>8s} {'fwd+bwd_s':>10s}  solver (fwd+bwd run)")
    best32 = None
    for case in args.cases.split(","):
        label, verts, quads = load_case(case)
        topo = ClothTopology.from_quads(verts, quads)
        for nt in threads:
            torch.set_num_threads(nt)
            run_once(topo, 3, True)  # warm-up
            fwd = statistics.median(run_once(topo, args.frames, False)[0] for _ in range(args.runs))
            res = [run_once(topo, args.frames, True) for _ in range(args.runs)]
            fb = statistics.median(r[0] for r in res)
            print(f"{label:16s} {topo.num_vertices:6d} {nt:3d} {fwd:8.3f} {fb:10.3f}  {res[-1][1]}", flush=True)
            if case == "32x32":
                best32 = fb if best32 is None else min(best32, fb)
    if best32 is not None:
        print(f"physics_fwd_bwd_s_32x32_{args.frames}f={best32:.3f}")


if __name__ == "__main__":
    main()
