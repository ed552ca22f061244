"""Starting a model from one with other latent sizes or outputs (``init_transfer``)."""

import torch

from prismonet.model.config import ModelConfig
from prismonet.model.io import HEAD, transfer_weights
from prismonet.model.prismonet import PriSMONet
from prismonet.shapes.decoder import SDFDecoder, SDFDecoderConfig
from prismonet.shapes.prior import ShapePrior


def _prior(dim: int) -> ShapePrior:
    torch.manual_seed(dim)
    return ShapePrior(SDFDecoder(SDFDecoderConfig(latent_dim=dim)), torch.zeros(2, dim), ["a", "b"], [0, 0], [0, 1])


def test_transfer_copies_what_fits_and_the_pose_rows():
    torch.manual_seed(0)
    src = PriSMONet(ModelConfig(), prior=_prior(8))  # D_sh 8, D_tex 7: out 21
    torch.manual_seed(1)
    dst = PriSMONet(ModelConfig(tex_dim=15, full_rotation=True), prior=_prior(16))  # 16 + 15 + 6 + 3 = 40
    before = {k: v.clone() for k, v in dst.state_dict().items()}
    fresh = transfer_weights(dst, src)
    s, d = src.state_dict(), dst.state_dict()
    for name in ("encoder.trunk.0.weight", "encoder.head.0.weight", "bg_encoder.head.2.bias", "texture.layers.1.weight"):
        assert torch.equal(d[name], s[name]), name
    # the texture field's latent input has another size: fresh
    assert torch.equal(d["texture.layers.0.z.weight"], before["texture.layers.0.z.weight"])
    assert "texture.layers.0.z.weight" in fresh
    w_src, w_dst, b_dst = s[f"{HEAD}.weight"], d[f"{HEAD}.weight"], d[f"{HEAD}.bias"]
    assert w_dst.shape == (40, 256) and w_src.shape == (21, 256)
    assert torch.equal(w_dst[31:37], w_src[15:21])  # position, cos/sin, scale
    assert torch.equal(b_dst[31:37], s[f"{HEAD}.bias"][15:21])
    assert torch.equal(w_dst[:31], before[f"{HEAD}.weight"][:31])  # latents: fresh
    assert torch.equal(w_dst[37:], before[f"{HEAD}.weight"][37:])  # the axis: the source has none
    assert set(fresh) == {"texture.layers.0.z.weight", f"{HEAD} (z_sh rows)", f"{HEAD} (z_tex rows)", f"{HEAD} (axis rows)"}


def test_transfer_keeps_the_latents_of_the_same_prior():
    prior = _prior(8)
    torch.manual_seed(0)
    src = PriSMONet(ModelConfig(), prior=prior)
    torch.manual_seed(1)
    dst = PriSMONet(ModelConfig(full_rotation=True), prior=prior)
    before = dst.state_dict()[f"{HEAD}.weight"].clone()
    assert transfer_weights(dst, src) == [f"{HEAD} (axis rows)"]
    w = dst.state_dict()[f"{HEAD}.weight"]
    assert torch.equal(w[:21], src.state_dict()[f"{HEAD}.weight"])
    assert torch.equal(w[21:], before[21:])


def test_transfer_between_equal_layouts_is_a_full_copy():
    torch.manual_seed(0)
    src = PriSMONet(ModelConfig(full_rotation=True), prior=_prior(8))
    torch.manual_seed(1)
    dst = PriSMONet(ModelConfig(full_rotation=True), prior=_prior(8))
    assert transfer_weights(dst, src) == []
    for k, v in src.state_dict().items():
        assert torch.equal(dst.state_dict()[k], v), k


def test_bad_transfer_and_inside_test_settings_say_what_is_wrong():
    import pytest

    from prismonet.model.trainer import TrainConfig
    from prismonet.shapes.sdf_samples import SamplingConfig

    with pytest.raises(ValueError, match="init_transfer needs init_from"):
        TrainConfig(init_transfer=True)
    with pytest.raises(ValueError, match="sampling.inside: expected one of"):
        SamplingConfig(inside="parity")
