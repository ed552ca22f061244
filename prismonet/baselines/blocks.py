"""Building blocks that MONet and GENESIS share: a strided convolutional encoder with an MLP head, and
the spatial broadcast decoder (Watters et al. 2019) both papers use."""

from __future__ import annotations

import math

import torch
import torch.nn as nn
import torch.nn.functional as F


def conv_encoder(in_ch: int, channels: tuple[int, ...], image_size: int, out_dim: int) -> nn.Sequential:
    """3x3 stride-2 convolutions with ReLU, then an MLP of 256: ``(n, in_ch, S, S)`` -> ``(n, out_dim)``."""
    layers, c = [], in_ch
    for ch in channels:
        layers += [nn.Conv2d(c, ch, 3, stride=2, padding=1), nn.ReLU()]
        c = ch
    side = image_size // 2 ** len(channels)
    return nn.Sequential(*layers, nn.Flatten(), nn.Linear(c * side * side, 256), nn.ReLU(), nn.Linear(256, out_dim))


class BroadcastDecoder(nn.Module):
    """Latent ``(n, D)`` -> ``(n, out, S, S)``: the latent tiled over an ``(S + 8)``-square grid with x, y
    coordinates in [-1, 1], four unpadded 3x3 convolutions of ``channels`` (each takes 2 pixels off), a 1x1
    convolution to ``out``.

    The first convolution is computed without tiling: over a tiled latent an unpadded convolution gives
    the same value everywhere, ``(sum of its taps) @ z``, so only the coordinate channels are convolved
    (the same function and weights as ``net`` applied to the tiled input, a third of the FLOPs)."""

    def __init__(self, latent_dim: int, channels: int, out: int, image_size: int) -> None:
        super().__init__()
        C, S = channels, image_size + 8
        self.net = nn.Sequential(nn.Conv2d(latent_dim + 2, C, 3), nn.ReLU(), nn.Conv2d(C, C, 3), nn.ReLU(),
                                 nn.Conv2d(C, C, 3), nn.ReLU(), nn.Conv2d(C, C, 3), nn.ReLU(), nn.Conv2d(C, out, 1))
        ys, xs = torch.meshgrid(torch.linspace(-1, 1, S), torch.linspace(-1, 1, S), indexing="ij")
        self.register_buffer("coords", torch.stack([xs, ys])[None], persistent=False)

    def forward(self, z: torch.Tensor) -> torch.Tensor:
        first, D = self.net[0], z.shape[1]
        h = F.conv2d(self.coords, first.weight[:, D:], first.bias)  # (1, C, S - 2, S - 2)
        h = h + (z @ first.weight[:, :D].sum((2, 3)).t())[:, :, None, None]
        return self.net[1:](h)

    def tiled(self, z: torch.Tensor) -> torch.Tensor:
        """``forward`` computed as written, on the tiled latent (the reference the test checks against)."""
        S = self.coords.shape[-1]
        return self.net(torch.cat([z[:, :, None, None].expand(-1, -1, S, S), self.coords.expand(z.shape[0], -1, -1, -1)], 1))


def reparameterize(mu: torch.Tensor, sd: torch.Tensor, generator: torch.Generator | None, training: bool) -> torch.Tensor:
    """A sample ``mu + sd * noise`` while training (noise from ``generator`` when given), the mean otherwise."""
    if not training:
        return mu
    noise = torch.randn(mu.shape, generator=generator, dtype=mu.dtype) if generator is not None else torch.randn_like(mu)
    return mu + sd * noise


def mixture_nll(rgb: torch.Tensor, colors: torch.Tensor, log_masks: torch.Tensor, sigma) -> torch.Tensor:
    """``(B,)`` negative log likelihood, summed over pixels, of ``rgb (B, 3, H, W)`` under the spatial
    Gaussian mixture of ``colors (B, K, 3, H, W)`` weighted by ``exp(log_masks) (B, K, H, W)``, with
    standard deviation ``sigma`` (a number, or a tensor broadcasting to ``(1, K, 1, 1, 1)``)."""
    sigma = torch.as_tensor(sigma, dtype=rgb.dtype)
    log_px = (-0.5 * ((rgb[:, None] - colors) / sigma) ** 2 - torch.log(sigma) - 0.5 * math.log(2 * math.pi)).sum(2)
    return -torch.logsumexp(log_masks + log_px, dim=1).sum((1, 2))
