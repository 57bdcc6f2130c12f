"""Which vertices of a reconstruction are wrong: those the truth hides, those where the truth lies in layers?

    python benchmarks/diagnose_layer_error.py SCENE_DIR RESULT_DIR [--layer 0.02] [--tolerance 0.01]

SCENE_DIR: an independent-simulator scene (its truth resampled onto the template's grid, as
diagnose_independent.py reads it); RESULT_DIR: a saft result of it. Per frame, the RMS vertex error (cm)
of the template's vertices, split

- by visibility: hidden = more than --tolerance (m) behind the truth's own rendered surface at its pixel
  (saft.reconstruct.tracks.hidden_vertices on a render of the truth), i.e. what the camera cannot see;
- by layering: layered = within --layer (m) of a truth vertex further than 2.5 template spacings away on
  the rest cloth (a flap lying on, or passing through, another part of the cloth), the vertices a
  self-contact term would act on;

and the depth / lateral parts of the error of the hidden vertices in the working camera.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch

from saft.evaluate.self_contact import layered
from saft.reconstruct.tracks import hidden_vertices
from saft.render import get_rasterizer, render_cloth
from saft.scene import load_scene, read_obj
from saft.synthetic.hanging_cloth import grid_template

from diagnose_independent import truth_on_template


def rms(e: np.ndarray) -> str:
    return f"{100 * np.sqrt((e ** 2).mean()):5.2f}" if len(e) else "    -"


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("scene", type=Path)
    p.add_argument("result", type=Path)
    p.add_argument("--layer", type=float, default=0.02)
    p.add_argument("--tolerance", type=float, default=0.01)
    args = p.parse_args()
    scene = load_scene(args.scene)
    cam = scene.working_camera(1.0)
    tpl = scene.template
    n = round(len(tpl.vertices) ** 0.5)
    size = float(json.loads((args.scene / "generator.json").read_text())["spec"]["size"])
    rest = np.asarray(grid_template(n, size).vertices)
    tri = torch.as_tensor(tpl.triangles, dtype=torch.int32)
    uvs = torch.as_tensor(tpl.uvs, dtype=torch.float32)
    ras = get_rasterizer("torch", "cpu")
    truth = truth_on_template(args.scene, len(tpl.vertices))
    recon = np.stack([read_obj(args.result / "meshes" / f"frame_{t:03d}.obj").vertices for t in range(len(truth))])
    R = np.asarray(cam.world_to_camera[:3, :3])
    print("frame | all | visible hidden (share hidden) | layered not (share layered) | hidden: depth lateral")
    for t in range(len(truth)):
        v = torch.as_tensor(truth[t], dtype=torch.float32)
        depth = render_cloth(v[None], tri, uvs, torch.zeros(4, 4, 3), cam, rasterizer=ras).depth[0]
        hid = hidden_vertices(v[None], [depth], cam, args.tolerance)[0].numpy()
        lay = layered(rest, truth[t], args.layer, 2.5 * size / (n - 1))
        d = recon[t] - truth[t]
        e = np.linalg.norm(d, axis=1)
        dc = d[hid] @ R.T
        print(f"{t:3d} | {rms(e)} | {rms(e[~hid])} {rms(e[hid])} ({hid.mean():4.2f}) | {rms(e[lay])} {rms(e[~lay])} "
              f"({lay.mean():4.2f}) | {rms(dc[:, 2])} {rms(np.linalg.norm(dc[:, :2], axis=1))}")


if __name__ == "__main__":
    main()
