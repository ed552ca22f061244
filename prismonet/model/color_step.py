"""A learnt colour step (beyond the paper): the test-time colour fit, amortised into one pass.

The test-time colour fit (``prismonet.model.color_fit``) holds every object's shape, pose and scale and runs 50
Adam steps on the texture latents against the input image; on the shipped models' own geometry it adds about
0.5-0.7 dB of PSNR, at the cost of 51 texture-field evaluations. The colour step ``g_c`` does it in one: per slot it
sees what the refiner sees (the image, what the composition misses of it, the slot's visible and full silhouettes,
through the same glimpse) and the slot's latents, and outputs a step of the texture latent. The geometry is not
touched, so the scene is not ray-cast again: the texture field is evaluated once more at the hits the last render
already found (``PriSMONet.recolor``, ``shade_objects``), and masks, depth and every detection measure stay exactly as they were.

It is trained photometrically (``prismonet.model.color_step_fit``): the rest of the model frozen, on training images
alone (no mask, no pose, no depth), the loss is the colour error of the recoloured composite, the quantity PSNR
measures. Its last layer starts at zero, so a fresh step changes nothing. It runs at inference only (``eval()``).
"""

from __future__ import annotations

import torch
from torch import nn

from prismonet.model.encoder import conv_trunk


class ColorStep(nn.Module):
    """``(R, C, H, W)`` slot views and ``(R, P)`` slot latents -> ``(R, D_tex)`` steps of the texture latents."""

    def __init__(self, in_channels: int, vec_dim: int, tex_dim: int, image_size: int,
                 channels: tuple[int, ...] = (32, 32, 64, 64), fc: tuple[int, ...] = (256,)) -> None:
        super().__init__()
        self.trunk = conv_trunk(in_channels, channels)
        side = image_size // 2 ** len(channels)
        dims = [channels[-1] * side * side + vec_dim, *fc]
        mlp: list[nn.Module] = []
        for a, b in zip(dims[:-1], dims[1:]):
            mlp += [nn.Linear(a, b), nn.ReLU(inplace=True)]
        mlp.append(nn.Linear(dims[-1], tex_dim))
        self.head = nn.Sequential(*mlp)
        self.head[-1].weight.data.zero_()  # a fresh step is the identity
        self.head[-1].bias.data.zero_()

    def forward(self, views: torch.Tensor, latents: torch.Tensor) -> torch.Tensor:
        h = self.trunk(views.contiguous(memory_format=torch.channels_last)).flatten(1)
        return self.head(torch.cat([h, latents], 1))
