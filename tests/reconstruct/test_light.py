"""The shape phase's light vector (saft.reconstruct.light): absent, learned, or held at a known light."""

import numpy as np
import torch

from saft.reconstruct.config import PhysicsConfig, ShapeConfig
from saft.reconstruct.light import initial_light, light_learned, light_used


def _state(cfg):
    from saft.reconstruct.shape_phase import new_shape_state

    return new_shape_state(4, 9, np.zeros(3), PhysicsConfig(), cfg, "cpu")


def test_unlit_as_the_paper_when_no_light_is_asked_for():
    cfg = ShapeConfig(lr_light=0.0, plain_shading=0.0, light_from_above=0.0)
    assert not light_used(cfg) and initial_light(cfg) is None
    assert _state(cfg).params.light is None
    assert light_used(ShapeConfig())   # the default: a learned light, kept on plain fabrics only (plain_cloth)


def test_a_known_light_is_held_where_the_rate_is_zero():
    cfg = ShapeConfig(lr_light=0.0, light_init=(-0.25, 0.45, 0.4))
    assert light_used(cfg) and not light_learned(cfg)
    state = _state(cfg)
    assert torch.allclose(state.params.light, torch.tensor([-0.25, 0.45, 0.4], dtype=torch.float64))
    assert not state.params.light.requires_grad
    assert "light" not in state.optimizer.specs            # never stepped


def test_a_learned_light_starts_at_light_init():
    cfg = ShapeConfig(lr_light=0.05, light_init=(0.0, 0.3, 0.0))
    state = _state(cfg)
    assert state.params.light.requires_grad and "light" in state.optimizer.specs
    assert torch.equal(state.params.light.detach(), torch.tensor([0.0, 0.3, 0.0], dtype=torch.float64))


class _Ctx:
    """The part of a PhaseContext plain_cloth reads: frame 0, the camera, a render with depth."""

    def __init__(self, rgb0, template, camera):
        from saft.scene.mesh import quad_triangles
        self.target_rgb = torch.as_tensor(rgb0[None], dtype=torch.float32)
        self.target_mask = torch.ones(1, *rgb0.shape[:2])
        self.template_positions = template
        self.triangles = torch.as_tensor(quad_triangles(np.array([[0, 1, 4, 3], [1, 2, 5, 4], [3, 4, 7, 6],
                                                                   [4, 5, 8, 7]])), dtype=torch.int32)
        self.camera = camera

    def render(self, vertices, texture):
        from types import SimpleNamespace
        return SimpleNamespace(depth=torch.zeros(1, *self.target_rgb.shape[1:3]))   # nothing hides anything


def _plain_or_textured(textured: bool):
    from saft.reconstruct.tracks import VertexTracks
    from saft.scene import look_at

    H = W = 64
    K = np.array([[80.0, 0, 31.5], [0, 80.0, 31.5], [0, 0, 1]])
    camera = look_at((0, 0, 1.0), (0, 0, 0), (0, 1, 0), K, W, H)
    g = np.linspace(-0.15, 0.15, 3)
    template = torch.tensor([(x, y, 0.0) for y in g for x in g], dtype=torch.float64)
    rng = np.random.default_rng(0)
    rgb0 = 0.5 + 0.004 * rng.standard_normal((H, W, 3))                       # plain: noise only
    if textured:
        yy, xx = np.mgrid[:H, :W]
        rgb0 = rgb0 + 0.3 * (((yy // 4 + xx // 4) % 2)[..., None] - 0.5)       # a fine checker
    tracks = VertexTracks(points=torch.zeros(2, 9, 2), valid=torch.ones(2, 9, dtype=torch.bool), scale=64.0)
    return _Ctx(rgb0.clip(0, 1), template, camera), template, tracks


def test_plain_shading_keeps_the_light_and_weighs_the_tracks_down_on_a_plain_cloth_only():
    from saft.reconstruct.light import plain_cloth

    cfg = ShapeConfig(lr_light=0.05, plain_shading=0.5)
    for textured in (False, True):
        ctx, template, tracks = _plain_or_textured(textured)
        state = _state(cfg)
        out = plain_cloth(ctx, state, cfg, torch.zeros(4, 4, 3), template, tracks)
        if textured:                   # the unlit run: no light, tracks untouched
            assert state.params.light is None and "light" not in state.optimizer.specs and out is tracks
        else:
            assert state.params.light is not None and "light" in state.optimizer.specs
            assert out.strength < 0.5
    mask = torch.zeros(4, 64, 64)                                   # a clip that starts moving:
    mask[0, 10:50, 10:50] = 1                                       # the silhouette jumps from frame 0 to 1
    mask[1:, 16:56, 10:50] = 1
    mask[3, 16:57, 10:50] = 1
    for bend in (0.0, 0.5):       # a flat cloth in a breeze; a billowed one cut from the middle of its motion
        ctx, template, tracks = _plain_or_textured(False)
        template = template.clone()
        template[:, 2] = bend * template[:, 0].abs()                # a tent: bend_degrees 19.8
        ctx.template_positions, ctx.target_mask = template, mask
        state = _state(cfg)
        assert plain_cloth(ctx, state, cfg, torch.zeros(4, 4, 3), template, tracks) is tracks   # full weight
        assert (state.params.light is None) == (bend > 0)            # the billowed one unlit
    off = _state(ShapeConfig(lr_light=0.05, plain_shading=0.0))   # plain_shading = 0: nothing changes
    ctx, template, tracks = _plain_or_textured(False)
    off_cfg = ShapeConfig(lr_light=0.05, plain_shading=0.0)
    assert plain_cloth(ctx, off, off_cfg, torch.zeros(4, 4, 3), template, tracks) is tracks
    assert off.params.light is not None


def test_a_held_light_survives_a_checkpoint_and_stays_held():
    from saft.reconstruct.shape_phase import restore_shape_state

    cfg = ShapeConfig(lr_light=0.0, light_init=(0.1, 0.4, 0.0))
    back = restore_shape_state(_state(cfg).state_dict(), cfg, "cpu")
    assert torch.allclose(back.params.light, torch.tensor([0.1, 0.4, 0.0], dtype=torch.float64))
    assert "light" not in back.optimizer.specs


def test_the_light_starts_above_the_cloth_where_the_scene_states_gravity():
    from saft.reconstruct.light import scene_up
    from saft.reconstruct.shape_phase import new_shape_state

    cfg = ShapeConfig(lr_light=0.05, light_from_above=0.4)
    assert light_used(cfg)
    up = scene_up([0.0, 0.0, -9.81])                       # a z-up world
    np.testing.assert_allclose(up, [0.0, 0.0, 1.0])
    state = new_shape_state(4, 9, np.zeros(3), PhysicsConfig(), cfg, "cpu", up=up)
    torch.testing.assert_close(state.params.light.detach(), torch.tensor([0.0, 0.0, 0.4], dtype=torch.float64))
    assert state.params.light.requires_grad
    assert scene_up(None) is None and scene_up([0.0, 0.0, 0.0]) is None
    unstated = new_shape_state(4, 9, np.zeros(3), PhysicsConfig(), cfg, "cpu", up=None)
    assert torch.count_nonzero(unstated.params.light) == 0     # no stated gravity: no "above"; learned from zero
