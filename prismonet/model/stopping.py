"""Stop the recurrent encoder when the objects found so far explain the input (beyond the paper,
which always runs all ``N`` steps).

The composition of the slots found so far (background colour, ground-plane depth, z-buffered
objects) is compared with the input. A pixel is *unexplained* when its colour differs by more than
``color_tol`` in some channel, or (when the input has depth) its depth differs by more than
``depth_tol`` world units. The unexplained pixels are eroded by ``erode`` pixels (a
``(2 erode + 1)``-square minimum), which removes the seams along the outlines of objects that are
found but not fitted exactly. Two tests, both at the evaluation's own threshold of 25 pixels, under
which an object does not count (``MIN_VISIBLE_PIXELS``):

- *explained*: before a step, fewer than ``min_pixels`` pixels are unexplained. The step is not
  taken; this costs nothing, since the encoder builds that composition anyway.
- *no gain*: after a step, its slot has made fewer than ``min_gain`` more pixels explained (it is a
  duplicate, hidden, or wrong). The slot is dropped and the scene stops.

A stopped scene takes no more encoder steps; its remaining slots are inactive, so they cast no ray,
and when every scene of a batch has stopped the loop ends.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, replace
import torch
import torch.nn.functional as F

from prismonet.evaluation.metrics import MIN_VISIBLE_PIXELS



def erode(mask: torch.Tensor, pixels: int) -> torch.Tensor:
    """``(B, H, W)`` bool ``mask`` eroded by a ``(2 pixels + 1)``-square minimum (image borders pad
    with true, so an object cut by the border is not eroded from that side)."""
    if pixels == 0:
        return mask
    k = 2 * pixels + 1
    return -F.max_pool2d(-mask[:, None].float(), k, stride=1, padding=pixels)[:, 0] > 0.5


def color_unexplained(image: torch.Tensor, comp_image: torch.Tensor, tol: float) -> torch.Tensor:
    """``(B, H, W)`` bool: the pixels of ``image (B, 3, H, W)`` whose colour ``comp_image`` misses by more than
    ``tol`` in some channel."""
    return (comp_image - image).abs().amax(1) > tol


@dataclass(frozen=True)
class StopRule:
    """When the encoder stops (see the module docstring)."""

    min_pixels: int = MIN_VISIBLE_PIXELS
    """Explained when fewer unexplained pixels than this remain (after erosion)."""
    min_gain: int = 5
    """A slot that makes fewer pixels explained than this (before erosion) is dropped, and the scene stops."""
    color_tol: float = 0.25
    """Largest per-channel colour difference (in [0, 1]) of an explained pixel."""
    depth_tol: float = 0.5
    """Largest depth difference (world units) of an explained pixel; unused without input depth."""
    erode: int = 0
    """Pixels of erosion applied to the unexplained pixels before the *explained* test."""

    def __post_init__(self) -> None:
        if self.min_pixels < 1 or self.min_gain < 1 or self.erode < 0:
            raise ValueError(f"stop rule: min_pixels and min_gain must be >= 1 and erode >= 0, "
                             f"got {self.min_pixels}, {self.min_gain} and {self.erode}")
        if not (self.color_tol > 0 and self.depth_tol > 0):
            raise ValueError(f"stop rule: tolerances must be positive, got colour {self.color_tol} and depth {self.depth_tol}")

    def unexplained(self, image: torch.Tensor, depth: torch.Tensor | None, comp_image: torch.Tensor,
                    comp_depth: torch.Tensor, eroded: bool = True) -> torch.Tensor:
        """``(B, H, W)`` bool: the pixels the composition does not explain (after erosion, unless
        ``eroded`` is false). Input depth 0 means unknown and is ignored there."""
        bad = color_unexplained(image, comp_image, self.color_tol)
        if depth is not None:
            known = depth[:, 0] > 0
            bad = bad | (known & ((comp_depth[:, 0] - depth[:, 0]).abs() > self.depth_tol))
        return erode(bad, self.erode) if eroded else bad

    def bind(self, image: torch.Tensor, depth: torch.Tensor | None = None) -> "BoundStop":
        """The rule on input ``image (B, 3, H, W)`` and ``depth (B, 1, H, W)`` (``None``: colour
        alone, as for a photo), for the model's loop."""
        return BoundStop(self, image, depth)

    def record(self) -> dict:
        return asdict(self)


@dataclass
class BoundStop:
    """A ``StopRule`` on one input batch: what ``PriSMONet.forward`` calls."""

    rule: StopRule
    image: torch.Tensor
    depth: torch.Tensor | None

    def count(self, comp_image: torch.Tensor, comp_depth: torch.Tensor) -> torch.Tensor:
        """``(B, 2)`` unexplained pixels of the composition ``comp_image (B, 3, H, W)``,
        ``comp_depth (B, 1, H, W)`` (the ground plane's depth where no object is): after erosion,
        and before."""
        bad = self.rule.unexplained(self.image, self.depth, comp_image, comp_depth, eroded=False)
        return torch.stack([erode(bad, self.rule.erode).sum((1, 2)), bad.sum((1, 2))], 1)

    def explained(self, count: torch.Tensor) -> torch.Tensor:
        """``(B,)``: fewer than ``min_pixels`` unexplained pixels after erosion."""
        return count[:, 0] < self.rule.min_pixels

    def gained(self, before: torch.Tensor, after: torch.Tensor) -> torch.Tensor:
        """``(B,)``: at least ``min_gain`` more pixels explained (before erosion, so that a slot that
        finds a small object is credited with all of it)."""
        return before[:, 1] - after[:, 1] >= self.rule.min_gain


def stop_counts(rule: StopRule, out, image: torch.Tensor, depth: torch.Tensor | None) -> torch.Tensor:
    """``(B,)`` the slots a stopped encoder keeps, read off a full output ``out`` (a ``ModelOutput``
    of every step): the slots before the stop are the same either way, since each step sees only the
    composition of the steps before it. For choosing the rule's settings from one decoding."""
    from prismonet.render import composite

    bound = rule.bind(image, depth)
    B, N = out.obj_depth.shape[:2]
    kept = torch.full((B,), N, dtype=torch.long)

    def count(k: int) -> torch.Tensor:
        c = composite(out.obj_depth, out.obj_mask, out.obj_color, out.latents.bg_color, out.bg_depth, upto=k)
        return bound.count(c.image, torch.minimum(c.depth, out.bg_depth))

    before = count(0)
    for k in range(N):
        after = count(k + 1)
        stop = (bound.explained(before) | ~bound.gained(before, after)) & (kept == N)
        kept[stop] = k
        before = after
    return kept


def keep_first(out, counts: torch.Tensor):
    """``out`` with each scene's slots from ``counts[b]`` on emptied (no pixels, inactive), composed anew."""
    N = out.obj_depth.shape[1]
    return keep_slots(out, torch.arange(N)[None] < counts[:, None])


def keep_slots(out, keep: torch.Tensor):
    """``out`` with the slots where ``keep (B, N)`` is false emptied (no pixels, inactive), composed anew."""
    from prismonet.render import composite

    mask = out.obj_mask & keep[:, :, None, None]
    p = out.latents.params
    params = replace(p, active=keep if p.active is None else p.active & keep)
    comp = composite(out.obj_depth, mask, out.obj_color, out.latents.bg_color, out.bg_depth)
    return replace(out, latents=replace(out.latents, params=params), composite=comp, obj_mask=mask)
