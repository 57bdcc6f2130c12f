"""Does the video determine a material? A per-cluster test after a guided fit (issue 28, "honest output").

A matte cloth never shows a specular highlight, so its roughness (and whether it is metal) cannot be read
from the video: any value fits the frames as well. For every material cluster of a ``GuidedMaps`` fit we
compare the image loss over the frames with the fitted material against the same maps with that cluster
made matte (roughness 1, metallic 0: the texture-only assumption), rendered with the SAME random samples so
that the Monte Carlo noise cancels in the difference. When the fitted material lowers the whole image loss
by less than ``threshold`` × the cluster's share of the texture (relative: a cluster of threads covering a
fifth of the cloth can change only about a fifth of the loss), the data does not insist: the cluster is
set to matte and marked undetermined.

Matte (roughness 1) is only one of the roughnesses such a cluster cannot be told from: a rough dielectric
shows no highlight either. With ``band`` the test goes on down a ladder of roughnesses (0.9, 0.8, …) until the
frames rule one out (it raises the loss by more than the same threshold × area over matte), and the cluster
gets the middle of the range [lowest not ruled out, 1]: the value whose largest error over every roughness
the video allows is smallest. The range itself is reported with it.
"""

from __future__ import annotations

from typing import Callable

import numpy as np
import torch


@torch.no_grad()
def cluster_evidence(model, env: torch.Tensor, render: Callable, frames: list[int], loss: Callable,
                     spp: int = 4, threshold: float = 0.01, dielectric_below: float = 0.05,
                     band: bool = False) -> list[dict]:
    """One dict per cluster: area, fitted roughness / metallic, relative loss gain over matte, determined.

    render(frame, diffuse, roughness, metallic, env, spp, seed) → linear image; loss(frame, image) → scalar.
    Clusters judged undetermined are set to matte in `model` (in place); determined ones whose metallic
    is below `dielectric_below` are set to metallic 0 (a few per cent of metal is noise, not a material).
    With band, an undetermined cluster gets the middle of the roughness range the frames do not rule out
    (roughness_range in its dict) instead of 1.
    """
    maps = model.base_maps(env)   # the dielectric diffuse; model.mix_metal adds a metal colour (appearance.metal)
    vals = {k: v.detach().clone() for k, v in model.cluster_values().items()}

    def total(rough, metal) -> float:
        diffuse = model.mix_metal(maps["diffuse"], metal)
        return sum(float(loss(f, render(f, diffuse, rough, metal, env, spp, 7919 + f))) for f in frames)

    fitted = total(maps["roughness"], maps["metallic"])
    out = []
    for k in range(model.num_clusters):
        member = model.members[k]
        r, m = float(vals["roughness"][k]), float(vals["metallic"][k])
        if r > 0.9 and m < 0.05:  # already matte: nothing to test
            out.append({"cluster": k, "area": float(model.area[k]), "roughness": r, "metallic": m,
                        "gain_over_matte": 0.0, "determined": False})
            continue
        rough = maps["roughness"] * (1 - member) + member
        metal = maps["metallic"] * (1 - member)
        gain = (total(rough, metal) - fitted) / max(fitted, 1e-12)
        area = float(model.area[k])
        out.append({"cluster": k, "area": area, "roughness": r, "metallic": m,
                    "gain_over_matte": gain, "determined": bool(gain > threshold * area)})
    for row in out:
        if not row["determined"]:
            model.set_matte(row["cluster"])
            row["roughness"], row["metallic"] = 1.0, 0.0
        elif row["metallic"] < dielectric_below:
            model.set_dielectric(row["cluster"])
            row["metallic"] = 0.0
    if band and any(not row["determined"] for row in out):
        _roughness_bands(model, env, total, out, threshold)
    return out


ROUGHNESS_LADDER = (0.9, 0.8, 0.7, 0.6, 0.5, 0.4, 0.3, 0.2)


def lowest_allowed(cost: Callable[[float], float], limit: float, ladder=ROUGHNESS_LADDER) -> float:
    """Walking down `ladder` from 1, the last roughness whose cost (relative loss over matte) is ≤ limit."""
    lowest = 1.0
    for r in ladder:
        if cost(r) > limit:
            break
        lowest = r
    return lowest


def _roughness_bands(model, env, total: Callable, out: list[dict], threshold: float) -> None:
    """Each undetermined cluster to the middle of the roughness range its frames allow (see the module)."""
    maps = model.base_maps(env)
    matte = total(maps["roughness"], maps["metallic"])
    for row in out:
        if row["determined"]:
            continue
        member = model.members[row["cluster"]]

        def cost(r: float) -> float:
            rough = maps["roughness"] * (1 - member) + r * member
            return (total(rough, maps["metallic"] * (1 - member)) - matte) / max(matte, 1e-12)

        lowest = lowest_allowed(cost, threshold * row["area"])
        row["roughness_range"] = [lowest, 1.0]
        row["roughness"] = 0.5 * (lowest + 1.0)
        model.set_roughness(row["cluster"], row["roughness"])


def undetermined_note(evidence: list[dict]) -> str | None:
    """A sentence for appearance.json when some of the cloth's material is not determined by the data."""
    area = float(np.sum([e["area"] for e in evidence if not e["determined"]]))
    if area <= 0:
        return None
    rows = [e for e in evidence if not e["determined"]]
    text = (f"{100 * area:.0f} % of the texture (clusters {[e['cluster'] for e in rows]}) showed no specular "
            "evidence in the video: roughness and metallic there are not determined by the data")
    if any("roughness_range" in e for e in rows):
        ranges = ", ".join(f"cluster {e['cluster']}: {e['roughness_range'][0]:.1f}-1" for e in rows)
        return (text + "; metallic was set to 0 and roughness to the middle of the range the video cannot "
                f"tell apart ({ranges})")
    return text + " and were set to matte (roughness 1, metallic 0)"
