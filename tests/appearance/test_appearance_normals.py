"""appearance.normals: the learnt shading-normal correction (a smooth tangent offset, zero at frame 0), and
the renderer's gradient to the shading normals."""

import numpy as np
import torch

from saft.appearance.normals import NormalCorrection, tangent_frames, uv_hat_basis
from saft.appearance.renderer import ClothRenderer
from saft.scene.mesh import vertex_normals
from saft.synthetic.appearance import make_scene


def test_hat_basis_is_a_partition_of_unity():
    uv = np.random.default_rng(0).random((50, 2))
    for grid in (1, 2, 4):
        b = uv_hat_basis(uv, grid)
        assert b.shape == (50, grid * grid) and np.all(b >= 0)
        assert np.allclose(b.sum(1), 1.0)


def test_tangent_frames_are_orthonormal():
    sc = make_scene(n_frames=3, image_size=16, map_size=8, render=False)
    n, t, s = tangent_frames(sc.vertices, sc.triangles, sc.uvs)
    for a, b in ((n, t), (n, s), (t, s)):
        assert np.abs((a * b).sum(-1)).max() < 1e-6
    for a in (n, t, s):
        assert np.allclose(np.linalg.norm(a, axis=-1), 1.0)


def test_correction_starts_at_the_meshes_normals_and_frame_0_stays():
    sc = make_scene(n_frames=6, image_size=16, map_size=8, render=False)
    nc = NormalCorrection(sc.vertices, sc.triangles, sc.uvs, grid=2, keys=3)
    for f in (0, 3, 5):
        assert np.allclose(nc(f).detach().numpy(), vertex_normals(sc.vertices[f], sc.triangles), atol=1e-5)
    with torch.no_grad():
        nc.coeffs.add_(0.2)
    assert np.allclose(nc(0).detach().numpy(), vertex_normals(sc.vertices[0], sc.triangles), atol=1e-5)
    tilt = nc.tilt_degrees()
    assert tilt[0] < 1e-3 and tilt[5] > 5.0 and tilt[1] < tilt[5]
    assert float(nc.penalty().detach()) > 0


def test_renderer_gradient_reaches_the_normals():
    sc = make_scene(n_frames=2, image_size=24, map_size=16, render=False)
    r = ClothRenderer(sc.triangles, sc.uvs, sc.camera, map_shape=(16, 16), env_shape=(16, 32))
    r.set_vertices(sc.vertices[1])
    nc = NormalCorrection(sc.vertices, sc.triangles, sc.uvs, grid=2, keys=0)
    env = torch.ones(16, 32, 3)
    env[:8] = 4.0   # brighter from above: a tilt changes the shading
    maps = (torch.full((16, 16, 3), 0.5), torch.full((16, 16), 0.3), torch.zeros(16, 16), env)
    plain = r.render(*maps, spp=16, seed=3)
    same = r.render(*maps, spp=16, seed=3, normals=nc(1))
    assert torch.allclose(plain, same, atol=1e-5)
    r.render(*maps, spp=16, seed=3, normals=nc(1)).sum().backward()
    assert nc.coeffs.grad is not None and float(nc.coeffs.grad.abs().sum()) > 0


def test_fit_with_the_correction_and_the_blurred_loss_resumes():
    from saft.appearance.config import cpu_profile
    from saft.appearance.fit import fit_appearance

    sc = make_scene(n_frames=3, image_size=32, map_size=16, render_spp=16)
    cfg = cpu_profile()
    cfg.maps, cfg.texel_size, cfg.env_levels, cfg.env_height, cfg.env_width = "texels", 32, 1, 16, 32
    cfg.epochs, cfg.image_scale, cfg.frames_per_epoch, cfg.checkpoint_every = 4, 1.0, 2, 2
    cfg.normal_grid, cfg.normal_keys, cfg.lr_normals, cfg.loss_blur = 2, 0, 0.05, 1.5
    moving = fit_appearance(sc.vertices, sc.triangles, sc.uvs, sc.camera, sc.rgb, sc.mask, cfg)
    assert "normals" not in moving.state   # it starts curved in motion: the meshes' own normals (saft.scene.motion)
    at_rest = lambda a: np.concatenate([np.asarray(a)[:1], np.asarray(a)])   # frame 0 held for a frame
    verts, rgb, mask = at_rest(sc.vertices), at_rest(sc.rgb), at_rest(sc.mask)
    states = []
    res = fit_appearance(verts, sc.triangles, sc.uvs, sc.camera, rgb, mask, cfg, checkpoint=states.append)
    assert np.isfinite(res.losses).all() and "normals" in res.state
    coeffs = res.state["normals"]["coeffs"]
    assert coeffs.shape == (3, 4, 2) and float(coeffs.abs().max()) > 0   # keys 1-3 of 4 frames were learnt
    resumed = fit_appearance(verts, sc.triangles, sc.uvs, sc.camera, rgb, mask, cfg, resume_state=states[0])
    assert len(resumed.losses) == 4 and resumed.losses[:2] == states[0]["losses"]
