"""Two starts, Occam's choice: the matte fit is kept unless the glossier one is clearly better."""

from types import SimpleNamespace

import numpy as np
import torch

from saft.appearance.two_starts import choose, pick, product_loss


def _fit(roughness: float, losses: list[float], init: float):
    return SimpleNamespace(roughness=np.full((4, 4), roughness, np.float32), held_out_loss=losses,
                           config=SimpleNamespace(init_roughness=init), cpu_seconds=1.0)


def test_choose_prefers_matte_inside_the_margin():
    assert choose(0.94, 1.0, margin=0.1) == "matte"      # 6 % better: not enough (the cotton case)
    assert choose(0.5, 1.0, margin=0.1) == "glossy"      # a highlight explained: the data insists
    assert choose(1.2, 1.0, margin=0.0) == "matte"


def test_pick_keeps_the_matte_start_unless_the_glossy_one_wins_by_the_margin():
    glossy, matte = _fit(0.55, [0.94, 0.94], 0.6), _fit(0.88, [1.0, 1.0], 0.9)
    kept, rec = pick(glossy, matte, margin=0.1)
    assert kept is matte and rec["winner"] == "matte_start"
    assert rec["held_out_loss"] == {"profile_start": 0.94, "matte_start": 1.0}
    kept, rec = pick(_fit(0.1, [0.3, 0.3], 0.6), matte, margin=0.1)
    assert rec["winner"] == "profile_start"
    # the glossier is judged by the fitted roughness, not by which start it came from
    kept, rec = pick(_fit(0.9, [1.0], 0.6), _fit(0.5, [0.95], 0.9), margin=0.1)
    assert rec["winner"] == "profile_start"


def test_product_loss_removes_the_noise_floor():
    g = torch.Generator().manual_seed(0)
    target = torch.full((64, 64, 3), 0.5)
    ones, mask = torch.ones_like(target), torch.ones(64, 64)
    a = 0.6 + 0.2 * torch.randn(target.shape, generator=g)   # mean off by 0.1, noise 0.2
    b = 0.6 + 0.2 * torch.randn(target.shape, generator=g)
    assert abs(float(product_loss(a, b, target, ones, mask)) - 0.01) < 0.003
    assert float(product_loss(a, a, target, ones, mask)) > 0.04   # a squared residual carries the noise
