"""Slot Attention (Locatello et al., NeurIPS 2020), the object-discovery autoencoder, for 64x64 images.

Written from the paper (its Appendix E.1 architecture for CLEVR, scaled to 64x64 as PriSMONet's
comparison did): a CNN encoder with a soft position embedding, ``iters`` rounds of slot attention
(softmax over slots, weighted mean over inputs, GRU update and residual MLP), and a spatial broadcast
decoder per slot giving RGB and an alpha logit; the alphas are normalised over slots (softmax) and the
image is their mixture. The loss is the pixel MSE. Choices where the paper leaves room, for 64x64:
the decoder broadcasts to 8x8 and upsamples x8 by three stride-2 transposed convolutions (the paper's
128x128 CLEVR decoder broadcasts to 8x8 and upsamples x16); the encoder keeps the full resolution.

Shapes: B batch, K slots, N = H*W input positions, D slot size, C channels.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn as nn
import torch.nn.functional as F

from prismonet.baselines.output import SlotOutput


@dataclass(frozen=True)
class SlotAttentionConfig:
    num_slots: int = 4
    """Objects + background (the PriSMONet paper: number of objects + 1)."""
    iters: int = 3
    """Slot-attention rounds (the paper: 3)."""
    slot_dim: int = 64
    hidden: int = 64
    """Encoder and decoder channels (the paper: 64)."""
    image_size: int = 64
    broadcast: int = 8
    """Side of the decoder's spatial broadcast grid."""
    eps: float = 1e-8
    """Added to the attention before the weighted mean, as in the paper (no division by zero)."""

    def __post_init__(self) -> None:
        if self.num_slots < 1 or self.iters < 1 or self.slot_dim < 1 or self.hidden < 1:
            raise ValueError(f"slot attention: counts and sizes must be positive, got {self}")
        if self.image_size != self.broadcast * 8:
            raise ValueError(f"slot attention: image_size must be 8x broadcast ({self.broadcast * 8}), got {self.image_size}")


def position_grid(h: int, w: int) -> torch.Tensor:
    """``(h, w, 4)``: x, y, 1 - x, 1 - y in [0, 1] (the paper's position embedding input)."""
    ys, xs = torch.meshgrid(torch.linspace(0, 1, h), torch.linspace(0, 1, w), indexing="ij")
    return torch.stack([xs, ys, 1 - xs, 1 - ys], -1)


class SoftPositionEmbed(nn.Module):
    def __init__(self, channels: int, h: int, w: int) -> None:
        super().__init__()
        self.proj = nn.Linear(4, channels)
        self.register_buffer("grid", position_grid(h, w), persistent=False)

    def forward(self, x: torch.Tensor) -> torch.Tensor:  # (B, C, H, W)
        return x + self.proj(self.grid).permute(2, 0, 1)[None]


class SlotAttention(nn.Module):
    """Iterative attention of ``K`` slots over ``N`` inputs, slots competing (softmax over slots)."""

    def __init__(self, cfg: SlotAttentionConfig, in_dim: int) -> None:
        super().__init__()
        D = cfg.slot_dim
        self.cfg = cfg
        self.mu = nn.Parameter(torch.randn(1, 1, D) * D**-0.5)
        self.log_sigma = nn.Parameter(torch.zeros(1, 1, D))
        self.norm_in, self.norm_slots, self.norm_mlp = nn.LayerNorm(in_dim), nn.LayerNorm(D), nn.LayerNorm(D)
        self.q, self.k, self.v = nn.Linear(D, D, bias=False), nn.Linear(in_dim, D, bias=False), nn.Linear(in_dim, D, bias=False)
        self.gru = nn.GRUCell(D, D)
        self.mlp = nn.Sequential(nn.Linear(D, 128), nn.ReLU(), nn.Linear(128, D))

    def forward(self, inputs: torch.Tensor, generator: torch.Generator | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """``inputs (B, N, C)`` -> ``(slots (B, K, D), attention (B, K, N))`` of the last round."""
        B, _, _ = inputs.shape
        K, D = self.cfg.num_slots, self.cfg.slot_dim
        x = self.norm_in(inputs)
        k, v = self.k(x), self.v(x)  # (B, N, D)
        noise = torch.randn(B, K, D, generator=generator, device=inputs.device, dtype=inputs.dtype)
        slots = self.mu + self.log_sigma.exp() * noise
        for _ in range(self.cfg.iters):
            prev = slots
            q = self.q(self.norm_slots(slots))  # (B, K, D)
            attn = torch.softmax(torch.einsum("bkd,bnd->bkn", q, k) * D**-0.5, dim=1) + self.cfg.eps  # over slots
            updates = torch.einsum("bkn,bnd->bkd", attn / attn.sum(-1, keepdim=True), v)  # weighted mean over inputs
            slots = self.gru(updates.reshape(-1, D), prev.reshape(-1, D)).reshape(B, K, D)
            slots = slots + self.mlp(self.norm_mlp(slots))
        return slots, attn


class SlotAttentionAutoEncoder(nn.Module):
    def __init__(self, cfg: SlotAttentionConfig = SlotAttentionConfig()) -> None:
        super().__init__()
        self.cfg = cfg
        C, S = cfg.hidden, cfg.image_size
        self.encoder = nn.Sequential(*[m for i in range(4) for m in (nn.Conv2d(3 if i == 0 else C, C, 5, padding=2), nn.ReLU())])
        self.enc_pos = SoftPositionEmbed(C, S, S)
        self.enc_mlp = nn.Sequential(nn.LayerNorm(C), nn.Linear(C, C), nn.ReLU(), nn.Linear(C, C))
        self.attention = SlotAttention(cfg, C)
        self.dec_pos = SoftPositionEmbed(cfg.slot_dim, cfg.broadcast, cfg.broadcast)
        up = [nn.ConvTranspose2d(cfg.slot_dim if i == 0 else C, C, 5, stride=2, padding=2, output_padding=1) for i in range(3)]
        self.decoder = nn.Sequential(*[m for u in up for m in (u, nn.ReLU())], nn.Conv2d(C, C, 5, padding=2), nn.ReLU(), nn.Conv2d(C, 4, 3, padding=1))

    def forward(self, rgb: torch.Tensor, generator: torch.Generator | None = None) -> SlotOutput:
        """``rgb (B, 3, H, W)`` in [0, 1] (mapped to [-1, 1] inside, as the paper)."""
        B = rgb.shape[0]
        K, G = self.cfg.num_slots, self.cfg.broadcast
        h = self.enc_pos(self.encoder(rgb * 2 - 1))  # (B, C, H, W)
        h = self.enc_mlp(h.flatten(2).transpose(1, 2))  # (B, N, C)
        slots, _ = self.attention(h, generator)
        grid = slots.reshape(B * K, -1, 1, 1).expand(-1, -1, G, G)  # spatial broadcast
        out = self.decoder(self.dec_pos(grid)).reshape(B, K, 4, *rgb.shape[-2:])
        colors = (out[:, :, :3] + 1) / 2  # back to [0, 1]
        masks = torch.softmax(out[:, :, 3], dim=1)
        image = (masks[:, :, None] * colors).sum(1)
        return SlotOutput(image, masks, colors, slots)

    def loss(self, rgb: torch.Tensor, generator: torch.Generator | None = None) -> torch.Tensor:
        """The paper's objective: pixel MSE of the reconstruction (images in [-1, 1], as it trains)."""
        return F.mse_loss(self(rgb, generator).image * 2 - 1, rgb * 2 - 1)
