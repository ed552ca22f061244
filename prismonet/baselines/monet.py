"""MONet (Burgess et al. 2019), the Multi-Object Network, for 64x64 images.

Written from the paper (its Appendix B): a recurrent attention network (a U-Net) splits the image
into ``K`` masks by stick-breaking over a *scope*: step ``k`` sees the image and the log scope left
by the steps before, predicts ``alpha_k``, takes ``m_k = s_{k-1} alpha_k`` and leaves
``s_k = s_{k-1} (1 - alpha_k)``; the last step takes what is left. A component VAE encodes the image
with each log mask into a 16-dimensional latent and decodes it, by a spatial broadcast decoder, into
an RGB mean and a mask logit. The loss is the negative log likelihood of the image under the mixture
of the components' Gaussians weighted by the attention masks (standard deviation 0.09 for the first,
background, component and 0.11 for the others), plus ``beta`` x the latents' KL divergence to
N(0, I), plus ``gamma`` x the KL divergence of the decoded masks (softmax over components) from the
attention masks. Choices where the paper leaves room: the U-Net has ``blocks`` levels of 3x3
convolution, instance norm and ReLU, halving by nearest-neighbour down-sampling and doubling back with
skip connections, and a 3-layer MLP at the bottom (the paper: 5 blocks for 64x64, MLP 128-128);
the log likelihood is summed over pixels and averaged over the batch, as the paper's objective.

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
class MONetConfig:
    num_slots: int = 4
    """K components: objects + background (the PriSMONet paper: number of objects + 1)."""
    latent_dim: int = 16
    """Component VAE latent size (the paper: 16)."""
    image_size: int = 64
    blocks: int = 5
    """U-Net levels (the paper: 5 for 64x64 images)."""
    unet_channels: int = 32
    vae_channels: tuple[int, ...] = (32, 32, 64, 64)
    """Component encoder: 3x3 stride-2 convolutions (the paper: 32, 32, 64, 64), then an MLP of 256."""
    decoder_channels: int = 32
    """Spatial broadcast decoder: 4 unpadded 3x3 convolutions of this many channels (the paper: 32)."""
    beta: float = 0.5
    """Weight of the latents' KL term (the paper: 0.5)."""
    gamma: float = 0.5
    """Weight of the mask KL term (the paper: 0.5 for CLEVR-like scenes)."""
    sigma_bg: float = 0.09
    sigma_fg: float = 0.11

    def __post_init__(self) -> None:
        if self.num_slots < 2 or self.latent_dim < 1 or self.blocks < 1 or self.unet_channels < 1:
            raise ValueError(f"monet: need at least 2 slots and positive sizes, got {self}")
        if self.image_size % (2 ** (self.blocks - 1)) or self.image_size % (2 ** len(self.vae_channels)):
            raise ValueError(f"monet: image_size {self.image_size} must be divisible by 2^(blocks - 1) and 2^len(vae_channels)")
        if not (self.sigma_bg > 0 and self.sigma_fg > 0 and self.beta >= 0 and self.gamma >= 0):
            raise ValueError(f"monet: sigmas must be positive and weights non-negative, got {self}")


class AttentionUNet(nn.Module):
    """``(image, log scope)`` -> ``alpha`` logits ``(B, 1, H, W)``."""

    def __init__(self, cfg: MONetConfig) -> None:
        super().__init__()
        C, L = cfg.unet_channels, cfg.blocks
        block = lambda cin, cout: nn.Sequential(nn.Conv2d(cin, cout, 3, padding=1, bias=False), nn.InstanceNorm2d(cout, affine=True), nn.ReLU())
        self.down = nn.ModuleList([block(4 if i == 0 else C, C) for i in range(L)])
        self.up = nn.ModuleList([block(2 * C, C) for _ in range(L)])
        side = cfg.image_size // 2 ** (L - 1)
        self.side = side
        self.mlp = nn.Sequential(nn.Flatten(), nn.Linear(C * side * side, 128), nn.ReLU(), nn.Linear(128, 128), nn.ReLU(),
                                 nn.Linear(128, C * side * side), nn.ReLU())
        self.out = nn.Conv2d(C, 1, 1)

    def forward(self, image: torch.Tensor, log_scope: torch.Tensor) -> torch.Tensor:
        x, skips = torch.cat([image, log_scope], 1), []
        for i, blk in enumerate(self.down):
            x = blk(x)
            skips.append(x)
            if i < len(self.down) - 1:
                x = F.interpolate(x, scale_factor=0.5, mode="nearest")
        x = self.mlp(x).view_as(x)
        for i, blk in enumerate(self.up):
            x = blk(torch.cat([x, skips[-1 - i]], 1))
            if i < len(self.up) - 1:
                x = F.interpolate(x, scale_factor=2.0, mode="nearest")
        return self.out(x)


class ComponentVAE(nn.Module):
    """``(image, log mask)`` -> latent posterior; latent -> ``(rgb (B, 3, H, W), mask logit (B, 1, H, W))``."""

    def __init__(self, cfg: MONetConfig) -> None:
        super().__init__()
        self.encoder = conv_encoder(4, cfg.vae_channels, cfg.image_size, 2 * cfg.latent_dim)
        self.decoder = BroadcastDecoder(cfg.latent_dim, cfg.decoder_channels, 4, cfg.image_size)

    def encode(self, image: torch.Tensor, log_mask: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        mu, raw = self.encoder(torch.cat([image, log_mask], 1)).chunk(2, dim=1)
        return mu, F.softplus(raw) + 1e-4  # mean, standard deviation

    def decode(self, z: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        out = self.decoder(z)
        return torch.sigmoid(out[:, :3]), out[:, 3:]


class MONet(nn.Module):
    def __init__(self, cfg: MONetConfig = MONetConfig()) -> None:
        super().__init__()
        self.cfg = cfg
        self.attention = AttentionUNet(cfg)
        self.vae = ComponentVAE(cfg)

    def attention_masks(self, rgb: torch.Tensor) -> torch.Tensor:
        """``(B, K, H, W)`` log attention masks by stick-breaking over the scope (they sum to 1)."""
        log_scope = torch.zeros_like(rgb[:, :1])
        logs = []
        for _ in range(self.cfg.num_slots - 1):
            a = self.attention(rgb, log_scope)
            logs.append(log_scope + F.logsigmoid(a))
            log_scope = log_scope + F.logsigmoid(-a)
        logs.append(log_scope)
        return torch.cat(logs, 1)

    def _components(self, rgb: torch.Tensor, generator: torch.Generator | None):
        log_m = self.attention_masks(rgb)
        B, K, H, W = log_m.shape
        x = rgb.repeat_interleave(K, 0)
        mu, sd = self.vae.encode(x, log_m.reshape(B * K, 1, H, W))
        z = reparameterize(mu, sd, generator, self.training)
        colors, mask_logits = self.vae.decode(z)
        return log_m, mu, sd, colors.reshape(B, K, 3, H, W), mask_logits.reshape(B, K, H, W), z.reshape(B, K, -1)

    def forward(self, rgb: torch.Tensor, generator: torch.Generator | None = None) -> SlotOutput:
        """``rgb (B, 3, H, W)`` in [0, 1]: the reconstruction (the mask-weighted mean of the components),
        the attention masks and each component's RGB."""
        log_m, _, _, colors, _, z = self._components(rgb, generator)
        masks = log_m.exp()
        return SlotOutput((masks[:, :, None] * colors).sum(1), masks, colors, z)

    def loss(self, rgb: torch.Tensor, generator: torch.Generator | None = None) -> torch.Tensor:
        """The paper's objective per image: mixture negative log likelihood + beta KL(latents) + gamma KL(masks)."""
        log_m, mu, sd, colors, mask_logits, _ = self._components(rgb, generator)
        B, K = log_m.shape[:2]
        sigma = torch.full((1, K, 1, 1, 1), self.cfg.sigma_fg, dtype=rgb.dtype)
        sigma[:, 0] = self.cfg.sigma_bg
        nll = mixture_nll(rgb, colors, log_m, sigma)
        kl_z = (0.5 * (mu**2 + sd**2 - 1) - torch.log(sd)).sum(1).reshape(B, K).sum(1)
        log_m_dec = torch.log_softmax(mask_logits, dim=1)
        kl_m = (log_m.exp() * (log_m - log_m_dec)).sum((1, 2, 3))
        return (nll + self.cfg.beta * kl_z + self.cfg.gamma * kl_m).mean()
