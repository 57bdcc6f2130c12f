"""Relative shading for the shape phase: how much brighter or darker each vertex is than in frame 0.

The texture of phase 1 is fitted to frame 0, so it already holds frame 0's shading. When the cloth turns,
its diffuse shading changes with the normal: a cloth tilting away from the light darkens, one tilting
towards it brightens. A texture-only renderer cannot show this, and the shape phase then has no cue that
tells a cloth tilted by +θ from one tilted by −θ (they project almost alike). With Lambertian reflection
under distant light, the irradiance is, to first order in the normal (the first two spherical-harmonic
bands), E(n) = e0 + e·n; the colour of a point at frame f is then the frame-0 colour times
E(n_f) / E(n_0). With e0 = 1 (the scale is the texture's), three numbers (the light vector e, grey) are
learned with the shape: zero gives a ratio of 1 everywhere, the unlit renderer.

Normals are taken on the side that faces the camera (a cloth is seen from both sides), per vertex; the
ratio is interpolated across the triangles by render_cloth(vertex_shading=...).
"""

from __future__ import annotations

import torch

from saft.render.output import vertex_normals

MIN_IRRADIANCE = 0.05  # E is clamped here: a clamped Lambertian never goes below black


def facing_normals(vertices: torch.Tensor, triangles: torch.Tensor, camera_center: torch.Tensor) -> torch.Tensor:
    """(B, V, 3) unit vertex normals, each flipped to the side that faces the camera."""
    n = vertex_normals(vertices, triangles)
    to_cam = camera_center.to(vertices) - vertices
    sign = torch.where((n * to_cam).sum(-1, keepdim=True) < 0, -1.0, 1.0).to(n)
    return n * sign.detach()


def irradiance(normals: torch.Tensor, light: torch.Tensor) -> torch.Tensor:
    """(…, V, 1) first-order irradiance 1 + light·n, clamped to MIN_IRRADIANCE."""
    return (1.0 + (normals * light.to(normals)).sum(-1, keepdim=True)).clamp_min(MIN_IRRADIANCE)


def shading_ratio(vertices: torch.Tensor, reference_normals: torch.Tensor, triangles: torch.Tensor,
                  camera_center: torch.Tensor, light: torch.Tensor) -> torch.Tensor:
    """(B, V, 3) per-vertex factors E(n) / E(n_ref) (the same in the three channels) for
    render_cloth(vertex_shading=...). vertices (B, V, 3); reference_normals (V, 3): facing_normals of the
    frame the texture was fitted on; light (3,) the learned first-order light vector."""
    if vertices.dim() == 2:
        vertices = vertices[None]
    n = facing_normals(vertices, triangles, camera_center)
    ratio = irradiance(n, light) / irradiance(reference_normals[None], light)
    return ratio.expand(-1, -1, 3)
