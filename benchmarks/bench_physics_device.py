"""Solver comparison of ``bench_physics.py --device/--solver`` (issue 27): one size (default 32x32, R1's
template), forward + backward, per solver: two 3-frame runs (CUDA graphs recorded, kernels loaded; a solver
projected past --budget-s is skipped), a full warm-up run, then the median of --repeats timed runs
(torch.cuda.synchronize around each), CG iterations per solve, factorisations, host reads per solve, the
largest differences from the CPU default (numba + ReusedLUSolver) on the same input, and for the first solver
one profiled run (--profile-frames) that splits the time into phases and counts the launches and host
synchronisations per substep.

Machine-readable lines: physics_cpu_fwdbwd_s=, physics_cpu_tol_spread_pos= / _grad= (the CPU default at tol
against tol/10: the size of the differences the tolerance allows), per solver physics_fwdbwd_s_<solver>=,
physics_<device>_vs_cpu_maxdiff_<solver>= (positions, metres) and ..._grad_<solver>= (largest over the
parameters of max |g - g_cpu| / max |g_cpu|); last physics_fwdbwd_s= and physics_<device>_vs_cpu_maxdiff= of
the fastest solver (physics_best_solver=).
"""

from __future__ import annotations

import itertools
import os
import statistics
import time

import torch

from saft.physics import ClothTopology
from saft.physics.cuda_graphs import ENV_GRAPHS
from saft.physics.simulation import DENSE_SOLVERS
from saft.physics.solver_choice import dense_variant

# "all": the dense variants, "dense" that also refactorises every 25 substeps (R1 on the CPU, 50 frames fwd+bwd:
# 5231 CG iterations with 1 factorisation without, 4115 with 8; 3431 / 16 every 12 substeps), then the Jacobi
# CG ("cg", ~12 s per 50-frame run on an H200 in issue 27: its 3-frame probes give the projection and it is
# skipped unless --budget-s allows it)
ALL = (*DENSE_SOLVERS, "dense:20:25", "cg")
# the profiler's names of a kernel launch and of a host synchronisation (also read by bench_r1, bench_render)
LAUNCH_EVENTS = ("cudaLaunchKernel", "cudaLaunchKernelExC", "cuLaunchKernel", "cuLaunchKernelEx")
SYNC_EVENTS = ("cudaStreamSynchronize", "cudaDeviceSynchronize", "cudaEventSynchronize")


def _solver_names(spec):
    """A comma list of solver names; "all" stands for ALL; a dense variant with options is registered by
    saft.physics.solver_choice.dense_variant (this process only), e.g. dense:20:25 (refactor_after 20,
    refactor_age 25) or densebf16:block=3:f32=1."""
    names = []
    for name in spec.split(","):
        if name in names:
            continue
        if name == "all":
            names += _solver_names(",".join(n for n in ALL if n not in names))
            continue
        if ":" in name:
            try:
                dense_variant(name)
            except ValueError as exc:
                raise SystemExit(f"--solver: {exc}") from None
        names.append(name)
    return names


def _tag(name: str) -> str:
    """A solver name as the key of its name=value output lines: dense:20:25 -> dense_20_age25,
    densebf16:block=3:f32=1 -> densebf16_block3_f32."""
    if "=" in name:
        return name.replace(":", "_").replace("f32=1", "f32").replace("=", "")
    return name.replace(":", "_", 1).replace(":", "_age")


def _diffs(pos, grads, ref_pos, ref_grads):
    """(max |pos - ref| in metres, max over parameters of max |g - g_ref| / max |g_ref|)."""
    dp = (pos - ref_pos).abs().max().item()
    dg = 0.0
    for g, r in zip(grads, ref_grads):
        if g is not None and r is not None:
            dg = max(dg, ((g - r).abs().max() / r.abs().max().clamp_min(1e-300)).item())
    return dp, dg


def _its(st, prefix=""):
    s = st.get(prefix + "solves", 0)
    return st.get(prefix + "iterations", 0) / max(s, 1)


def _stats_line(st):
    return (f"fwd its/solve {_its(st):.1f} fact {st.get('factorizations', 0)} fallbacks {st.get('fallbacks', 0)}"
            f" checks/solve {st.get('checks', 0) / max(st.get('solves', 1), 1):.2f} | bwd its/solve "
            f"{_its(st, 'bwd_'):.1f} fact {st.get('bwd_factorizations', 0)} fallbacks {st.get('bwd_fallbacks', 0)}"
            f" checks/solve {st.get('bwd_checks', 0) / max(st.get('bwd_solves', 1), 1):.2f}")


def _profile(topo, frames, solver, tol, run_once, compile):
    """One profiled fwd+bwd run: per saft range (CPU ms incl. waits, GPU ms), launches and syncs per substep."""
    from torch.profiler import ProfilerActivity, profile

    cuda = topo.device.type == "cuda"
    acts = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if cuda else [])
    with profile(activities=acts) as prof:
        wall = run_once(topo, frames, True, solver=solver, tol=tol, compile=compile)[0]
    ka = prof.key_averages()
    substeps = 2 * 4 * (frames - 1)

    def dev_ms(e, self_only=False):
        name = "self_device_time_total" if self_only else "device_time_total"
        alt = "self_cuda_time_total" if self_only else "cuda_time_total"
        return getattr(e, name, getattr(e, alt, 0.0)) / 1e3

    print(f"  profile ({frames} frames fwd+bwd, {substeps} substeps, wall {wall:.3f} s with the profiler on):")
    for e in sorted(ka, key=lambda e: -e.cpu_time_total):
        if e.key.startswith("saft."):
            print(f"    {e.key:24s} calls {e.count:6d}  cpu {e.cpu_time_total / 1e3:8.1f} ms  "
                  f"gpu {dev_ms(e):8.1f} ms")
    count = {e.key: e.count for e in ka}
    launches = sum(count.get(k, 0) for k in LAUNCH_EVENTS)
    graphs = count.get("cudaGraphLaunch", 0)
    syncs = sum(count.get(k, 0) for k in SYNC_EVENTS)
    copies = count.get("cudaMemcpyAsync", 0)
    gpu_rows = [e for e in ka if getattr(e, "device_type", None) == torch.autograd.DeviceType.CUDA]
    busy = sum(dev_ms(e, True) for e in gpu_rows)  # kernels and copies (graph replays' kernels included)
    print(f"    per substep: {launches / substeps:.1f} kernel launches, {graphs / substeps:.1f} graph replays, "
          f"{syncs / substeps:.1f} syncs, {copies / substeps:.1f} memcpys; GPU busy {busy:.1f} ms of "
          f"{wall * 1e3:.1f} ms wall")
    top = sorted(gpu_rows, key=lambda e: -dev_ms(e, True))[:10]
    for e in top:
        print(f"    gpu {dev_ms(e, True):8.1f} ms  {e.count:7d}x  {e.key[:90]}")


def _run_solver(topo, name, tag, compile, args, ref, run_once, profile):
    """Probe, warm-up, timed runs, differences from the CPU reference, profile: (median s, diffs or None)."""
    frames, tol, dev = args.frames, args.tol, topo.device
    kw = dict(solver=name, tol=tol, compile=compile)
    try:
        run_once(topo, 3, True, **kw)  # records the graphs (and compiles), loads cuSOLVER
        probe = run_once(topo, 3, True, **kw)[0] * (frames - 1) / 2
        if args.budget_s and probe > args.budget_s:
            print(f"{tag}: skipped, a {frames}-frame run would take ~{probe:.1f} s (> --budget-s {args.budget_s})")
            print(f"physics_fwdbwd_s_{tag}_projected={probe:.2f}\n", flush=True)
            return None
        warm = run_once(topo, frames, True, keep=True, **kw)
    except Exception as exc:  # noqa: BLE001 - one broken variant must not hide the others' numbers
        print(f"{tag}: FAILED {exc!r:.300}", flush=True)
        return None
    runs = [run_once(topo, frames, True, **kw) for _ in range(args.repeats)]
    med = statistics.median(r[0] for r in runs)
    print(f"{tag}: {med:.3f} s (median of {args.repeats}; warm-up {warm[0]:.3f} s)  {_stats_line(runs[-1][2])}")
    print(f"physics_fwdbwd_s_{tag}={med:.3f}")
    diff = None
    if ref is not None:
        diff = _diffs(warm[3], warm[4], *ref)
        print(f"physics_{dev.type}_vs_cpu_maxdiff_{tag}={diff[0]:.3e}")
        print(f"physics_{dev.type}_vs_cpu_maxdiff_grad_{tag}={diff[1]:.3e}")
    if profile and args.profile_frames > 1:
        _profile(topo, args.profile_frames, name, tol, run_once, compile)
    print(flush=True)
    return med, diff


def compare(args, load_case, run_once):
    dev = torch.device(args.device or "cpu")
    compiles = {"env": [None], "0": [False], "1": [True], "both": [False, True]}[args.compile]
    names = _solver_names(args.solver or "auto")
    frames, tol = args.frames, args.tol
    size = args.sizes.split(",")[0] if args.sizes else "32x32"
    label, verts, quads = load_case(size)
    topo_cpu = ClothTopology.from_quads(verts, quads)
    topo = topo_cpu.to(dev)
    cuda = dev.type == "cuda"
    card = torch.cuda.get_device_name(dev) if cuda else "CPU"
    print(f"saft.physics solvers: {label}, {topo.num_vertices} vertices ({3 * topo.num_vertices} unknowns), "
          f"{frames} frames x 4 substeps, fwd+bwd, float64, tol {tol:g}, on {dev} ({card}), torch "
          f"{torch.__version__}, median of {args.repeats} after a warm-up, compile={args.compile}", flush=True)
    ref = None
    if not args.no_cpu_reference:
        run_once(topo_cpu, 3, True, tol=tol)  # numba's compilation (or its disk cache)
        wall, _, st, ref_pos, ref_grads = run_once(topo_cpu, frames, True, tol=tol, keep=True)
        tight = run_once(topo_cpu, frames, True, tol=tol / 10, keep=True)
        sp, sg = _diffs(tight[3], tight[4], ref_pos, ref_grads)
        ref = (ref_pos, ref_grads)
        print(f"CPU default (numba kernels + ReusedLUSolver): {wall:.3f} s (one run); {_stats_line(st)}")
        print(f"physics_cpu_fwdbwd_s={wall:.3f}")
        print(f"physics_cpu_tol_spread_pos={sp:.3e}")
        print(f"physics_cpu_tol_spread_grad={sg:.3e}", flush=True)
    modes = [None] if not cuda else (["1", "0"] if args.graphs == "both" else [args.graphs])
    best = None
    for k, (mode, compile, name) in enumerate(itertools.product(modes, compiles, names)):
        if mode is not None:
            os.environ[ENV_GRAPHS] = mode
        tag = _tag(name) + ("_nographs" if mode == "0" else "") + ("_compiled" if compile else "")
        res = _run_solver(topo, name, tag, compile, args, ref, run_once, args.profile_all or k == 0)
        if res is not None and (best is None or res[0] < best[1]):
            best = (tag, *res)
    if best is not None:
        print(f"physics_best_solver={best[0]}")
        print(f"physics_fwdbwd_s={best[1]:.3f}")
        if best[2] is not None:
            print(f"physics_{dev.type}_vs_cpu_maxdiff={best[2][0]:.3e}")
            print(f"physics_{dev.type}_vs_cpu_maxdiff_grad={best[2][1]:.3e}")
