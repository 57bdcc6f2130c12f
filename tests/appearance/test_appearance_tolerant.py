"""appearance.tolerant: the blurred residual, under which a highlight a few pixels off costs little."""

import torch

from saft.appearance.fit import masked_linearised_srgb_mse
from saft.appearance.tolerant import blur_image, blurred_linearised_mse


def test_blur_keeps_the_sum_inside():
    img = torch.zeros(40, 40, 3)
    img[20, 20] = 1.0
    out = blur_image(img, 2.0)
    assert abs(float(out.sum()) - 3.0) < 1e-4 and float(out.max()) < 0.1


def test_a_misplaced_spot_costs_less_blurred_than_a_missing_one():
    target = torch.full((40, 40, 3), 0.1)
    target[18:21, 18:21] = 0.8
    shifted = torch.full((40, 40, 3), 0.1)
    shifted[19:22, 20:23] = 0.8
    flat = torch.full((40, 40, 3), 0.1)
    mask, slope = torch.ones(40, 40), torch.ones(40, 40, 3)
    sharp = [float(masked_linearised_srgb_mse(x, target, slope, mask)) for x in (shifted, flat)]
    blurred = [float(blurred_linearised_mse(x, target, slope, mask, 2.0)) for x in (shifted, flat)]
    assert sharp[0] > 0.5 * sharp[1]            # per pixel: the shifted spot is nearly as bad as none
    assert blurred[0] < 0.5 * blurred[1]        # blurred: it is much better than none
