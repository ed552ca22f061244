"""Starting a model from one with other latent sizes or outputs (``init_transfer``), or from a narrower one
(``init_widen``)."""

from dataclasses import replace

import pytest
import torch

from prismonet.model.config import ModelConfig
from prismonet.model.io import HEAD, CheckpointError, transfer_weights, widen_weights
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

    for flag in ("init_transfer", "init_widen", "init_keep_positions"):
        with pytest.raises(ValueError, match="init_keep_positions need init_from"):
            TrainConfig(**{flag: True})
    with pytest.raises(ValueError, match="exclude each other"):
        TrainConfig(init_from="shipped", init_transfer=True, init_widen=True)
    with pytest.raises(ValueError, match="sampling.inside: expected one of"):
        SamplingConfig(inside="parity")


def test_a_widened_model_starts_as_the_same_function_and_its_new_units_train():
    """Wider encoders (every conv block, the fully connected layers, the background encoder) from a narrower
    model: the same encoder outputs in float64 (to rounding: the new units add zeros, in another summation order),
and every new unit gets a
    gradient within two steps."""
    import pytest

    prior = _prior(8)
    torch.manual_seed(0)
    src = PriSMONet(ModelConfig(channels=(8, 8, 16, 16), fc=(32, 32), bg_channels=(4, 4, 8, 8)), prior=prior).double()
    torch.manual_seed(1)
    wide = PriSMONet(ModelConfig(channels=(12, 8, 24, 32), fc=(48, 32), bg_channels=(8, 4, 8, 8)), prior=prior).double()
    grown = widen_weights(wide, src)
    assert "encoder.trunk.0.weight" in grown and "encoder.head.0.weight" in grown and "texture.layers.1.weight" not in grown
    x = torch.rand(2, 7, 64, 64, dtype=torch.float64)
    assert torch.allclose(wide.encoder(x), src.encoder(x), rtol=0, atol=1e-14)
    assert torch.allclose(wide.bg_encoder(x[:, :3]), src.bg_encoder(x[:, :3]), rtol=0, atol=1e-14)
    # the zero columns and then the new rows receive gradients: nothing stays frozen at its start
    opt = torch.optim.SGD(wide.encoder.parameters(), lr=0.1)
    for _ in range(2):
        opt.zero_grad()
        wide.encoder(x).pow(2).sum().backward()
        opt.step()
    w = wide.encoder.trunk[0].weight
    assert w.grad[8:].abs().sum() > 0  # new output channels of the first block
    assert wide.encoder.trunk[3].weight.grad[:, 8:].abs().sum() > 0  # the next block's columns that read them
    # a narrower target, or one with other tensors, is refused with the name of the tensor
    with pytest.raises(CheckpointError, match="smaller than the source"):
        widen_weights(src, wide)
    with pytest.raises(CheckpointError, match="differ in more than widths"):
        widen_weights(PriSMONet(ModelConfig(channels=(8, 8, 16), fc=(32, 32), bg_channels=(4, 4, 8, 8)), prior=prior), src)


@pytest.mark.parametrize("frame", ["world", "camera"])
def test_new_position_units_start_at_the_same_positions(frame):
    from prismonet.geometry.camera import intrinsics_matrix, look_at
    from prismonet.model.io import remap_position_outputs

    torch.manual_seed(0)
    src = PriSMONet(ModelConfig(num_slots=3, pose_frame=frame)).eval()
    with torch.no_grad():  # a head whose position outputs are not near zero, as a trained one
        src.state_dict()[f"{HEAD}.bias"].normal_(0.0, 1.0)
    dst = PriSMONet(replace(src.cfg, position_offset=(0.3, -0.2, 0.8), position_scale=(2.0, 1.0, 1.2))).eval()
    dst.load_state_dict(src.state_dict())
    rows = remap_position_outputs(dst, src.cfg)
    first = src.sh_dim + src.cfg.tex_dim
    assert rows == ([first + 2] if frame == "camera" else [first, first + 1, first + 2])  # the camera frame: the height
    B = 4
    K = intrinsics_matrix(80.0, 80.0, 31.5, 31.5)[None].expand(B, 3, 3)
    T = look_at(torch.tensor([0.0, -10.0, 3.0]), torch.zeros(3))[None].expand(B, 4, 4)
    x = torch.rand(B, src.encoder.trunk[0].in_channels, 64, 64)
    with torch.no_grad():
        a = src.decode_latent(src.encoder(x), K, T, torch.zeros(B))
        b = dst.decode_latent(dst.encoder(x), K, T, torch.zeros(B))
    torch.testing.assert_close(b.position, a.position, atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(b.scale, a.scale)
    assert remap_position_outputs(dst, dst.cfg) == []  # the same units: nothing to do
    with pytest.raises(ValueError, match="refiner"):
        remap_position_outputs(PriSMONet(replace(dst.cfg, refine_passes=1)), src.cfg)
