"""Z-buffer composition of per-object renders over the background plane (the paper's F)."""

from __future__ import annotations

from dataclasses import dataclass

import torch


@dataclass
class Composite:
    """A composed scene.

    Attributes:
        image: ``(B, 3, H, W)``; depth: ``(B, 1, H, W)``; mask: ``(B, 1, H, W)`` float, 1 where an
        object wins; instance: ``(B, H, W)`` int64, 0 = background, k = slot k-1 (1-based).
    """

    image: torch.Tensor
    depth: torch.Tensor
    mask: torch.Tensor
    instance: torch.Tensor


def zbuffer(obj_depth: torch.Tensor, obj_mask: torch.Tensor, upto: int | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Winning slot per pixel among slots ``< upto``: ``(winner (B, H, W) int64, any (B, H, W) bool)``."""
    d = obj_depth[:, :upto].detach()
    m = obj_mask[:, :upto]
    if d.shape[1] == 0:
        B, _, H, W = obj_depth.shape
        return (torch.zeros(B, H, W, dtype=torch.long, device=obj_depth.device),
                torch.zeros(B, H, W, dtype=torch.bool, device=obj_depth.device))
    d = torch.where(m, d, torch.full_like(d, float("inf")))
    winner = d.min(dim=1).indices  # first minimum on ties, like argmin, and ~14x faster on CPU
    return winner, m.any(dim=1)


def composite(
    obj_depth: torch.Tensor, obj_mask: torch.Tensor, obj_color: torch.Tensor, bg_color: torch.Tensor,
    bg_depth: torch.Tensor, upto: int | None = None,
) -> Composite:
    """Compose slots ``0..upto-1`` (all by default) over the background by z-buffering.

    Args:
        obj_depth: ``(B, K, H, W)``; obj_mask: ``(B, K, H, W)`` bool; obj_color: ``(B, K, 3, H, W)``.
        bg_color: ``(B, 3)`` the regressed ground colour; bg_depth: ``(B, 1, H, W)`` known plane depth.
    """
    winner, hit = zbuffer(obj_depth, obj_mask, upto)
    w = winner[:, None]
    depth = torch.gather(obj_depth, 1, w)  # (B, 1, H, W)
    color = torch.gather(obj_color, 1, w[:, :, None].expand(-1, -1, 3, -1, -1))[:, 0]  # (B, 3, H, W)
    hit4 = hit[:, None]
    image = torch.where(hit4, color, bg_color[:, :, None, None].expand_as(color))
    depth = torch.where(hit4, depth, bg_depth)
    instance = torch.where(hit, winner + 1, torch.zeros_like(winner))
    return Composite(image, depth, hit4.to(image.dtype), instance)


def presence_composite(
    obj_depth: torch.Tensor, obj_mask: torch.Tensor, obj_color: torch.Tensor, presence: torch.Tensor,
    bg_color: torch.Tensor, bg_depth: torch.Tensor,
) -> Composite:
    """Compose slots that are each present with a probability (the explicit presence output).

    Per pixel, the slots that hit it are taken front to back (by detached depth; ties keep slot
    order) and composed like layers of opacity ``presence``: slot k adds ``p_k T_k`` of its colour
    and depth, where ``T_k`` is the product of ``1 - p_j`` over the slots in front of it, and the
    background gets what is left. With every presence 0 or 1 this is exactly ``composite`` of the
    present slots; in between it is differentiable in ``presence``, colours and depths.

    Args:
        presence: ``(B, K)`` in [0, 1]; the rest as in ``composite``. ``instance`` and ``mask`` are
        those of the slots with presence >= 0.5.
    """
    B, K, H, W = obj_depth.shape
    alpha = presence[:, :, None, None] * obj_mask.to(obj_depth.dtype)  # (B, K, H, W)
    order = torch.where(obj_mask, obj_depth.detach(), torch.full_like(obj_depth, float("inf")))
    order = order.sort(dim=1, stable=True).indices
    a = torch.gather(alpha, 1, order)
    d = torch.gather(obj_depth, 1, order)
    c = torch.gather(obj_color, 1, order[:, :, None].expand(B, K, 3, H, W))
    keep = torch.cumprod(1 - a, dim=1)  # transmittance behind each layer
    T = torch.cat([torch.ones_like(keep[:, :1]), keep[:, :-1]], 1)
    w = a * T  # (B, K, H, W)
    rest = keep[:, -1:]  # (B, 1, H, W)
    image = (w[:, :, None] * c).sum(1) + rest * bg_color[:, :, None, None]
    depth = (w * d).sum(1, keepdim=True) + rest * bg_depth
    winner, hit = zbuffer(obj_depth, obj_mask & (presence >= 0.5)[:, :, None, None])
    return Composite(image, depth, hit[:, None].to(image.dtype), torch.where(hit, winner + 1, torch.zeros_like(winner)))
