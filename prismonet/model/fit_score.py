"""How badly a composed render explains the input: the one criterion that test-time slot selection
(``select``), pose search (``search``) and colour fit (``color_fit``) all minimise.

The training loss's unblurred terms at their weights: mean squared colour error (summed over
channels) plus 0.1 x mean absolute depth error, the latter only when the input has depth. With
``far_depth`` the render's depth is clipped there first, like the sensor's (``loss.far_clip`` in
training): an object placed correctly beyond the clip is then not charged for rendering deeper than it.
"""

from __future__ import annotations

import torch


def fit_score(image: torch.Tensor, depth: torch.Tensor | None, rgb: torch.Tensor, target_depth: torch.Tensor | None,
              w_image: float = 1.0, w_depth: float = 0.1, far_depth: float | None = None) -> torch.Tensor:
    """``(B,)`` how badly a composed ``image (B, 3, H, W)`` and ``depth (B, 1, H, W)`` explain the
    input (lower is better): ``w_image`` x mean squared colour error (summed over channels) +
    ``w_depth`` x mean absolute depth error (only when ``target_depth`` is given), of ``depth``
    clipped at ``far_depth`` when that is given."""
    s = w_image * ((image - rgb) ** 2).sum(1).mean((1, 2))
    if target_depth is not None:
        if far_depth is not None:
            depth = depth.clamp(max=far_depth)
        s = s + w_depth * (depth - target_depth).abs().mean((1, 2, 3))
    return s
