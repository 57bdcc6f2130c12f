"""The texture confidence of point tracks: Shi–Tomasi strength at each track's start in units of the noise."""

import numpy as np
import pytest
import torch

from saft.reconstruct.tracks import (VertexTracks, noise_level, project, texture_confidence,
                                     texture_strength, track_loss)
from saft.scene.camera import look_at
from saft.scene.mesh import quad_triangles
from saft.scene.motion import bend_degrees, starts_curved_in_motion, starts_moving
from saft.synthetic import procedural_texture


def _half_printed_frame(noise: float, seed: int = 0) -> np.ndarray:
    """(96, 192, 3) sRGB: the left half a printed pattern, the right half a plain grey; both with Gaussian
    noise of `noise` (in [0, 1] units)."""
    rng = np.random.default_rng(seed)
    frame = np.full((96, 192, 3), 0.5)
    frame[:, :96] = procedural_texture(96, seed)
    return np.clip(frame + rng.normal(0.0, noise, frame.shape), 0.0, 1.0)


def test_noise_level_recovers_the_noise_of_a_plain_image():
    rng = np.random.default_rng(3)
    for sigma in (2.0, 6.0):
        gray = np.clip(128 + rng.normal(0.0, sigma, (120, 160)), 0, 255)
        assert noise_level(gray, np.ones_like(gray)) == pytest.approx(sigma, rel=0.1)
    assert noise_level(np.zeros((8, 8)), np.zeros((8, 8))) == 0.0


def test_texture_strength_is_high_on_a_print_and_low_on_a_plain_cloth():
    frame = _half_printed_frame(noise=4 / 255)
    mask = np.ones(frame.shape[:2])
    printed = np.array([[float(u), float(v)] for u in (24, 48, 72) for v in (24, 48, 72)])
    plain = printed + [96.0, 0.0]
    q_print, q_plain = texture_strength(frame, mask, printed), texture_strength(frame, mask, plain)
    assert q_print.min() > 20 * q_plain.max()
    assert q_plain.max() < 0.2
    # in units of the noise: more noise on the same print, lower strength
    q_noisy = texture_strength(_half_printed_frame(noise=8 / 255), mask, printed)
    assert np.median(q_noisy) < 0.5 * np.median(q_print)


def test_texture_confidence_weighs_the_loss_of_a_plain_cloth_down():
    frame = _half_printed_frame(noise=4 / 255)
    mask = np.ones(frame.shape[:2])
    printed = np.array([[float(u), float(v)] for u in (24, 48, 72) for v in (24, 48, 72)])
    plain = printed + [96.0, 0.0]
    every = np.ones(len(printed), bool)
    assert texture_confidence(frame, mask, plain, every, 0.0) == 1.0
    assert texture_confidence(frame, mask, printed, every, 1.0) == 1.0
    assert texture_confidence(frame, mask, plain, every, 1.0) < 0.2
    assert texture_confidence(frame, mask, plain, ~every, 1.0) == 1.0   # no track: nothing to weigh
    # the median of the tracks that start: a few printed ones among many plain ones do not lift it
    mixed = np.concatenate([printed[:3], plain])
    assert texture_confidence(frame, mask, mixed, np.ones(len(mixed), bool), 1.0) < 0.2


def test_track_strength_scales_the_loss_absolutely():
    K = np.array([[100.0, 0, 31.5], [0, 100.0, 31.5], [0, 0, 1]])
    cam = look_at((0.1, 0.05, 1.0), (0, 0, 0), (0, 1, 0), K, 64, 64)
    x = torch.zeros(1, 2, 3, dtype=torch.float64)
    uv, _ = project(x, cam)
    off = uv + torch.tensor([[1.0, 0.0], [2.0, 0.0]], dtype=torch.float64)
    valid = torch.ones(1, 2, dtype=torch.bool)
    full = float(track_loss(x, VertexTracks(off, valid, 64.0), cam, 3.0))
    assert float(track_loss(x, VertexTracks(off, valid, 64.0, strength=0.25), cam, 3.0)) == pytest.approx(0.25 * full)
    w = torch.tensor([[1.0, 1.0]])   # the normalised weights keep their mean; the strength scales it
    assert float(track_loss(x, VertexTracks(off, valid, 64.0, weight=w, strength=0.25),
                            cam, 3.0)) == pytest.approx(0.25 * full)


def test_a_reconstruction_with_texture_confidence_runs(tiny_reconstruction):
    out = tiny_reconstruction(["shape.track_texture=1e6"])
    assert (out / "log.csv").is_file()


def _moving_square(still_frames: int, n: int = 6) -> np.ndarray:
    """(n, 40, 40) masks of a square that stands for `still_frames` frames, then moves 2 px per frame."""
    masks = np.zeros((n, 40, 40))
    for t in range(n):
        x = 5 + 2 * max(0, t - still_frames)
        masks[t, 10:30, x:x + 15] = 1.0
    return masks


def test_a_clip_starts_moving_where_its_silhouette_changes_from_frame_0():
    assert starts_moving(_moving_square(still_frames=0))
    assert not starts_moving(_moving_square(still_frames=1))   # at rest for a frame, then moving
    assert not starts_moving(_moving_square(still_frames=0)[:1])
    assert not starts_moving(np.ones((4, 8, 8)))                # nothing moves at all


def _grid(bend: float) -> tuple[np.ndarray, np.ndarray]:
    """A 5 x 5 grid of 0.1 m quads bent about its middle column into a tent of slope `bend`; its triangles."""
    g = np.linspace(-0.2, 0.2, 5)
    v = np.array([(x, y, bend * abs(x)) for y in g for x in g])
    quads = np.array([[r * 5 + c, r * 5 + c + 1, (r + 1) * 5 + c + 1, (r + 1) * 5 + c]
                      for r in range(4) for c in range(4)])
    return v, quad_triangles(quads)


def test_bend_degrees_is_zero_for_a_plane_and_the_tent_angle_for_a_tent():
    assert bend_degrees(*_grid(0.0)) == pytest.approx(0.0, abs=1e-9)
    # the faces of a tent of slope 0.5 tilt by atan(0.5) = 26.6 deg; the ridge's normals stay on the mean
    tilted = bend_degrees(*_grid(0.5))
    assert 15.0 < tilted < np.degrees(np.arctan(0.5))
    assert bend_degrees(*_grid(0.1)) < bend_degrees(*_grid(0.3)) < tilted


def test_only_a_clearly_curved_clip_in_motion_starts_curved_in_motion():
    moving, still = _moving_square(still_frames=0), _moving_square(still_frames=1)
    assert starts_curved_in_motion(moving, *_grid(0.5))
    assert not starts_curved_in_motion(moving, *_grid(0.0))     # a flat cloth already in a breeze
    assert not starts_curved_in_motion(moving, *_grid(0.05))    # a real template's few degrees
    assert not starts_curved_in_motion(still, *_grid(0.5))      # curved but at rest
