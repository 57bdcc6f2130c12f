"""Two starts, chosen on held-out frames: the glossier fit is kept only if it predicts frames it never saw
better, beyond the frame-to-frame noise of that comparison."""

from types import SimpleNamespace

import numpy as np
import torch

from saft.appearance.two_starts import paired_z, pick, product_loss, split_frames, undetermined_roughness_note


def _fit(roughness: float, losses: list[float], init: float):
    return SimpleNamespace(roughness=np.full((4, 4), roughness, np.float32), held_out_loss=losses,
                           fitted_loss=[0.5], config=SimpleNamespace(init_roughness=init), cpu_seconds=1.0)


def test_split_holds_out_every_kth_frame_and_never_fits_it():
    fit, held = split_frames(32, 4)
    assert list(held) == [2, 6, 10, 14, 18, 22, 26, 30]
    assert len(fit) == 24 and not set(fit) & set(held)
    fit, held = split_frames(32, 4, "last")
    assert list(held) == list(range(24, 32)) and list(fit) == list(range(24))
    fit, held = split_frames(5, 4)            # too short to spare frames: scored in-sample
    assert list(fit) == list(held) == [0, 1, 2, 3, 4]


def test_paired_z_is_the_mean_difference_in_standard_errors():
    assert paired_z([1.0, 2.0, 3.0], [1.1, 2.1, 3.1]) == np.inf        # always 0.1 better: no noise
    z = paired_z([1.0, 1.0, 1.0, 1.0], [1.2, 0.9, 1.1, 0.9])           # mean 0.025, sd 0.15
    assert abs(z - 0.025 / (np.std([0.2, -0.1, 0.1, -0.1], ddof=1) / 2)) < 1e-9
    assert paired_z([1.2, 1.2], [1.0, 1.1]) < 0


def test_pick_keeps_the_fit_that_predicts_the_held_out_frames_and_says_when_that_is_noise():
    matte = _fit(0.88, [1.0, 1.2, 0.9, 1.1], 0.9)
    # better on average but not on every frame: kept, yet the roughness is reported undetermined
    kept, rec = pick(_fit(0.55, [0.9, 1.25, 0.8, 1.12], 0.6), matte, z=2.0)
    assert rec["winner"] == "profile_start" and not rec["determined"]
    assert "not determined" in undetermined_roughness_note(rec)
    # a highlight predicted on every held-out frame: the data insists
    kept, rec = pick(_fit(0.2, [0.3, 0.5, 0.2, 0.4], 0.6), matte, z=2.0)
    assert rec["winner"] == "profile_start" and rec["determined"]
    assert undetermined_roughness_note(rec) is None
    # the glossier is judged by the fitted roughness, not by which start it came from
    kept, rec = pick(_fit(0.9, [1.0, 1.1], 0.6), _fit(0.5, [0.5, 0.6], 0.9), z=2.0)
    assert rec["winner"] == "matte_start"
    # the matter fit clearly better on the held-out frames (the glossy one overfitted the fitted frames)
    kept, rec = pick(_fit(0.3, [2.0, 2.2, 2.1, 2.0], 0.6), matte, z=2.0)
    assert kept is matte and rec["determined"]
    assert rec["held_out_loss"]["matte_start"] == 1.05


def test_product_loss_removes_the_noise_floor():
    g = torch.Generator().manual_seed(0)
    target = torch.full((64, 64, 3), 0.5)
    ones, mask = torch.ones_like(target), torch.ones(64, 64)
    a = 0.6 + 0.2 * torch.randn(target.shape, generator=g)   # mean off by 0.1, noise 0.2
    b = 0.6 + 0.2 * torch.randn(target.shape, generator=g)
    assert abs(float(product_loss(a, b, target, ones, mask)) - 0.01) < 0.003
    assert float(product_loss(a, a, target, ones, mask)) > 0.04   # a squared residual carries the noise


def test_two_start_fit_records_its_choice_and_saves_it(tmp_path):
    import json

    from saft.appearance.config import cpu_profile
    from saft.appearance.fit import fit_appearance, load_appearance, save_appearance
    from saft.appearance.params import linear_to_srgb
    from saft.synthetic.appearance import make_scene

    sc = make_scene(n_frames=8, image_size=32, map_size=32, render_spp=16)
    texture = linear_to_srgb(torch.as_tensor(sc.diffuse)).numpy()
    cfg = cpu_profile()
    cfg.epochs, cfg.frames_per_epoch, cfg.texel_size, cfg.image_scale = 4, 2, 64, 1.0
    cfg.matte_start_roughness = 0.9
    epochs = []
    res = fit_appearance(sc.vertices, sc.triangles, sc.uvs, sc.camera, sc.rgb, sc.mask, cfg, init_texture=texture,
                         progress=lambda e, n, loss: epochs.append(e))
    rec = res.start_choice
    assert epochs == [1, 2, 3, 4] * 2                        # two fits
    assert rec["held_out_frames"] == [2, 6] and rec["winner"] in ("profile_start", "matte_start")
    assert rec["init_roughness"] == {"profile_start": cfg.init_roughness, "matte_start": 0.9}
    assert len(rec["held_out_loss_per_frame"]["matte_start"]) == 2
    assert res.config.init_roughness == cfg.init_roughness   # the run's config, not the kept start's
    save_appearance(res, tmp_path)
    saved = json.loads((tmp_path / "material" / "appearance.json").read_text())
    assert saved["start_choice"]["winner"] == rec["winner"]
    assert ("not determined" in (saved.get("undetermined") or "")) == (not rec["determined"])
    assert load_appearance(tmp_path).start_choice == saved["start_choice"]
