"""How badly a composed render explains the input: the one criterion that test-time slot selection
(``select``), pose search (``search``) and colour fit (``color_fit``) all minimise.

The training loss's unblurred terms at their weights: mean squared colour error (summed over
channels) plus 0.1 x mean absolute depth error, the latter only when the input has depth.
"""

from __future__ import annotations

import torch


def fit_score(image: torch.Tensor, depth: torch.Tensor | None, rgb: torch.Tensor, target_depth: torch.Tensor | None,
              w_image: float = 1.0, w_depth: float = 0.1) -> torch.Tensor:
    """``(B,)`` how badly a composed ``image (B, 3, H, W)`` and ``depth (B, 1, H, W)`` explain the
    input (lower is better): ``w_image`` x mean squared colour error (summed over channels) +
    ``w_depth`` x mean absolute depth error (only when ``target_depth`` is given)."""
    s = w_image * ((image - rgb) ** 2).sum(1).mean((1, 2))
    if target_depth is not None:
        s = s + w_depth * (depth - target_depth).abs().mean((1, 2, 3))
    return s
