"""The appearance scenes' motion (saft.synthetic.appearance.appearance_motion): start > 0 gives a curved frame 0."""

from __future__ import annotations

import numpy as np

from saft.scene.mesh import vertex_normals
from saft.synthetic.appearance import AppearanceSceneSpec, appearance_motion

TINY = AppearanceSceneSpec(grid=6, frames=3, frame_dt=0.04)


def test_start_drops_simulated_frames_and_makes_frame_zero_the_template():
    flat_template, flat, held = appearance_motion(TINY)
    np.testing.assert_allclose(flat[0], flat_template.vertices, atol=1e-12)     # frame 0 = the rest shape
    assert np.ptp(flat[0][:, 2]) < 1e-12                                         # a plane
    start = 12
    template, positions, held_s = appearance_motion(AppearanceSceneSpec(grid=6, frames=3, frame_dt=0.04, start=start))
    longer = appearance_motion(AppearanceSceneSpec(grid=6, frames=start + 3, frame_dt=0.04))[1]
    assert positions.shape == flat.shape
    np.testing.assert_allclose(positions, longer[start:], atol=1e-12)           # the same simulation, later
    np.testing.assert_allclose(template.vertices, positions[0], atol=1e-12)     # template = frame 0
    np.testing.assert_array_equal(template.quads, flat_template.quads)
    np.testing.assert_array_equal(held_s, held)
    # frame 0 is billowed: its normals spread, where the flat one's are all equal
    n = vertex_normals(template.vertices, template.triangles)
    assert np.degrees(np.arccos(np.clip(n @ n.mean(0) / np.linalg.norm(n.mean(0)), -1, 1))).max() > 5
