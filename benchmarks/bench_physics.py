"""Benchmark of the differentiable cloth simulator (saft.physics).

Rollouts of the R1 template (32x32 quads, 1024 vertices; read from ../shared) and of synthetic 16x16 and
64x64 grids: 50 frames x 4 substeps, forward and forward+backward, with 1 and 2 torch threads.
Reports wall and CPU (process) seconds, medians of --repeats runs, one table row per size and thread count.
Last line (machine-readable): physics_fwd_bwd_s_32x32_50f=<seconds> (median wall, best thread count).

    python benchmarks/bench_physics.py [--repeats 3] [--sizes 16x16,32x32,64x64] [--threads 1,2]
                                       [--frames 50] [--compile {0,1,env}] [--kernels {auto,numba,torch,env}]

With --device or --solver: the solver comparison of issue 27 instead (bench_physics_device.py), the first
size only (default 32x32), forward + backward, against the CPU default on the same input:

    python benchmarks/bench_physics.py --device cuda --solver all [--graphs 1|0|both] [--profile-frames 5]
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


def make_inputs(V, frames, seed=0, device="cpu", requires_grad=True):
    """(params, loss weights w) of the benchmark rollout: loss = sum(positions * w)."""
    g = torch.Generator().manual_seed(seed)
    p = PhysicsParams.default(frames, V)
    p.a_vert = 0.5 * torch.randn(frames - 1, V, 3, generator=g, dtype=torch.float64)
    # wind-like forcing, no pins: as in the reconstruction (accelerations hold and move the cloth)
    w = torch.randn(frames, V, 3, generator=g, dtype=torch.float64)
    p = PhysicsParams(*(t_.to(device).requires_grad_(requires_grad) for t_ in p.tensors()))
    return p, w.to(device)


def run_once(topo, frames, backward: bool, seed=0, compile=None, kernels=None, solver="auto", tol=1e-6,
             keep=False):
    """One rollout (and backward); returns (wall s, CPU s, solver stats), and with ``keep`` also the
    positions and the parameters' gradients (on the CPU)."""
    p, w = make_inputs(topo.num_vertices, frames, seed, topo.device, backward)
    stats = {}
    cuda = topo.device.type == "cuda"
    if cuda:
        torch.cuda.synchronize()
    c0, t0 = time.process_time(), time.perf_counter()
    pos = rollout(topo, topo.template, None, p, num_frames=frames, stats=stats, compile=compile, kernels=kernels,
                  solver=solver, tol=tol)
    if backward:
        (pos * w).sum().backward()
    if cuda:
        torch.cuda.synchronize()
    out = (time.perf_counter() - t0, time.process_time() - c0, stats)
    if keep:
        grads = [t_.grad.cpu() if backward else None for t_ in p.tensors()]
        out += (pos.detach().cpu(), grads)
    return out


def _fmt_stats(st):
    s = f"its {st.get('iterations', 0)}/{st.get('solves', 0)} fact {st.get('factorizations', 0)}"
    if "bwd_solves" in st:
        s += f" | bwd its {st['bwd_iterations']}/{st['bwd_solves']} fact {st['bwd_factorizations']}"
    return s


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repeats", "--runs", dest="repeats", type=int, default=3, help="runs per cell (median)")
    ap.add_argument("--frames", type=int, default=50)
    ap.add_argument("--sizes", "--cases", dest="sizes", default=None,
                    help="comma list of NxN (32x32 is the R1 template when ../shared has it); default "
                         "16x16,32x32,64x64, in the solver comparison 32x32")
    ap.add_argument("--threads", default="1,2", help="comma list of torch thread counts")
    ap.add_argument("--compile", choices=("0", "1", "env", "both"), default="env",
                    help="torch.compile the element kernels (env: SAFT_PHYSICS_COMPILE, off by default); in the "
                         "solver comparison also the CG blocks, and 'both' runs each solver without, then with")
    ap.add_argument("--kernels", choices=("auto", "numba", "torch", "env"), default="env",
                    help="element kernel backend (env: SAFT_PHYSICS_KERNELS, auto by default: numba on CPU)")
    ap.add_argument("--device", default=None, help="cpu or cuda: compare solvers there (see the docstring)")
    ap.add_argument("--solver", default=None,
                    help="solver(s) to compare: names of saft.physics.simulation.SOLVERS, 'all', comma-separated; "
                         "a dense one with ':N' refactorises after N iterations instead of 20 (dense:10), "
                         "with ':N:M' also when its factor is more than M substeps old (dense:20:25)")
    ap.add_argument("--tol", type=float, default=1e-6, help="relative residual of every solve (comparison mode)")
    ap.add_argument("--graphs", choices=("1", "0", "both"), default="1",
                    help="comparison mode on CUDA: record CUDA graphs (SAFT_PHYSICS_GRAPHS), or run both ways")
    ap.add_argument("--profile-frames", type=int, default=5,
                    help="comparison mode: frames of one extra profiled run of the first solver (0: none)")
    ap.add_argument("--profile-all", action="store_true", help="comparison mode: profile every solver")
    ap.add_argument("--no-cpu-reference", action="store_true",
                    help="comparison mode: skip the CPU default's runs (no max-diff lines)")
    ap.add_argument("--budget-s", type=float, default=2.0,
                    help="comparison mode: a solver whose 50-frame run would take longer (projected from two "
                         "3-frame runs) is skipped (0: never)")
    args = ap.parse_args()
    if args.device is None and args.solver is None and args.compile == "both":
        ap.error("--compile both is for the solver comparison (--device/--solver)")
    if args.device is not None or args.solver is not None:
        from bench_physics_device import compare  # noqa: E402 (a sibling script)

        return compare(args, load_case, run_once)
    compile_flag = None if args.compile == "env" else args.compile == "1"
    kern = None if args.kernels == "env" else args.kernels
    threads = [int(t) for t in args.threads.split(",")]
    print(f"saft.physics benchmark: {args.frames} frames x 4 substeps, float64, median of {args.repeats} runs, "
          f"compile={compile_flag if compile_flag is not None else 'env'}, kernels={args.kernels}; wall = elapsed, "
          f"cpu = process time (the machine may be shared: cpu is the steadier number)")
    hdr = (f"{'case':16s} {'V':>5s} {'thr':>3s} {'fwd_wall':>9s} {'fwd_cpu':>8s} {'fb_wall':>8s} {'fb_cpu':>7s}"
           f"  solver (last fwd+bwd run)")
    print(hdr)
    print("-" * len(hdr))
    best32 = None
    for case in (args.sizes or "16x16,32x32,64x64").split(","):
        label, verts, quads = load_case(case)
        topo = ClothTopology.from_quads(verts, quads)
        for nt in threads:
            torch.set_num_threads(nt)
            kw = dict(compile=compile_flag, kernels=kern)
            run_once(topo, 3, True, **kw)  # warm-up (and compilation, if on)
            fwd = [run_once(topo, args.frames, False, **kw) for _ in range(args.repeats)]
            fb = [run_once(topo, args.frames, True, **kw) for _ in range(args.repeats)]
            med = statistics.median
            fw_w, fw_c = med(r[0] for r in fwd), med(r[1] for r in fwd)
            fb_w, fb_c = med(r[0] for r in fb), med(r[1] for r in fb)
            print(f"{label:16s} {topo.num_vertices:5d} {nt:3d} {fw_w:9.3f} {fw_c:8.3f} {fb_w:8.3f} {fb_c:7.3f}"
                  f"  {_fmt_stats(fb[-1][2])}", flush=True)
            if case == "32x32":
                best32 = fb_w if best32 is None else min(best32, fb_w)
    if best32 is not None:
        print(f"physics_fwd_bwd_s_32x32_{args.frames}f={best32:.3f}")


if __name__ == "__main__":
    main()
