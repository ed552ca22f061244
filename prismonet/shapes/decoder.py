"""The DeepSDF auto-decoder Phi(z_sh, x) -> signed distance, as an MLP.

The first layer (and the optional latent skip) is split into a latent part and a point part,
``W [z; x] = W_z z + W_x x``, so a latent shared by many points (one object's rays) is multiplied
once, not once per point; the result is the same function as DeepSDF's concatenation.

Without autograd (the renderer's root search, evaluation, meshing) the layers run in place on one
flat buffer: no bias copied into a fresh output, no second buffer for each ReLU. Same function, same
bits; on the root search's 16K-point blocks the unfused ops ran the MLP at a third of matmul speed
(BENCHMARKS.md, "Training step").
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn


INPLACE_NOGRAD = True
"""Take the in-place path without autograd (``False``: the autograd path's ops; for A/B benchmarks)."""


class LatentSizeError(ValueError):
    """A latent code whose size differs from the decoder's ``latent_dim``."""


@dataclass(frozen=True)
class SDFDecoderConfig:
    """Architecture of Phi."""

    latent_dim: int = 8
    """D_sh: 8 for Clevr, 16 for the ShapeNet-style sets."""
    width: int = 64
    """Hidden units per layer. 64 reaches the Clevr quality target and is ~2x cheaper than 96-128
    in pre-training and in every render (BENCHMARKS.md)."""
    depth: int = 4
    """Hidden layers."""
    skip_layer: int | None = None
    """Hidden layer (1..depth-1) whose input is re-joined with [z; x], as DeepSDF does at layer 4."""
    tanh_output: bool = True
    """Squash the output with tanh, as DeepSDF does (the loss clamps at +-0.1 anyway)."""

    def __post_init__(self) -> None:
        if self.latent_dim <= 0 or self.width <= 0 or self.depth <= 0:
            raise ValueError(f"latent_dim, width and depth must be positive, got {self}")
        if self.skip_layer is not None and not 1 <= self.skip_layer < self.depth:
            raise ValueError(f"skip_layer must be in 1..{self.depth - 1}, got {self.skip_layer}")


class _JoinLinear(nn.Module):
    """``W_h h + W_z z + W_x x + b`` without concatenating the per-point inputs."""

    def __init__(self, in_h: int, latent_dim: int, out: int) -> None:
        super().__init__()
        self.h = nn.Linear(in_h, out, bias=True) if in_h > 0 else None
        self.z = nn.Linear(latent_dim, out, bias=self.h is None)
        self.x = nn.Linear(3, out, bias=False)

    def forward(self, h: torch.Tensor | None, z: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
        y = self.x(x) + self.z(z)
        return y if self.h is None else y + self.h(h)


class LatentMLP(nn.Module):
    """An MLP of ``(z (..., D), x (..., 3))`` with ReLU hidden layers; leading dims of ``z``
    broadcast against ``x``. Shared by Phi (shape) and Psi (texture)."""

    def __init__(self, cfg: SDFDecoderConfig, out_dim: int) -> None:
        super().__init__()
        self.cfg = cfg
        layers = []
        for i in range(cfg.depth):
            if i == 0:
                layers.append(_JoinLinear(0, cfg.latent_dim, cfg.width))
            elif i == cfg.skip_layer:
                layers.append(_JoinLinear(cfg.width, cfg.latent_dim, cfg.width))
            else:
                layers.append(nn.Linear(cfg.width, cfg.width))
        self.layers = nn.ModuleList(layers)
        self.out = nn.Linear(cfg.width, out_dim)

    def check_latent(self, z: torch.Tensor) -> None:
        if z.shape[-1] != self.cfg.latent_dim:
            raise LatentSizeError(f"latent: expected size {self.cfg.latent_dim}, got {z.shape[-1]} (shape {tuple(z.shape)})")

    def features(self, z: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
        self.check_latent(z)
        if x.shape[-1] != 3:
            raise ValueError(f"points: expected shape (..., 3), got {tuple(x.shape)}")
        if INPLACE_NOGRAD and not torch.is_grad_enabled():
            fast = self._features_nograd(z, x)
            if fast is not None:
                return fast
        h = None
        for layer in self.layers:
            h = layer(h, z, x) if isinstance(layer, _JoinLinear) else layer(h)
            h = torch.relu(h)
        return self.out(h)

    def _features_nograd(self, z: torch.Tensor, x: torch.Tensor) -> torch.Tensor | None:
        """The same function without autograd: the latent part once per latent, then each hidden
        layer as ``F.linear`` and an in-place ReLU on a flat ``(points, width)`` buffer. ``None`` when
        ``z`` does not broadcast into ``x``'s leading shape (the general path handles it)."""
        lead = x.shape[:-1]
        try:
            if torch.broadcast_shapes(z.shape[:-1], lead) != lead:
                return None
        except RuntimeError:
            return None
        h = None
        for layer in self.layers:
            if isinstance(layer, _JoinLinear):
                y = layer.x(x)  # (..., W), a fresh buffer to accumulate into
                y.add_(layer.z(z))
                if layer.h is not None:
                    y.add_(layer.h(h.reshape(*lead, h.shape[-1])))
                h = y.relu_().reshape(-1, y.shape[-1])
            else:
                h = F.linear(h, layer.weight, layer.bias).relu_()
        return self.out(h).reshape(*lead, self.out.out_features)  # explicit width: lead may hold 0 points


class SDFDecoder(LatentMLP):
    """Phi: ``(z (..., D), x (..., 3)) -> sdf (...,)``; leading dims of ``z`` broadcast against ``x``.

    Example:
        >>> phi = SDFDecoder(SDFDecoderConfig(latent_dim=8))
        >>> phi(torch.zeros(2, 1, 8), torch.zeros(2, 100, 3)).shape
        torch.Size([2, 100])
    """

    def __init__(self, cfg: SDFDecoderConfig = SDFDecoderConfig()) -> None:
        super().__init__(cfg, 1)

    def forward(self, z: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
        y = self.features(z, x)[..., 0]
        return torch.tanh(y) if self.cfg.tanh_output else y
