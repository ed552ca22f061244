"""GENESIS (Engelcke et al., ICLR 2020), the generative scene model with mask and component latents,
for 64x64 images.

Written from the paper: the image is a spatial Gaussian mixture of ``K`` components. *Mask latents*
``z^m_1..K`` are inferred in sequence: a CNN encodes the image once, and an LSTM unrolled over ``K``
steps (fed the image code and the previous mask latent) gives each posterior; a spatial broadcast
decoder turns each ``z^m_k`` into a logit, and the masks follow by stick-breaking (``pi_k`` takes
``sigmoid(logit_k)`` of the scope left, the last takes the rest). *Component latents* ``z^c_k`` are
inferred from the image and ``log pi_k`` by a CNN, and decoded to RGB by a spatial broadcast decoder.
The priors are autoregressive for the mask latents (an LSTM over ``z^m_<k``) and conditional for the
component latents (an MLP of ``z^m_k``). The objective is the paper's GECO: minimise the KL terms
subject to the mixture's negative log likelihood (per pixel and channel, fixed standard deviation
``sigma_x`` = 0.7) staying under ``geco_goal``, with a Lagrange multiplier ``lambda`` (a buffer, so it
is checkpointed and resumes) that grows while the reconstruction is worse than the goal.

Choices where the paper leaves room, stated: encoders are 4 stride-2 3x3 convolutions (32, 32, 64, 64)
and an MLP of 256 as in MONet; the LSTMs have 256 units; latents are 64-dimensional; decoders broadcast
to 72x72 with coordinates and apply four unpadded 3x3 convolutions of 32 channels; ``lambda`` starts at
1, is multiplied each step by ``exp(geco_lr * (C_ema - geco_goal))`` with ``C_ema`` a 0.99 running
mean of the per-value NLL, and is kept in ``[1, 1e4]``. The first step's running mean is its own value.

Shapes: B batch, K components, H x W image.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn as nn
import torch.nn.functional as F

from prismonet.baselines.blocks import BroadcastDecoder, conv_encoder, mixture_nll, reparameterize
from prismonet.baselines.output import SlotOutput


@dataclass(frozen=True)
class GenesisConfig:
    num_slots: int = 4
    """K components: objects + background (the PriSMONet paper: number of objects + 1)."""
    latent_dim: int = 64
    image_size: int = 64
    enc_channels: tuple[int, ...] = (32, 32, 64, 64)
    dec_channels: int = 32
    lstm: int = 256
    sigma_x: float = 0.7
    """Standard deviation of every component's Gaussian (the paper: 0.7)."""
    geco_goal: float = 0.5655
    """Reconstruction goal: NLL per pixel and channel (a perfect fit at sigma_x = 0.7 gives 0.5622)."""
    geco_lr: float = 1.0
    geco_ema: float = 0.99

    def __post_init__(self) -> None:
        if self.num_slots < 2 or self.latent_dim < 1 or self.lstm < 1 or self.dec_channels < 1:
            raise ValueError(f"genesis: need at least 2 slots and positive sizes, got {self}")
        if self.image_size % (2 ** len(self.enc_channels)):
            raise ValueError(f"genesis: image_size {self.image_size} must be divisible by 2^len(enc_channels)")
        if not (self.sigma_x > 0 and self.geco_lr >= 0 and 0 <= self.geco_ema < 1):
            raise ValueError(f"genesis: sigma_x must be positive, geco_lr >= 0 and geco_ema in [0, 1), got {self}")


def _gaussian(params: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    mu, raw = params.chunk(2, dim=-1)
    return mu, F.softplus(raw) + 1e-4


def _kl(mu_q, sd_q, mu_p, sd_p) -> torch.Tensor:
    """KL(N(mu_q, sd_q) || N(mu_p, sd_p)) summed over the last axis."""
    return (torch.log(sd_p / sd_q) + (sd_q**2 + (mu_q - mu_p) ** 2) / (2 * sd_p**2) - 0.5).sum(-1)


def stick_breaking(logits: torch.Tensor) -> torch.Tensor:
    """``(B, K-1, H, W)`` logits -> ``(B, K, H, W)`` log masks that sum to 1 over K."""
    log_scope, logs = torch.zeros_like(logits[:, :1]), []
    for k in range(logits.shape[1]):
        logs.append(log_scope + F.logsigmoid(logits[:, k : k + 1]))
        log_scope = log_scope + F.logsigmoid(-logits[:, k : k + 1])
    return torch.cat(logs + [log_scope], 1)


class Genesis(nn.Module):
    def __init__(self, cfg: GenesisConfig = GenesisConfig()) -> None:
        super().__init__()
        self.cfg = cfg
        D, L = cfg.latent_dim, cfg.lstm
        self.image_encoder = conv_encoder(3, cfg.enc_channels, cfg.image_size, L)
        self.mask_lstm = nn.LSTMCell(L + D, L)
        self.mask_head = nn.Linear(L, 2 * D)
        self.mask_decoder = BroadcastDecoder(D, cfg.dec_channels, 1, cfg.image_size)
        self.comp_encoder = conv_encoder(4, cfg.enc_channels, cfg.image_size, 2 * D)
        self.comp_decoder = BroadcastDecoder(D, cfg.dec_channels, 3, cfg.image_size)
        self.prior_lstm = nn.LSTMCell(D, L)
        self.prior_head = nn.Linear(L, 2 * D)
        self.comp_prior = nn.Sequential(nn.Linear(D, 256), nn.ReLU(), nn.Linear(256, 2 * D))
        self.register_buffer("geco_lambda", torch.ones(()))
        self.register_buffer("geco_err", torch.full((), float("nan")))

    def _mask_latents(self, rgb: torch.Tensor, generator: torch.Generator | None):
        B, K, D = rgb.shape[0], self.cfg.num_slots, self.cfg.latent_dim
        h = self.image_encoder(rgb)
        state = (torch.zeros(B, self.cfg.lstm), torch.zeros(B, self.cfg.lstm))
        z_prev, zs, mus, sds = torch.zeros(B, D), [], [], []
        for _ in range(K - 1):
            state = self.mask_lstm(torch.cat([h, z_prev], 1), state)
            mu, sd = _gaussian(self.mask_head(state[0]))
            z_prev = reparameterize(mu, sd, generator, self.training)
            zs.append(z_prev)
            mus.append(mu)
            sds.append(sd)
        return torch.stack(zs, 1), torch.stack(mus, 1), torch.stack(sds, 1)

    def _decode(self, rgb: torch.Tensor, generator: torch.Generator | None):
        B, K, H, W = rgb.shape[0], self.cfg.num_slots, *rgb.shape[-2:]
        zm, mu_m, sd_m = self._mask_latents(rgb, generator)  # (B, K-1, D)
        logits = self.mask_decoder(zm.reshape(B * (K - 1), -1)).reshape(B, K - 1, H, W)
        log_pi = stick_breaking(logits)
        mu_c, sd_c = _gaussian(self.comp_encoder(torch.cat([rgb.repeat_interleave(K, 0), log_pi.reshape(B * K, 1, H, W)], 1)))
        zc = reparameterize(mu_c, sd_c, generator, self.training)
        colors = torch.sigmoid(self.comp_decoder(zc)).reshape(B, K, 3, H, W)
        return log_pi, colors, (zm, mu_m, sd_m), (zc.reshape(B, K, -1), mu_c.reshape(B, K, -1), sd_c.reshape(B, K, -1))

    def forward(self, rgb: torch.Tensor, generator: torch.Generator | None = None) -> SlotOutput:
        """``rgb (B, 3, H, W)`` in [0, 1]: the mixture's mean image, the masks and each component's RGB."""
        log_pi, colors, _, (zc, _, _) = self._decode(rgb, generator)
        masks = log_pi.exp()
        return SlotOutput((masks[:, :, None] * colors).sum(1), masks, colors, zc)

    def kl_terms(self, zm, mu_m, sd_m, zc, mu_c, sd_c) -> torch.Tensor:
        """``(B,)`` KL of the posteriors from the autoregressive mask prior and the conditional component prior."""
        B, K1, D = zm.shape
        state = (torch.zeros(B, self.cfg.lstm), torch.zeros(B, self.cfg.lstm))
        kl = torch.zeros(B)
        for k in range(K1):
            mu_p, sd_p = (torch.zeros(B, D), torch.ones(B, D)) if k == 0 else _gaussian(self.prior_head(state[0]))
            kl = kl + _kl(mu_m[:, k], sd_m[:, k], mu_p, sd_p)
            state = self.prior_lstm(zm[:, k], state)
        # the last component's mask latent is the scope's rest: its component prior is conditioned on zero
        zm_all = torch.cat([zm, torch.zeros(B, 1, D)], 1)
        mu_p, sd_p = _gaussian(self.comp_prior(zm_all))
        return kl + _kl(mu_c, sd_c, mu_p, sd_p).sum(1)

    def loss(self, rgb: torch.Tensor, generator: torch.Generator | None = None) -> torch.Tensor:
        """GECO: mean KL + lambda x the summed mixture NLL; lambda is updated from this batch's NLL."""
        log_pi, colors, m, c = self._decode(rgb, generator)
        nll = mixture_nll(rgb, colors, log_pi, self.cfg.sigma_x)  # (B,)
        per_value = nll.mean().detach() / (3 * rgb.shape[-2] * rgb.shape[-1])
        if self.training:
            with torch.no_grad():
                ema = self.cfg.geco_ema
                err = per_value if torch.isnan(self.geco_err) else ema * self.geco_err + (1 - ema) * per_value
                self.geco_err.copy_(err)
                self.geco_lambda.mul_(torch.exp(self.cfg.geco_lr * (err - self.cfg.geco_goal))).clamp_(1.0, 1e4)
        return (self.kl_terms(*m, *c) + self.geco_lambda * nll).mean()
