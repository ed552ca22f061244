"""The texture field Psi(z_tex, x_obj) -> RGB in [0, 1]: an MLP like Phi (Texture Fields)."""

from __future__ import annotations

import torch

from prismonet.shapes.decoder import LatentMLP, SDFDecoderConfig


class TextureField(LatentMLP):
    """``(z (..., D_tex), x (..., 3)) -> rgb (..., 3)``."""

    def __init__(self, tex_dim: int, width: int = 64, depth: int = 4) -> None:
        super().__init__(SDFDecoderConfig(latent_dim=tex_dim, width=width, depth=depth), 3)

    def forward(self, z: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
        return torch.sigmoid(self.features(z, x))
