"""Forward + backward of render_cloth on the R1 template (32×32 grid, 1922 triangles, 512² texture).

Gradients flow to the vertex positions and to the texture, from the loss of the texture and shape phases
(saft.reconstruct.losses: image_loss + 0.2 silhouette_loss against a blank target; before 2026-11-27 the
same loss written out, `(rgb - target).square().mean() + 0.2 * mask.square().mean()`, 7 ops forward and
about 8 backward more per step: a quarter of a GPU step's launches, BENCHMARKS.md "GPU, fourth session").
Resolutions: 700×800 (the R1 crop) and 350×400 (half), with 1 and 2 torch threads (--threads); per step both the wall-clock time and the process
CPU time (time.process_time: the honest number on a shared, loaded machine, where wall time also counts
waiting for a core). Prints a table of medians of --runs timed steps after warm-up; the last line is
machine-readable: render_fwd_bwd_ms_350x400=<ms>, the median WALL time at 350×400 for the thread count
that is fastest there, after render_fwd_bwd_ms_<resolution>_<device>_<backend>=<ms> at that thread count. On CUDA the
step ends with torch.cuda.synchronize, so wall time is the GPU's time; use --threads 1 there.

    python benchmarks/bench_render.py [--runs 15] [--threads 1,2] [--backend torch] [--device cpu] [--profile]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import torch

from saft.reconstruct.losses import image_loss, silhouette_loss
from saft.render import get_rasterizer, render_cloth
from saft.scene.camera import Camera, Crop
from saft.scene.mesh import read_obj

REPO = Path(__file__).resolve().parents[1]
R1 = (REPO / ".." / "shared" / "data" / "phi_sft" / "data" / "R1").resolve()


def r1_camera() -> Camera:
    """The R1 camera of φ-SfT (scenes/R1.json) and its crop, written out so the benchmark needs only the
    template."""
    K = np.array([[971.522, 0, 962.134], [0, 944.575, 554.778], [0, 0, 1]])
    return Camera(K, np.diag([-1.0, -1.0, 1.0, 1.0]), 1920, 1080).cropped(Crop(280, 300, 700, 800))


def load_texture(size: int = 512) -> torch.Tensor:
    path = R1 / "texture.png"
    if path.is_file():
        from PIL import Image
        img = Image.open(path).convert("RGB").resize((size, size), Image.BILINEAR)
        return torch.from_numpy(np.asarray(img, dtype=np.float32) / 255.0)
    return torch.rand(size, size, 3, generator=torch.Generator().manual_seed(0))


def bench(cam, mesh, tex0, rasterizer, device, runs: int) -> tuple[float, float]:
    """(median wall ms, median CPU ms) of one forward+backward step over `runs` timed steps."""
    v = torch.tensor(mesh.vertices, dtype=torch.float32, device=device, requires_grad=True)
    tex = tex0.to(device).clone().requires_grad_(True)
    tri = torch.from_numpy(mesh.triangles).to(device)
    uvs = torch.from_numpy(mesh.uvs).float().to(device)
    target = torch.zeros(1, cam.height, cam.width, 3, device=device)
    target_mask = torch.zeros(1, cam.height, cam.width, device=device)

    def step():
        v.grad = None
        tex.grad = None
        out = render_cloth(v, tri, uvs, tex, cam, rasterizer=rasterizer)
        loss = image_loss(out.rgb, target) + 0.2 * silhouette_loss(out.mask, target_mask)
        loss.backward()
        if device.type == "cuda":
            torch.cuda.synchronize()

    for _ in range(3):
        step()
    wall, cpu = [], []
    for _ in range(runs):
        t, c = time.perf_counter(), time.process_time()
        step()
        cpu.append((time.process_time() - c) * 1000)
        wall.append((time.perf_counter() - t) * 1000)
    return statistics.median(wall), statistics.median(cpu)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=15)
    ap.add_argument("--threads", default="1,2", help="comma-separated torch thread counts (default 1,2)")
    ap.add_argument("--backend", default="auto")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--profile", action="store_true", help="print a torch.profiler table at 350×400")
    args = ap.parse_args(argv)
    obj = R1 / "0_R1_quad.obj"
    if not obj.is_file():
        print(f"R1 template not found at {obj}", file=sys.stderr)
        return 2
    mesh = read_obj(obj)
    tex = load_texture()
    device = torch.device(args.device)
    R = get_rasterizer(args.backend, device)
    full = r1_camera()
    half = full.scaled(0.5)
    threads = [int(t) for t in args.threads.split(",") if t.strip()]
    print(f"backend={R.name} device={device} triangles={len(mesh.triangles)} texture={tuple(tex.shape)} "
          f"runs={args.runs} (medians; CPU = process time of all threads)")
    print(f"{'threads':>7}  {'resolution':>10}  {'wall ms':>8}  {'CPU ms':>8}")
    wall_half, wall_full = {}, {}
    for n in threads:
        torch.set_num_threads(n)
        for cam in (full, half):
            wall, cpu = bench(cam, mesh, tex, R, device, args.runs)
            print(f"{n:>7}  {f'{cam.height}x{cam.width}':>10}  {wall:8.1f}  {cpu:8.1f}", flush=True)
            (wall_half if cam is half else wall_full)[n] = wall
    best = min(wall_half, key=wall_half.get)
    torch.set_num_threads(best)
    if args.profile:
        from torch.profiler import ProfilerActivity, profile
        acts = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if device.type == "cuda" else [])
        with profile(activities=acts) as prof:
            bench(half, mesh, tex, R, device, 5)
        ev = prof.key_averages()
        print(ev.table(sort_by="self_cpu_time_total", row_limit=25))
        from bench_physics_device import LAUNCH_EVENTS, SYNC_EVENTS

        counts = {k: sum(e.count for e in ev if e.key == k) for k in LAUNCH_EVENTS + SYNC_EVENTS + ("cudaMemcpyAsync",)}
        print("per profiled step (8 steps):", {k: v / 8 for k, v in counts.items() if v})
    print(f"best thread count at 350x400: {best}")
    print(f"render_fwd_bwd_ms_700x800_{device.type}_{R.name}={wall_full[best]:.2f}")
    print(f"render_fwd_bwd_ms_350x400_{device.type}_{R.name}={wall_half[best]:.2f}")
    print(f"render_fwd_bwd_ms_350x400={wall_half[best]:.1f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
