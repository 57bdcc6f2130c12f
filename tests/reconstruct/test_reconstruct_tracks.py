"""Point tracks from optical flow and the track loss of the shape phase."""

import numpy as np
import pytest
import torch

from saft.reconstruct.config import ShapeConfig
from saft.reconstruct.optim import ClippedAdam, ParamSpec
from saft.reconstruct.frame_schedule import lr_factor
from saft.reconstruct.tracks import (VertexTracks, appearance_steps, bilinear_sample, end_at_appearance_jumps,
                                     drift_confidence, end_at_colour_drift, project,
                                     track_loss, track_points)
from saft.scene.camera import look_at
from saft.synthetic import procedural_texture


def _smooth_texture(size: int, seed: int = 0) -> np.ndarray:
    return procedural_texture(size, seed)


def test_bilinear_sample_interpolates_and_clamps():
    img = np.arange(12, dtype=np.float64).reshape(3, 4)
    pts = np.array([[0.0, 0.0], [1.5, 0.0], [1.0, 1.5], [10.0, -3.0]])
    assert np.allclose(bilinear_sample(img, pts), [0.0, 1.5, 7.0, 3.0])


def test_tracks_follow_a_translating_pattern():
    tex = _smooth_texture(160)
    shifts = [(0.0, 0.0), (2.0, 1.0), (4.0, 2.0), (6.0, 3.0)]
    frames = np.stack([np.roll(tex, (int(dy), int(dx)), axis=(0, 1)) for dx, dy in shifts])
    mask = np.ones(frames.shape[:3], dtype=np.float32)
    start = np.array([[40.0, 50.0], [80.0, 80.0], [100.0, 60.0]])
    pts, valid = track_points(frames, mask, start, np.ones(3, bool), fb_threshold=1.0)
    assert valid.all()
    for t, (dx, dy) in enumerate(shifts):
        assert np.abs(pts[t] - (start + [dx, dy])).max() < 0.35


def test_reanchoring_to_frame_0_removes_the_drift_of_chained_flow():
    from scipy.ndimage import shift as nd_shift
    tex = _smooth_texture(160)
    shifts = [(0.37 * t, 0.23 * t) for t in range(16)]           # sub-pixel steps: chained flow drifts
    frames = np.stack([np.stack([nd_shift(tex[..., c], (dy, dx), order=3, mode="wrap") for c in range(3)], -1)
                       for dx, dy in shifts]).clip(0, 1)
    mask = np.ones(frames.shape[:3], dtype=np.float32)
    start = np.random.default_rng(0).uniform(40, 110, (50, 2))
    err = {}
    for radius in (0.0, 2.0):
        pts, valid = track_points(frames, mask, start, np.ones(50, bool), 1.0, reanchor_radius=radius)
        assert valid[-1].all()
        err[radius] = np.median(np.linalg.norm(pts[-1] - (start + shifts[-1]), axis=1))
    assert err[0.0] > 0.5                                          # about 0.9 px after 15 frames
    assert err[2.0] < 0.2 and err[2.0] < err[0.0] / 4


def test_a_track_ends_where_the_flow_is_not_consistent_or_leaves_the_mask():
    rng = np.random.default_rng(0)
    tex = _smooth_texture(128)
    noise = rng.uniform(0, 1, tex.shape).astype(np.float32)       # frame 1 unrelated to frame 0
    frames = np.stack([tex, noise, noise])
    mask = np.ones(frames.shape[:3], dtype=np.float32)
    start = rng.uniform(20, 100, (40, 2))
    _, valid = track_points(frames, mask, start, np.ones(40, bool), fb_threshold=0.5)
    assert valid[0].all() and valid[1].mean() < 0.5
    assert not (valid[2] & ~valid[1]).any()                       # once lost, lost for good
    mask_off = mask.copy()
    mask_off[1:] = 0.0
    _, valid = track_points(np.stack([tex, tex]), mask_off[:2], start, np.ones(40, bool))
    assert not valid[1].any()


def _camera():
    K = np.array([[100.0, 0, 31.5], [0, 100.0, 31.5], [0, 0, 1]])
    return look_at((0.1, 0.05, 1.0), (0, 0, 0), (0, 1, 0), K, 64, 64)


def test_projection_matches_the_camera():
    cam = _camera()
    pts = np.random.default_rng(1).uniform(-0.2, 0.2, (10, 3))
    uv, z = project(torch.tensor(pts), cam)
    uv_ref, z_ref = cam.project(pts)
    assert np.allclose(uv.numpy(), uv_ref) and np.allclose(z.numpy(), z_ref)


def test_track_loss_is_zero_on_the_tracks_and_pulls_towards_them():
    cam = _camera()
    x = torch.tensor(np.random.default_rng(2).uniform(-0.2, 0.2, (2, 5, 3)))
    uv, _ = project(x, cam)
    valid = torch.ones(2, 5, dtype=torch.bool)
    tracks = VertexTracks(points=uv.clone(), valid=valid, scale=64.0)
    assert float(track_loss(x, tracks, cam, huber_delta=3.0)) == pytest.approx(0.0, abs=1e-20)
    moved = x.clone()
    moved[1, 2, 0] += 0.01
    moved.requires_grad_(True)
    loss = track_loss(moved, tracks, cam, huber_delta=3.0)
    loss.backward()
    assert float(loss.detach()) > 0
    assert moved.grad[1, 2, 0] > 0 and float(moved.grad[0].abs().sum()) == 0.0
    # an invalid track contributes nothing
    tracks.valid[1, 2] = False
    assert float(track_loss(moved.detach(), tracks, cam, huber_delta=3.0)) == pytest.approx(0.0, abs=1e-20)


def test_huber_counts_far_residuals_linearly():
    cam = _camera()
    x = torch.zeros(1, 1, 3, dtype=torch.float64)
    uv, _ = project(x, cam)
    losses = []
    for d in (10.0, 20.0):
        tracks = VertexTracks(points=uv + torch.tensor([d, 0.0], dtype=torch.float64), valid=torch.ones(1, 1, dtype=torch.bool),
                              scale=1.0)
        losses.append(float(track_loss(x, tracks, cam, huber_delta=2.0)))
    assert losses[1] - losses[0] == pytest.approx(2.0 * 10.0)


def test_final_learning_rate_decay_is_a_cosine_to_the_fraction():
    cfg = ShapeConfig(final_epochs=5, final_lr_fraction=0.1)
    assert lr_factor(3, 10, cfg) == 1.0
    assert lr_factor(10, 10, cfg) == pytest.approx(1.0)
    assert lr_factor(12, 10, cfg) == pytest.approx(0.55)
    assert lr_factor(14, 10, cfg) == pytest.approx(0.1)
    assert lr_factor(14, 10, ShapeConfig(final_epochs=5, final_lr_fraction=1.0)) == 1.0
    p = torch.zeros(2, requires_grad=True)
    opt = ClippedAdam([ParamSpec("p", p, 0.2)])
    opt.set_lr_factor(0.5)
    assert opt.optims["p"].param_groups[0]["lr"] == pytest.approx(0.1)


def test_autoclip_of_the_reference_uses_earlier_norms_only():
    p = torch.zeros(1, requires_grad=True)
    opt = ClippedAdam([ParamSpec("p", p, 0.1)], clip=1e3, quantile=0.75, history=2, include_current=False)
    for g in (1.0, 2.0, 8.0):
        p.grad = torch.tensor([g])
        opt.step()
    assert opt.history["p"] == [2.0, 8.0]          # the last 2 norms, unclipped values recorded
    p.grad = torch.tensor([100.0])
    opt.step()
    assert float(p.grad) == pytest.approx(np.quantile([2.0, 8.0], 0.75))  # clipped by the earlier norms only


def test_a_window_from_stored_states_continues_the_full_simulation():
    from saft.reconstruct.config import PhysicsConfig
    from saft.reconstruct.shape_phase import ShapeSimulator, new_shape_state
    from saft.synthetic import grid_template

    mesh = grid_template(5, 0.3)
    template = torch.tensor(mesh.vertices)
    sim = ShapeSimulator(template, mesh.quads, PhysicsConfig(), 0.02, np.arange(5))
    state = new_shape_state(7, len(template), np.array([0.0, -9.81, 0.0]), PhysicsConfig(), ShapeConfig(), "cpu")
    with torch.no_grad():
        state.params.vertex_accel.normal_(0.0, 2.0, generator=torch.Generator().manual_seed(0))
        full = sim.simulate(state.params, 7)
        x, v = sim.simulate_from(state.params, 0, 7)
        assert torch.allclose(x, full, atol=1e-9)
        x3, _ = sim.simulate_from(state.params, 3, 7, x[3], v[3])
    assert torch.allclose(x3, full[3:], atol=1e-8)


def test_a_windowed_step_leaves_the_accelerations_before_the_window():
    """Adam's momentum would move the accelerations of frames before the window (no gradient there): the
    windowed step restores them; the window's own accelerations and the global parameters move."""
    from saft.reconstruct.config import PhysicsConfig
    from saft.reconstruct.shape_phase import new_shape_state
    from saft.reconstruct.window_hold import outside_window, restore_outside_window

    state = new_shape_state(6, 9, np.array([0.0, -9.81, 0.0]), PhysicsConfig(), ShapeConfig(window=2), "cpu")
    params = state.params
    for t in params.tensors().values():           # a full pass: every parameter gets a gradient
        t.grad = torch.ones_like(t)
    state.optimizer.step()
    before = {k: t.detach().clone() for k, t in params.tensors().items()}
    for t in params.tensors().values():           # a window from frame 3: gradients there only
        t.grad = torch.zeros_like(t)
    params.vertex_accel.grad[3:] = 1.0
    params.const_accel.grad = torch.ones_like(params.const_accel)
    keep = outside_window(params, 3)
    state.optimizer.step()
    restore_outside_window(params, 3, keep)
    assert torch.equal(params.vertex_accel[:3], before["vertex_accel"][:3])
    assert not torch.equal(params.vertex_accel[3:], before["vertex_accel"][3:])
    assert not torch.equal(params.const_accel, before["const_accel"])
    assert outside_window(params, 0) is None      # a full pass: nothing is held


def test_a_window_after_a_full_step_starts_from_refreshed_states():
    """A full pass's step changes every acceleration: the stored states are stale, and the next window is
    simulated from states brought up to date (forward only), so it equals a full simulation."""
    from saft.reconstruct.config import PhysicsConfig
    from saft.reconstruct.shape_phase import FrameStates, ShapeSimulator, new_shape_state, simulate_epoch
    from saft.synthetic import grid_template

    mesh = grid_template(5, 0.3)
    template = torch.tensor(mesh.vertices)
    sim = ShapeSimulator(template, mesh.quads, PhysicsConfig(), 0.02, np.arange(5))
    state = new_shape_state(8, len(template), np.array([0.0, -9.81, 0.0]), PhysicsConfig(), ShapeConfig(), "cpu")
    zeros = template.new_zeros((8,) + tuple(template.shape))
    state.states = FrameStates(zeros.clone(), zeros.clone(), 1)
    gen = torch.Generator().manual_seed(1)
    with torch.no_grad():
        state.params.vertex_accel.normal_(0.0, 2.0, generator=gen)
        simulate_epoch(sim, state, 8, 0)                      # a full pass stores every state
        assert state.states.fresh == 8
        state.params.vertex_accel.add_(torch.randn(state.params.vertex_accel.shape, generator=gen,
                                                   dtype=state.params.vertex_accel.dtype))
        state.states.stepped(0)                               # ... and its step makes them stale
        assert state.states.fresh == 1
        window = simulate_epoch(sim, state, 8, 4)
        assert torch.allclose(window, sim.simulate(state.params, 8)[4:], atol=1e-8)
        assert state.states.fresh == 8
        state.states.stepped(4)                               # a window's step: states up to frame 4 hold
        assert state.states.fresh == 5


def test_windowed_epochs_run_and_keep_gradients(tmp_path):
    """A tiny reconstruction whose epochs start from stored states (shape.window) runs end to end."""
    from saft.config_io import load_config
    from saft.reconstruct import SaftConfig, reconstruct
    from saft.result import read_result
    from saft.scene import load_scene
    from saft.synthetic import HangingClothSpec, write_hanging_cloth

    spec = HangingClothSpec(grid=6, size=0.4, frames=7, image_size=48, focal=92.0, texture_size=32, gt_points=200)
    scene = load_scene(write_hanging_cloth(tmp_path / "scene", spec))
    cfg = load_config(SaftConfig, None, ["texture.epochs=5", "texture.size=32", 'run.device="cpu"',
                                         "appearance.enabled=false", "shape.window=2", "shape.full_pass_every=4",
                                         "shape.add_frame_every=2", "shape.final_epochs=2", "shape.lambda_track=2e3"])
    reconstruct(scene, cfg, tmp_path / "out", quiet=True)
    r = read_result(tmp_path / "out")
    assert r.num_frames == 7 and np.isfinite(r.vertices).all()


def test_vertices_behind_another_layer_of_cloth_are_hidden():
    from saft.render import get_rasterizer
    from saft.render.cloth import render_cloth
    from saft.reconstruct.tracks import hidden_vertices

    cam = _camera()
    g = np.linspace(-0.15, 0.15, 6)
    xx, yy = np.meshgrid(g, g)
    front = np.stack([xx.ravel(), yy.ravel(), np.full(36, 0.05)], 1)
    back = front * [0.8, 0.8, 1.0] - [0.0, 0.0, 0.15]              # a smaller layer 15 cm behind
    verts = torch.as_tensor(np.concatenate([front, back]), dtype=torch.float64)
    quads = [(r * 6 + c, r * 6 + c + 1, r * 6 + c + 7, r * 6 + c + 6) for r in range(5) for c in range(5)]
    tris = np.array([t for q in quads for t in ((q[0], q[1], q[2]), (q[0], q[2], q[3]))])
    tris = np.concatenate([tris, tris + 36])
    uvs = torch.zeros(72, 2)
    depth = render_cloth(verts[None].float(), tris, uvs, torch.ones(4, 4, 3), cam,
                         rasterizer=get_rasterizer("torch")).depth
    hidden = hidden_vertices(verts[None], depth, cam, tolerance=0.03)[0]
    assert not hidden[:36].any()           # the front layer is what the camera sees
    assert hidden[36:].all()               # every vertex of the back layer lies behind it
    assert not hidden_vertices(verts[None], depth, cam, tolerance=0.5)[0].any()


def test_hidden_tracks_do_not_count():
    cam = _camera()
    pos = torch.zeros(1, 2, 3, dtype=torch.float64)
    uv, _ = project(pos, cam)
    pts = uv.clone()
    pts[0, 1] += 10.0                       # vertex 1's track is 10 px off
    tr = VertexTracks(points=pts, valid=torch.ones(1, 2, dtype=torch.bool), scale=64.0)
    assert float(track_loss(pos, tr, cam, 3.0)) > 0
    hidden = torch.tensor([[False, True]])
    assert float(track_loss(pos, tr, cam, 3.0, hidden=hidden)) == pytest.approx(0.0, abs=1e-15)


def test_a_track_ends_at_its_first_colour_jump():
    rng = np.random.default_rng(0)
    tex = _smooth_texture(96)
    frames = np.stack([tex] * 6) + rng.normal(0, 0.004, (6,) + tex.shape)
    grid = np.stack(np.meshgrid(np.arange(20.0, 80.0, 10.0), np.arange(20.0, 70.0, 10.0)), -1).reshape(-1, 2)
    points = np.repeat((grid + rng.uniform(-1, 1, grid.shape))[None], 6, axis=0)    # 30 points 10 px apart
    covered = np.zeros(30, bool)
    covered[:10] = True
    other = np.roll(_smooth_texture(96, seed=5), 17, axis=0)         # a flap printed with another pattern
    for t in range(3, 6):
        for u, v in points[t][covered]:
            r, c = int(round(v)), int(round(u))
            frames[t, r - 3:r + 4, c - 3:c + 4] = other[r - 3:r + 4, c - 3:c + 4]
    valid = np.ones((6, 30), bool)
    steps = appearance_steps(frames, points)
    assert steps[0].max() == 0.0 and np.median(steps[1:]) < 0.01
    kept = end_at_appearance_jumps(frames, points, valid, jump_ratio=8.0, jump_floor=0.03)
    jumped = covered & (steps[3] > 0.05)                             # where the flap's print differs enough
    assert jumped.sum() >= 8
    assert kept[:3].all() and kept[:, ~covered].all()
    assert not kept[3:, jumped].any()                                # ended for good, not just in frame 3
    assert (end_at_appearance_jumps(frames, points, valid, 0.0, 0.03) == valid).all()   # 0 = off


def test_the_colour_jump_threshold_follows_the_videos_noise():
    rng = np.random.default_rng(1)
    tex = _smooth_texture(96)
    points = np.repeat(rng.uniform(20, 76, (40, 2))[None], 8, axis=0)
    valid = np.ones((8, 40), bool)
    quiet = np.stack([tex] * 8) + rng.normal(0, 0.002, (8,) + tex.shape)
    noisy = np.stack([tex] * 8) + rng.normal(0, 0.05, (8,) + tex.shape)  # a noisy camera: no track ends
    assert end_at_appearance_jumps(noisy, points, valid, 8.0, 0.03).all()
    quiet[5:] += 0.2                                                 # a jump far above the quiet noise
    kept = end_at_appearance_jumps(quiet, points, valid, 8.0, 0.03)
    assert kept[:5].all() and not kept[5:].any()


def test_a_track_ends_where_its_colour_drifts_slowly_but_not_where_its_shading_changes():
    rng = np.random.default_rng(2)
    tex = _smooth_texture(96)
    frames = np.stack([tex * (1.0 - 0.06 * t) for t in range(8)])   # the cloth darkens as it turns
    points = np.repeat(rng.uniform(20, 76, (40, 2))[None], 8, axis=0)
    points[:, :10] += np.arange(8.0)[:, None, None] * np.array([2.0, 0.0])   # 10 tracks slide 2 px a frame
    valid = np.ones((8, 40), bool)
    kept = end_at_colour_drift(frames, points, valid, 0.02)
    assert kept[:, 10:].all()                                        # darker, same chromaticity: kept
    assert not kept[-1, :10].any() and kept[0].all()               # 14 px onto other threads: all ended
    ended = ~kept[-1]
    assert not kept[np.argmax(~kept, axis=0)[ended].max():, ended].any()   # ended for good
    assert (end_at_colour_drift(frames, points, valid, 0.0) == valid).all()  # 0 = off


def test_drift_confidence_weighs_down_sliding_tracks_and_the_loss_follows_it():
    rng = np.random.default_rng(2)
    tex = _smooth_texture(96)
    frames = np.stack([tex * (1.0 - 0.06 * t) for t in range(8)])
    points = np.repeat(rng.uniform(20, 76, (40, 2))[None], 8, axis=0)
    points[:, :10] += np.arange(8.0)[:, None, None] * np.array([2.0, 0.0])
    w = drift_confidence(frames, points, 0.03)
    assert np.allclose(w[0], 1.0) and w[:, 10:].min() > 0.9         # shading only: full weight
    assert w[-1, :10].max() < 0.5 and (np.diff(w, axis=0) <= 0).all()  # slid: weighed down, never back up
    assert drift_confidence(frames, points, 0.0) is None
    # the track loss is the weighted mean: a track of weight 0 does not count
    cam = _camera()
    x = torch.zeros(1, 2, 3, dtype=torch.float64)
    uv, _ = project(x, cam)
    off = uv + torch.tensor([[0.0, 0.0], [2.0, 0.0]], dtype=torch.float64)
    valid = torch.ones(1, 2, dtype=torch.bool)
    full = track_loss(x, VertexTracks(off, valid, 64.0), cam, huber_delta=3.0)
    half = track_loss(x, VertexTracks(off, valid, 64.0, weight=torch.tensor([[1.0, 1.0 / 3.0]])), cam, 3.0)
    none = track_loss(x, VertexTracks(off, valid, 64.0, weight=torch.tensor([[1.0, 0.0]])), cam, 3.0)
    assert float(none) == pytest.approx(0.0, abs=1e-20)
    assert float(half) == pytest.approx(float(full) * 2 * (1 / 3) / (4 / 3))


def test_a_reconstruction_with_soft_track_confidence_runs(tiny_reconstruction):
    out = tiny_reconstruction(["shape.track_drift_scale=0.03"])
    assert (out / "log.csv").is_file()
