"""The losses' Gaussian blur as matrix products: the same function as kornia's replicate-border blur."""

import kornia
import pytest
import torch

from prismonet.model.blur import blur_matrix, gaussian_blur
from prismonet.model.losses import LossConfig, blur


@pytest.mark.parametrize("sigma,taps", [(0.5, 7), (1.3, 9), (16 / 3, 17), (2.0, 3)])
@pytest.mark.parametrize("shape", [(2, 1, 16, 16), (2, 3, 12, 20), (1, 2, 40, 9)])
def test_equals_kornia_replicate_blur(sigma, taps, shape):
    x = torch.rand(shape, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    want = kornia.filters.gaussian_blur2d(x, (taps, taps), (sigma, sigma), border_type="replicate")
    assert torch.allclose(gaussian_blur(x, sigma, taps), want, atol=1e-12)


def test_hand_computed_rows():
    """Three taps of sigma 1: weights (e, 1, e) / (1 + 2e) with e = exp(-1/2); the border row folds its outer tap
    onto the edge pixel."""
    e = torch.exp(torch.tensor(-0.5, dtype=torch.float64))
    w = torch.stack([e, torch.ones_like(e), e]) / (1 + 2 * e)
    m = blur_matrix(4, 1.0, 3, torch.float64)
    assert torch.allclose(m[1], torch.stack([w[0], w[1], w[2], torch.zeros_like(e)]))
    assert torch.allclose(m[0], torch.stack([w[0] + w[1], w[2], torch.zeros_like(e), torch.zeros_like(e)]))
    assert torch.allclose(m.sum(1), torch.ones(4, dtype=torch.float64))  # a constant image stays constant


def test_gradcheck_and_linearity():
    x = torch.rand(1, 2, 7, 5, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda t: gaussian_blur(t, 0.8, 5), (x,))
    a, b = torch.rand(2, 3, 8, 8), torch.rand(2, 3, 8, 8)
    cfg = LossConfig()
    assert torch.allclose(blur(a, cfg, 0) - blur(b, cfg, 0), blur(a - b, cfg, 0), atol=1e-6)


def test_bad_arguments_are_one_line_errors():
    for n, sigma, taps in ((0, 1.0, 3), (4, 0.0, 3), (4, 1.0, 4)):
        with pytest.raises(ValueError, match="blur: "):
            blur_matrix(n, sigma, taps)


def test_one_sigma_per_image_equals_kornia():
    """The input augmentation's blur: a sigma per image, as kornia's per-sample ``sigma (B, 2)``."""
    g = torch.Generator().manual_seed(1)
    x = torch.rand(3, 2, 10, 14, generator=g, dtype=torch.float64)
    sigma = torch.tensor([1e-3, 0.4, 1.0], dtype=torch.float64)
    want = kornia.filters.gaussian_blur2d(x, (7, 7), torch.stack([sigma, sigma], 1), border_type="replicate")
    assert torch.allclose(gaussian_blur(x, sigma, 7), want, atol=1e-12)
    assert torch.allclose(gaussian_blur(x, sigma, 7)[1:2], gaussian_blur(x[1:2], 0.4, 7), atol=1e-12)
    with pytest.raises(ValueError, match="one sigma per image"):
        gaussian_blur(x, sigma[:2], 7)
