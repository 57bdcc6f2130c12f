"""Tensor-op count and CPU time of one render_cloth forward + backward (torch backend) on the R1 template.

Every aten op that reaches the dispatcher is one kernel launch on CUDA (a few, such as views, launch
nothing; they are counted separately), so the count on the CPU is the proxy for the GPU's launches of the
same code path. Host syncs are the ops that need a device value on the host: `_local_scalar_dense` (item,
int(), bool() of a tensor) and the ops whose output size depends on the data (nonzero and its users). The
loss (rgb and coverage, as bench_render.py) adds its few ops to the count.

    python benchmarks/bench_render_ops.py [--sizes 240x320,700x800] [--by op|site] [--top 25]
                                          [--time --runs 7 --threads 1,2] [--tex-grad 1|0] [--path fused|primitives]

--path primitives counts the nvdiffrast backend's path (saft.render.reference.render_cloth_primitives) on the
CPU: its four primitives are run by the torch backend but counted as one op each way (nvdiffrast launches
a few kernels per primitive), so what is counted is saft's own code around them: its launches on CUDA.

Last lines (machine-readable): render_ops_<H>x<W>=<forward>+<backward> and, with --time,
render_cpu_ms_<H>x<W>_t<threads>=<median process-time ms>.
"""

from __future__ import annotations

import argparse
import collections
import resource
import statistics
import sys
import time
from pathlib import Path

import torch
from torch.utils._python_dispatch import TorchDispatchMode

from bench_render import R1, load_texture, r1_camera
from saft.reconstruct.losses import image_loss, silhouette_loss
from saft.render import get_rasterizer, render_cloth
from saft.render.reference import render_cloth_primitives
from saft.scene.camera import Crop
from saft.scene.mesh import read_obj

# ops that launch nothing on a device: metadata only
_VIEWS = {"view", "_unsafe_view", "reshape", "expand", "permute", "select", "slice", "t", "transpose",
          "unsqueeze", "squeeze", "as_strided", "alias", "detach", "unbind", "split", "split_with_sizes",
          "chunk", "diagonal", "view_as", "lift_fresh", "_reshape_alias", "set_", "resize_", "empty",
          "empty_like", "empty_strided", "new_empty", "new_empty_strided"}
_SYNCS = {"_local_scalar_dense", "nonzero", "masked_select", "unique", "_unique2", "unique_consecutive",
          "unique_dim", "is_nonzero", "item"}


def camera_for(size: str):
    """R1's camera for 700x800; for 240x320 the central 600x800 window of the same view scaled by 0.4."""
    H, W = (int(x) for x in size.lower().split("x"))
    cam = r1_camera()
    if (H, W) == (cam.height, cam.width):
        return cam
    top = (cam.height - cam.width * H // W) // 2
    win = cam.cropped(Crop(top, 0, cam.width * H // W, cam.width))
    return win.scaled(H / win.height)


class _Count(TorchDispatchMode):
    paused = False  # set while an opaque primitive runs (--path primitives)

    def __init__(self, by: str):
        super().__init__()
        self.by = by
        self.ops = collections.Counter()

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        if _Count.paused:
            return func(*args, **(kwargs or {}))
        name = func.overloadpacket.__name__
        if name in ("index", "index_put", "index_put_") and any(
                isinstance(i, torch.Tensor) and i.dtype == torch.bool for i in (args[1] or ())):
            name += "[bool mask: nonzero inside]"  # a host sync like nonzero
        key = name
        if self.by == "site":
            key = f"{name} @ {_site()}"
        self.ops[key] += 1
        return func(*args, **(kwargs or {}))


def _site() -> str:
    """The innermost saft frame that issued the op, or the autograd node running it."""
    f = sys._getframe(2)
    while f is not None:
        fn = f.f_code.co_filename
        if "/saft/" in fn:
            return f"{fn.split('/saft/')[-1]}:{f.f_lineno} {f.f_code.co_name}"
        f = f.f_back
    node = torch._C._current_autograd_node()
    return f"autograd {type(node).__name__}" if node is not None else "?"


class _Opaque(torch.autograd.Function):
    """One primitive of the torch backend, counted as one op forward and one backward ("<name> primitive")."""

    @staticmethod
    def forward(ctx, name, fn, *inputs):
        with torch.enable_grad():
            leaves = [x.detach().requires_grad_(x.requires_grad) if isinstance(x, torch.Tensor) else x
                      for x in inputs]
            _Count.paused = True
            try:
                out = fn(*leaves)
            finally:
                _Count.paused = False
        outs = out if isinstance(out, tuple) else (out,)
        ctx.name, ctx.leaves, ctx.outs, ctx.tuple = name, leaves, outs, isinstance(out, tuple)
        _note(f"{name} primitive")
        return tuple(o.detach() if isinstance(o, torch.Tensor) else o for o in outs)

    @staticmethod
    def backward(ctx, *grads):
        pairs = [(o, g) for o, g in zip(ctx.outs, grads) if isinstance(o, torch.Tensor) and o.requires_grad
                 and g is not None]
        wrt = [x for x in ctx.leaves if isinstance(x, torch.Tensor) and x.requires_grad]
        _Count.paused = True
        try:
            got = torch.autograd.grad([o for o, _ in pairs], wrt, [g for _, g in pairs], allow_unused=True) \
                if pairs and wrt else [None] * len(wrt)
        finally:
            _Count.paused = False
        _note(f"{ctx.name} primitive backward")
        it = iter(got)
        return (None, None) + tuple(next(it) if isinstance(x, torch.Tensor) and x.requires_grad else None
                                    for x in ctx.leaves)


_ACTIVE: list = []


def _note(key: str):
    if _ACTIVE:
        _ACTIVE[-1].ops[key] += 1


class _OpaquePrimitives:
    """The torch backend's four primitives, each opaque to the counter (see --path primitives)."""

    name = "primitives"

    def __init__(self, device):
        self.R = get_rasterizer("torch", device)

    def render_cloth(self, *args):
        return render_cloth_primitives(self, *args)

    def _call(self, name, fn, *inputs):
        out = _Opaque.apply(name, fn, *inputs)
        return out if len(out) > 1 else out[0]

    def rasterize(self, pos, tri, resolution, with_db=False):
        return self._call("rasterize", lambda p: self.R.rasterize(p, tri, resolution, with_db=with_db), pos)

    def interpolate(self, attr, rast, tri, rast_db=None, diff_attrs=None):
        return self._call("interpolate", lambda a, r, d: self.R.interpolate(a, r, tri, rast_db=d,
                                                                              diff_attrs=diff_attrs),
                          attr, rast, rast_db)

    def texture(self, tex, uv, uv_da=None, filter_mode="auto", boundary_mode="wrap", max_mip_level=None,
                mask=None):
        return self._call("texture", lambda t, u, d: self.R.texture(
            t, u, d, filter_mode=filter_mode, boundary_mode=boundary_mode, max_mip_level=max_mip_level,
            mask=mask), tex, uv, uv_da)

    def antialias(self, color, rast, pos, tri):
        return self._call("antialias", lambda c, r, p: self.R.antialias(c, r, p, tri), color, rast, pos)


def setup(size, device, tex_grad: bool = True, path: str = "fused"):
    mesh = read_obj(R1 / "0_R1_quad.obj")
    cam = camera_for(size)
    v = torch.tensor(mesh.vertices, dtype=torch.float32, device=device, requires_grad=True)
    tex = load_texture().to(device).requires_grad_(tex_grad)
    tri = torch.from_numpy(mesh.triangles).to(device)
    uvs = torch.from_numpy(mesh.uvs).float().to(device)
    target = torch.zeros(1, cam.height, cam.width, 3, device=device)
    target_mask = torch.zeros(1, cam.height, cam.width, device=device)
    R = get_rasterizer("torch", device) if path == "fused" else _OpaquePrimitives(device)

    def forward():
        out = render_cloth(v, tri, uvs, tex, cam, rasterizer=R)
        return image_loss(out.rgb, target) + 0.2 * silhouette_loss(out.mask, target_mask)

    def step():
        v.grad = None
        tex.grad = None
        forward().backward()

    return forward, step, v, tex


def count(size, device, by, tex_grad=True, path="fused"):
    forward, step, v, tex = setup(size, device, tex_grad, path)
    step()  # warm caches (topology, allocator)
    v.grad = tex.grad = None
    with _Count(by) as cf:
        _ACTIVE.append(cf)
        loss = forward()
    with _Count(by) as cb:
        _ACTIVE[-1] = cb
        loss.backward()
    _ACTIVE.clear()
    return cf.ops, cb.ops


def split(ops):
    launches = sum(n for k, n in ops.items() if k.split(" @ ")[0] not in _VIEWS)
    views = sum(ops.values()) - launches
    syncs = sum(n for k, n in ops.items() if k.split(" @ ")[0] in _SYNCS or "bool mask" in k)
    return launches, views, syncs


def timed(size, device, threads, runs, tex_grad=True, path="fused"):
    torch.set_num_threads(threads)
    _, step, _, _ = setup(size, device, tex_grad, path)
    for _ in range(3):
        step()
    cpu = []
    flt = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    for _ in range(runs):
        c = time.process_time()
        step()
        cpu.append((time.process_time() - c) * 1000)
    flt = (resource.getrusage(resource.RUSAGE_SELF).ru_minflt - flt) / runs
    return statistics.median(cpu), min(cpu), flt


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", default="240x320,700x800")
    ap.add_argument("--by", choices=("op", "site"), default="op")
    ap.add_argument("--top", type=int, default=25)
    ap.add_argument("--time", action="store_true", help="also CPU time (process time) per step")
    ap.add_argument("--runs", type=int, default=7)
    ap.add_argument("--threads", default="1,2")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--tex-grad", type=int, choices=(0, 1), default=1,
                    help="1: gradients to the texture too (the texture phase, bench_render.py); 0: a fixed texture "
                         "without gradient (the shape phase: its mip pyramid is kept between renders)")
    ap.add_argument("--path", choices=("fused", "primitives"), default="fused",
                    help="fused: the torch backend's render_cloth; primitives: the nvdiffrast backend's code around "
                         "its four primitives, each counted as one op")
    args = ap.parse_args(argv)
    if not (R1 / "0_R1_quad.obj").is_file():
        print(f"R1 template not found at {R1}", file=sys.stderr)
        return 2
    device = torch.device(args.device)
    lines = []
    for size in args.sizes.split(","):
        fw, bw = count(size, device, args.by, bool(args.tex_grad), args.path)
        (lf, vf, sf), (lb, vb, sb) = split(fw), split(bw)
        print(f"== {size}: forward {lf} ops (+{vf} views), {sf} host syncs; backward {lb} ops (+{vb} views), "
              f"{sb} host syncs")
        for name, ops in (("forward", fw), ("backward", bw)):
            print(f"-- {name}, top {args.top}:")
            for k, n in ops.most_common(args.top):
                print(f"   {n:4d}  {k}")
        lines.append(f"render_ops_{size}={lf}+{lb}")
        lines.append(f"render_syncs_{size}={sf}+{sb}")
        if args.time:
            for t in (int(x) for x in args.threads.split(",")):
                med, best, flt = timed(size, device, t, args.runs, bool(args.tex_grad), args.path)
                print(f"   {size} threads={t}: CPU ms median {med:.2f}, min {best:.2f} ({args.runs} runs), "
                      f"{flt:.0f} page faults per step (first touches of memory the allocator got anew)",
                      flush=True)
                lines.append(f"render_cpu_ms_{size}_t{t}={med:.2f}")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
