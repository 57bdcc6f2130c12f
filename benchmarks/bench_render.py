"""Forward + backward of render_cloth on the R1 template (32×32 grid, 1922 triangles, 512² texture).

Gradients flow to the vertex positions and to the texture. Resolutions: 700×800 (the R1 crop) and
350×400 (half), with 1 and 2 torch threads; medians of --runs timed runs after warm-up. The last line is
machine-readable: render_fwd_bwd_ms_350x400=<ms> (2 threads, or --threads).

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


def bench(cam, mesh, tex0, rasterizer, device, runs: int) -> float:
    v = torch.tensor(mesh.vertices, dtype=torch.float32, device=device, requires_grad=True)
    tex = tex0.to(device).clone().requires_grad_(True)
    tri = torch.from_numpy(mesh.triangles).to(device)
    uvs = torch.from_numpy(mesh.uvs).float().to(device)
    target = torch.zeros(1, cam.height, cam.width, 3, device=device)

    def step():
        v.grad = None
        tex.grad = None
        out = render_cloth(v, tri, uvs, tex, cam, rasterizer=rasterizer)
        loss = (out.rgb - target).square().mean() + 0.2 * out.mask.square().mean()
        loss.backward()
        if device.type == "cuda":
            torch.cuda.synchronize()

    for _ in range(3):
        step()
    times = []
    for _ in range(runs):
        t = time.perf_counter()
        step()
        times.append((time.perf_counter() - t) * 1000)
    return statistics.median(times)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=15)
    ap.add_argument("--threads", default="1,2")
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
    threads = [int(t) for t in args.threads.split(",")]
    print(f"backend={R.name} device={device} triangles={len(mesh.triangles)} texture={tuple(tex.shape)}")
    last = None
    for n in threads:
        torch.set_num_threads(n)
        for cam in (full, half):
            ms = bench(cam, mesh, tex, R, device, args.runs)
            print(f"threads={n} {cam.height}x{cam.width}: {ms:.1f} ms (median of {args.runs})")
            if cam is half:
                last = ms
    if args.profile:
        from torch.profiler import ProfilerActivity, profile
        with profile(activities=[ProfilerActivity.CPU]) as prof:
            bench(half, mesh, tex, R, device, 5)
        print(prof.key_averages().table(sort_by="self_cpu_time_total", row_limit=20))
    print(f"render_fwd_bwd_ms_350x400={last:.1f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
