"""How much of each fabric's true base colour a video's pixels can hold (issue 28).

The true base colour (``appearance_gt/base_color.png`` of an appearance benchmark scene) is low-passed in
the Fourier domain (every frequency above c cycles per map width zeroed: the ideal reconstruction from
samples at 2c per map width) and scored with the benchmark's diffuse metric (PSNR, every texel). The
cloth's pixel footprint in frame 0 gives the video's own c (half the pixels the cloth spans).

    python3 benchmarks/appearance_ceiling.py [--root /tmp/saft-appearance-bench] [--fabrics cotton,plaid]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from saft.evaluate.appearance import psnr, read_appearance_ground_truth
from saft.io_utils import read_image


def low_pass(a: np.ndarray, cycles: float) -> np.ndarray:
    """(N, N, C) map with every frequency above `cycles` per map width (either axis) zeroed."""
    f = np.abs(np.fft.fftfreq(a.shape[0]) * a.shape[0])
    keep = (f[:, None] <= cycles) & (f[None, :] <= cycles)
    return np.real(np.fft.ifft2(np.fft.fft2(a, axes=(0, 1)) * keep[..., None], axes=(0, 1)))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--root", default="/tmp/saft-appearance-bench")
    ap.add_argument("--fabrics", default="cotton,print,plaid,satin,lame")
    ap.add_argument("--scene", default="{fabric}_32f_320x240", help="scene folder name under ROOT/scenes")
    ap.add_argument("--cycles", default="45,60,90,120,180")
    args = ap.parse_args()
    cycles = [float(c) for c in args.cycles.split(",")]
    print("fabric  cloth_px  video_c  " + "  ".join(f"c={c:g}" for c in cycles))
    for fabric in args.fabrics.split(","):
        folder = Path(args.root) / "scenes" / args.scene.format(fabric=fabric)
        gt = read_appearance_ground_truth(folder)
        if gt is None:
            raise SystemExit(f"{folder}: no appearance_gt/ (not an appearance benchmark scene)")
        mask = np.asarray(read_image(folder / "mask" / "000.png"))
        mask = (mask[..., 0] if mask.ndim == 3 else mask) > 0.5
        pixels = int(mask.sum())
        scores = [psnr(float(((low_pass(gt.base_color, c) - gt.base_color) ** 2).mean())) for c in cycles]
        print(f"{fabric:7s} {pixels:9d} {np.sqrt(pixels) / 2:8.1f}  " + "  ".join(f"{s:6.2f}" for s in scores))


if __name__ == "__main__":
    main()
