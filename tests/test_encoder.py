"""The conv encoders: each block pools before its ReLU, which must give exactly the outputs and gradients of the
textbook order (conv, ReLU, pool) with the same weights."""

import torch
import torch.nn.functional as F

from prismonet.model.encoder import ConvEncoder, conv_trunk


def _relu_then_pool(trunk: torch.nn.Sequential, x: torch.Tensor) -> torch.Tensor:
    """The trunk's convolutions applied in the order conv, ReLU, 2x2 max-pool."""
    for conv in [m for m in trunk if isinstance(m, torch.nn.Conv2d)]:
        x = F.max_pool2d(F.relu(conv(x)), 2)
    return x


def test_trunk_keeps_weight_names():
    # the shipped checkpoints name the convolutions trunk.0, trunk.3, ...: the order change must not move them
    trunk = conv_trunk(7, (32, 32, 64, 64))
    names = [k for k in trunk.state_dict()]
    assert [type(m).__name__ for m in trunk[:3]] == ["Conv2d", "MaxPool2d", "ReLU"]  # the cheaper order
    assert names == [f"{i}.{p}" for i in (0, 3, 6, 9) for p in ("weight", "bias")]


def test_pool_before_relu_is_exact_in_float64():
    torch.manual_seed(0)
    enc = ConvEncoder(5, (8, 8, 16), (32,), 16, 4).double()
    x = torch.randn(3, 5, 16, 16, dtype=torch.float64)
    x[0, :, :4, :4] = -5.0  # a region where whole windows are negative after the first conv (no gradient either way)
    ref_feat = _relu_then_pool(enc.trunk, x)
    feat = enc.trunk(x)
    assert torch.equal(feat, ref_feat)
    # gradients with respect to every weight and the input, for a loss that reads every feature
    xa, xb = x.clone().requires_grad_(), x.clone().requires_grad_()
    w = torch.randn_like(feat)
    (enc.trunk(xa) * w).sum().backward()
    grads = [p.grad.clone() for p in enc.parameters() if p.grad is not None]
    enc.zero_grad()
    (_relu_then_pool(enc.trunk, xb) * w).sum().backward()
    ref_grads = [p.grad.clone() for p in enc.parameters() if p.grad is not None]
    assert len(grads) == len(ref_grads) == 6
    for g, r in zip(grads, ref_grads):
        assert torch.equal(g, r)
    assert torch.equal(xa.grad, xb.grad)
    assert (feat == 0).any() and (feat > 0).any()  # the ReLU did something


def test_gradcheck_through_the_encoder():
    torch.manual_seed(1)
    enc = ConvEncoder(2, (3, 4), (5,), 8, 2).double()
    x = torch.randn(2, 2, 8, 8, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda t: enc(t), (x,))
