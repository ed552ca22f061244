"""The object encoder g_o and the background encoder: conv blocks (3x3, stride 1, ReLU, 2x2
max-pool), then fully connected layers. Run in channels-last memory format (faster on CPU).

Each block pools before its ReLU: ``relu(maxpool(x)) == maxpool(relu(x))`` exactly (ReLU is monotone), and the
gradients are equal too (a window whose maximum is at most 0 passes no gradient either way), but the ReLU and its
backward then touch a quarter of the elements. The modules' indices (and so the weights' names) are unchanged:
conv, pool, ReLU. BENCHMARKS.md, "Session 73"."""

from __future__ import annotations

import torch
from torch import nn


def conv_trunk(in_ch: int, channels: tuple[int, ...]) -> nn.Sequential:
    layers: list[nn.Module] = []
    for c in channels:
        layers += [nn.Conv2d(in_ch, c, 3, 1, 1), nn.MaxPool2d(2), nn.ReLU(inplace=True)]  # pool first: module docstring
        in_ch = c
    return nn.Sequential(*layers)


class ConvEncoder(nn.Module):
    """``(B, C, H, W) -> (B, out_dim)``."""

    def __init__(self, in_ch: int, channels: tuple[int, ...], fc: tuple[int, ...], image_size: int, out_dim: int) -> None:
        super().__init__()
        self.trunk = conv_trunk(in_ch, channels)
        side = image_size // 2 ** len(channels)
        dims = [channels[-1] * side * side, *fc]
        mlp: list[nn.Module] = []
        for a, b in zip(dims[:-1], dims[1:]):
            mlp += [nn.Linear(a, b), nn.ReLU(inplace=True)]
        mlp.append(nn.Linear(dims[-1], out_dim))
        self.head = nn.Sequential(*mlp)
        self.head[-1].weight.data.mul_(0.1)  # start near the offsets: small initial latents and poses
        self.head[-1].bias.data.zero_()

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        h = self.trunk(x.contiguous(memory_format=torch.channels_last))
        return self.head(h.flatten(1))
