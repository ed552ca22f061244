"""Take back the slots a keep output dropped that alone cover part of the image no kept slot explains (beyond the
paper).

A refiner with a keep output (``ModelConfig.refiner_keep``) is fitted to say whether the test-time search's fit shows
a slot. On shapes the prior never saw the search fits badly, and the keep output learns to drop slots that were the
only ones on their object: on novel cars the count falls by half an object per scene (EVALUATION.md, "Session 72").
Rescue runs after the refinement passes. A pixel is *open* when the kept slots' composition does not explain it
(``StopRule.unexplained``: colour within ``color_tol``, depth within ``depth_tol`` where the input has depth). A dropped
slot comes back when, added to the kept ones, it would show at least ``rule.min_gain`` open pixels, and these are at
least half of all it would show. Its own colour is not read: on an unseen shape the texture is what is off
(a median colour error of 0.28 on novel cars' pixels, over the 0.25 tolerance). A dropped duplicate of a kept slot,
a sliver on the ground or a hidden slot shows no open pixel and stays dropped.

Dropped slots come back one at a time, the one that covers most first; what it shows is then claimed, so of two
dropped duplicates on one missed object one comes back. The cost is one render of the dropped slots and a few
z-buffer compositions: the kept slots cast no ray again.
"""

from __future__ import annotations

import torch

from prismonet.model.stopping import StopRule
from prismonet.render.composite import composite


RESCUE_SHARE = 0.5
"""The least share of the pixels a dropped slot would show that must be ones the kept slots leave unexplained."""


def rescue_keep(rule: StopRule, obj_depth: torch.Tensor, obj_mask: torch.Tensor, obj_color: torch.Tensor,
                bg_color: torch.Tensor, bg_depth: torch.Tensor, image: torch.Tensor, depth: torch.Tensor | None,
                keep: torch.Tensor, dropped: torch.Tensor, share: float = RESCUE_SHARE) -> torch.Tensor:
    """``(B, N)`` bool: ``keep`` with the ``dropped`` slots that cover enough of what it leaves unexplained taken back
    (see the module docstring).

    Args:
        rule: a pixel is unexplained by the kept slots' composition as ``rule`` says (colour within ``color_tol``; depth
            within ``depth_tol`` where ``depth`` is given); a dropped slot comes back when it would show at least
            ``rule.min_gain`` such pixels not yet claimed, and they are at least ``share`` of all it would show.
        obj_depth, obj_mask: ``(B, N, H, W)`` every slot's render, the dropped ones' included.
        obj_color: ``(B, N, 3, H, W)`` (only the kept slots' colours are read).
        bg_color: ``(B, 3)``; bg_depth: ``(B, 1, H, W)`` the ground plane's depth.
        image: ``(B, 3, H, W)`` the input; depth: ``(B, 1, H, W)`` or ``None`` (colour alone, as for a photo).
        keep: ``(B, N)`` bool, the slots kept now; dropped: ``(B, N)`` bool, the candidates (not in ``keep``).
    """
    if keep.shape != dropped.shape or keep.shape != obj_mask.shape[:2]:
        raise ValueError(f"rescue: keep {tuple(keep.shape)} and dropped {tuple(dropped.shape)} must both be (B, N) of "
                         f"the renders {tuple(obj_mask.shape[:2])}")
    kept = composite(obj_depth, obj_mask & keep[:, :, None, None], obj_color, bg_color, bg_depth)
    open_ = rule.unexplained(image, depth, kept.image, torch.minimum(kept.depth, bg_depth), eroded=False)  # (B, H, W)
    keep = keep.clone()
    left = dropped & ~keep & obj_mask.flatten(2).any(2)
    B, N = keep.shape
    for _ in range(N):
        if not left.any():
            break
        gain = torch.full((B, N), -1, dtype=torch.long, device=keep.device)
        for k in range(N):
            if not left[:, k].any():
                continue
            kk = keep.clone()
            kk[:, k] |= left[:, k]
            inst = composite(obj_depth, obj_mask & kk[:, :, None, None], obj_color, bg_color, bg_depth).instance
            shown = inst == k + 1
            got = (shown & open_).flatten(1).sum(1)
            ok = left[:, k] & (got >= share * shown.flatten(1).sum(1))
            gain[:, k] = torch.where(ok, got, gain[:, k])
        best, k = gain.max(1)
        take = best >= rule.min_gain
        if not take.any():
            break
        rows = torch.nonzero(take).flatten()
        keep[rows, k[rows]] = True
        left[rows, k[rows]] = False
        now = composite(obj_depth, obj_mask & keep[:, :, None, None], obj_color, bg_color, bg_depth).instance
        open_[rows] &= now[rows] != (k[rows] + 1)[:, None, None]  # what a slot taken back shows is claimed
    return keep
