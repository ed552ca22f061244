"""Amortised refinement (beyond the paper): a learnt second look at every slot after the encoder.

The recurrent encoder places each object before it sees the ones found after it, and it never sees its
own render. The refiner ``g_r`` sees, per slot, the input image, what the composition of all slots
misses of it (``I - I_comp``), the slot's visible and full silhouettes, and the slot's latents, and
outputs a correction: a shift of the position, a turn of the yaw, a factor on the scale and a step of
the texture latent (the shape latent is left to the encoder). Its last layer starts at zero, so a
fresh refiner changes nothing. It reads colour alone, as the encoder does.

It is trained to move the encoder's slots to where the test-time pose search and colour fit put them
(``prismonet.model.refiner_fit``, targets from ``prismonet.model.distill_fit``: only the input RGB-D is
read), so one pass does at the cost of one encoder step per slot and one render what the search does
with hundreds of trial renders.
"""

from __future__ import annotations

import torch
from torch import nn

from prismonet.model.encoder import conv_trunk
from prismonet.render import SceneParams

IN_CHANNELS = 8
"""Image (3), image minus the composition (3), the slot's visible silhouette (1) and its full silhouette (1)."""
MAX_TURN = 0.6
"""The largest yaw correction in radians (about 34 degrees): ``tanh`` bounds it."""
MAX_LOG_SCALE = 0.4
"""The largest log-factor on the scale (a factor 0.67 to 1.49)."""


class SlotRefiner(nn.Module):
    """``(R, 8, H, W)`` slot views and ``(R, P)`` slot latents -> ``(R, 5 + D_tex)`` corrections."""

    def __init__(self, sh_dim: int, tex_dim: int, image_size: int, channels: tuple[int, ...] = (32, 32, 64, 64),
                 fc: tuple[int, ...] = (256, 256)) -> None:
        super().__init__()
        self.tex_dim = tex_dim
        self.trunk = conv_trunk(IN_CHANNELS, channels)
        side = image_size // 2 ** len(channels)
        self.vec_dim = sh_dim + tex_dim + 3 + 2 + 1
        dims = [channels[-1] * side * side + self.vec_dim, *fc]
        mlp: list[nn.Module] = []
        for a, b in zip(dims[:-1], dims[1:]):
            mlp += [nn.Linear(a, b), nn.ReLU(inplace=True)]
        mlp.append(nn.Linear(dims[-1], 5 + tex_dim))
        self.head = nn.Sequential(*mlp)
        self.head[-1].weight.data.zero_()  # a fresh refiner is the identity
        self.head[-1].bias.data.zero_()

    def forward(self, views: torch.Tensor, latents: torch.Tensor) -> torch.Tensor:
        h = self.trunk(views.contiguous(memory_format=torch.channels_last)).flatten(1)
        return self.head(torch.cat([h, latents], 1))


def slot_views(image: torch.Tensor, comp_image: torch.Tensor, instance: torch.Tensor, obj_mask: torch.Tensor) -> torch.Tensor:
    """``(B*N, 8, H, W)``: per slot, the image, the image minus the composition, the slot's visible
    silhouette (its id in ``instance (B, H, W)``) and its full silhouette (``obj_mask (B, N, H, W)``)."""
    B, N, H, W = obj_mask.shape
    ids = torch.arange(1, N + 1, device=instance.device)[None, :, None, None]
    visible = (instance[:, None] == ids).to(image.dtype)
    per_scene = torch.cat([image, image - comp_image], 1)[:, None].expand(B, N, 6, H, W)
    views = torch.cat([per_scene, visible[:, :, None], obj_mask[:, :, None].to(image.dtype)], 2)
    return views.reshape(B * N, IN_CHANNELS, H, W)


def slot_latents(params: SceneParams, pos_offset: torch.Tensor, pos_scale: torch.Tensor) -> torch.Tensor:
    """``(B*N, P)``: shape and texture latents, the position in the encoder's normalised units, the
    unit (cos, sin) of the yaw and the log scale."""
    cs = params.cos_sin / params.cos_sin.norm(dim=-1, keepdim=True).clamp_min(1e-6)
    pos = (params.position - pos_offset) / pos_scale
    v = torch.cat([params.z_sh, params.z_tex, pos, cs, params.scale.clamp_min(1e-3).log()[..., None]], -1)
    return v.reshape(-1, v.shape[-1])


def apply_correction(params: SceneParams, delta: torch.Tensor, pos_scale: torch.Tensor,
                     scale_range: tuple[float, float]) -> SceneParams:
    """``params`` moved by the refiner's raw output ``delta (B*N, 5 + D_tex)``: position + ``pos_scale``
    times the first three, yaw turned by ``MAX_TURN tanh``, scale times ``exp(MAX_LOG_SCALE tanh)``
    (kept in ``scale_range``), texture latent plus the rest. Inactive slots keep their latents."""
    B, N = params.scale.shape
    d = delta.reshape(B, N, -1)
    turn = MAX_TURN * torch.tanh(d[..., 3])
    c, s = torch.cos(turn), torch.sin(turn)
    cs = params.cos_sin
    cos_sin = torch.stack([cs[..., 0] * c - cs[..., 1] * s, cs[..., 0] * s + cs[..., 1] * c], -1)
    lo, hi = scale_range
    scale = (params.scale * torch.exp(MAX_LOG_SCALE * torch.tanh(d[..., 4]))).clamp(lo, hi)
    new = SceneParams(z_sh=params.z_sh, z_tex=params.z_tex + d[..., 5:], position=params.position + pos_scale * d[..., :3],
                      cos_sin=cos_sin, scale=scale, axis=params.axis, active=params.active)
    if params.active is not None:
        keep = ~params.active
        new.position = torch.where(keep[..., None], params.position, new.position)
        new.cos_sin = torch.where(keep[..., None], params.cos_sin, new.cos_sin)
        new.scale = torch.where(keep, params.scale, new.scale)
        new.z_tex = torch.where(keep[..., None], params.z_tex, new.z_tex)
    return new
