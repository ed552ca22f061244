"""What every 2-D baseline returns: a reconstruction and one mask and colour image per slot."""

from __future__ import annotations

from dataclasses import dataclass

import torch


@dataclass
class SlotOutput:
    image: torch.Tensor
    """``(B, 3, H, W)`` reconstruction in [0, 1]."""
    masks: torch.Tensor
    """``(B, K, H, W)`` slot masks that sum to 1 over slots (an instance map is their argmax)."""
    colors: torch.Tensor
    """``(B, K, 3, H, W)`` each slot's RGB."""
    latents: torch.Tensor
    """``(B, K, D)`` each slot's representation."""
