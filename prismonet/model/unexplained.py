"""The parts of the input that no slot explains yet, and where the next slot should look.

Two users: re-seeding at test time (``prismonet.model.reseed``) and the anchored encoder
(``ModelConfig.anchor``), whose every step is pointed at the largest unexplained part of the image.

- ``opening``: a morphological opening of a pixel mask, which removes the one-pixel seams that a fitted
  outline leaves and keeps a small object's blob whole.
- ``largest_components``: per scene, the largest 8-connected component of a mask (OpenCV).
- ``largest_region``: both together on a mask of unexplained pixels, away from parts proposed in vain: what
  re-seeding and the anchors propose.
- ``find_anchors``: per scene, the pixel deepest inside the largest component of what the composition
  leaves unexplained in colour (the centre of the largest disc that fits in it), and the component itself.
  Colour alone, like the encoder: a photo has no depth. The deepest pixel, not the centroid, because two
  touching objects make one component whose centroid can fall between them on the ground, while the
  deepest pixel lies inside the larger of the two.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import torch
import torch.nn.functional as F

from prismonet.data.gray import is_gray, luma
from prismonet.model.config import SHADE_MAX
from prismonet.model.stopping import color_unexplained, erode


def opening(mask: torch.Tensor, pixels: int) -> torch.Tensor:
    """``(B, H, W)`` bool ``mask`` opened by a ``(2 pixels + 1)``-square: eroded, then dilated, within ``mask``."""
    if pixels == 0:
        return mask
    k = 2 * pixels + 1
    grown = F.max_pool2d(erode(mask, pixels)[:, None].float(), k, stride=1, padding=pixels)[:, 0] > 0.5
    return grown & mask


def largest_components(mask: torch.Tensor, min_area: int) -> list[np.ndarray | None]:
    """Per scene of ``mask (B, H, W)`` bool, the boolean ``(H, W)`` mask of its largest 8-connected
    component with at least ``min_area`` pixels, or ``None``."""
    found: list[np.ndarray | None] = []
    for m in mask.cpu().numpy().astype(np.uint8):
        n, labels, stats, _ = cv2.connectedComponentsWithStats(m, connectivity=8)
        if n <= 1:
            found.append(None)
            continue
        areas = stats[1:, cv2.CC_STAT_AREA]
        best = int(areas.argmax())
        found.append(labels == best + 1 if areas[best] >= min_area else None)
    return found


def largest_region(unexplained: torch.Tensor, open_pixels: int, min_area: int,
                   exclude: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """``(region (B, H, W) bool, found (B,) bool)``: per scene, the largest component of at least ``min_area``
    pixels of ``unexplained (B, H, W)`` bool once opened by ``open_pixels`` and cleared of ``exclude``
    (empty where there is none)."""
    mask = opening(unexplained, open_pixels)
    if exclude is not None:
        mask = mask & ~exclude
    region = torch.zeros_like(mask)
    found = torch.zeros(mask.shape[0], dtype=torch.bool)  # on the host: read back by the callers
    for b, comp in enumerate(largest_components(mask, min_area)):
        if comp is not None:
            region[b], found[b] = torch.from_numpy(comp).to(mask.device), True
    return region, found.to(mask.device)


def shaded(image: torch.Tensor, comp_image: torch.Tensor, k_min: float, tol: float) -> torch.Tensor:
    """``(B, H, W)`` bool: where ``image (B, 3, H, W)`` is ``comp_image`` darkened by one factor ``k`` in ``[k_min,
    SHADE_MAX]``: every channel's ratio image / composition within ``tol`` of the channels' mean ratio, the composition
    at least 0.15 in some channel (a ratio to black means nothing)."""
    ratio = image / comp_image.clamp_min(0.05)
    k = ratio.mean(1)
    same = (ratio - k[:, None]).abs().amax(1) < tol
    return same & (k >= k_min) & (k <= SHADE_MAX) & (comp_image.amax(1) > 0.15)


@dataclass(frozen=True)
class AnchorRule:
    """What counts as unexplained, and how large a part must be to be worth a slot."""

    color_tol: float = 0.25
    """Largest per-channel colour difference (in [0, 1]) between the input and the composition of an
    explained pixel (the stop rule's)."""
    open: int = 1
    """Radius in pixels of the opening applied to the unexplained pixels."""
    min_area: int = 20
    """Least pixels of a component (after the opening) worth a slot."""
    min_gain: int = 10
    """A slot that leaves all but fewer than this many pixels of its anchor's component unexplained has failed
    there: the component is not proposed again (``failed``), so that the next step looks elsewhere."""
    shade_min: float | None = None
    """With a value (beyond the paper, for light with cast shadows): a pixel the composition misses is still explained
    where the input is the composition darkened by one factor ``k`` in ``[shade_min, SHADE_MAX]`` in every channel
    (each channel's ratio within ``shade_tol`` of their mean; the composition not black): a shadow, which the
    renderer does not cast. The price: a dark object of the ground's own hue reads as a shadow."""
    shade_tol: float = 0.03
    gray_tol: float | None = None
    """With a value (beyond the paper, for greyscale photos): in a grey input image (``is_gray``) a pixel is unexplained
    where the composition's luminance misses the input's by more than this, and no pixel reads as a shadow. A grey
    image gives only luminance: the colour differences ``color_tol`` was set for shrink to luminance differences, and
    every change in it is an even darkening. Colour images are read as without it. None: grey images are read as
    colour ones."""

    def __post_init__(self) -> None:
        if not self.color_tol > 0 or self.open < 0 or self.min_area < 1 or self.min_gain < 1:
            raise ValueError(f"anchor rule: color_tol must be > 0, open >= 0, min_area >= 1 and min_gain >= 1, "
                             f"got {self.color_tol}, {self.open}, {self.min_area} and {self.min_gain}")
        if self.gray_tol is not None and not self.gray_tol > 0:
            raise ValueError(f"anchor rule: gray_tol must be > 0 (or None), got {self.gray_tol}")
        if self.shade_min is not None and not (0 < self.shade_min < SHADE_MAX and self.shade_tol > 0):
            raise ValueError(f"anchor rule: shade_min must be in (0, {SHADE_MAX}) and shade_tol > 0, "
                             f"got {self.shade_min} and {self.shade_tol}")

    def shadows(self, image: torch.Tensor, comp_image: torch.Tensor, gray: torch.Tensor | None = None) -> torch.Tensor:
        """``(B, H, W)`` bool: the pixels this rule reads as a cast shadow on the composition ``comp_image`` (``shaded``
        by ``shade_min``): none without it, and none in a grey image with ``gray_tol`` (there every change is an even
        darkening). ``gray``: ``is_gray(image)``, when the caller has it already."""
        if self.shade_min is None:
            return torch.zeros_like(image[:, 0], dtype=torch.bool)
        s = shaded(image, comp_image, self.shade_min, self.shade_tol)
        if self.gray_tol is not None:
            s = s & ~(is_gray(image) if gray is None else gray)[:, None, None]
        return s

    def unexplained(self, image: torch.Tensor, comp_image: torch.Tensor) -> torch.Tensor:
        """``(B, H, W)`` bool: the pixels whose colour the composition ``comp_image`` misses (``shadows`` excepted;
        in grey images, with ``gray_tol``, the pixels whose luminance it misses)."""
        bad = color_unexplained(image, comp_image, self.color_tol)
        gray = is_gray(image) if self.gray_tol is not None else None
        if self.shade_min is not None:
            bad = bad & ~self.shadows(image, comp_image, gray)
        if gray is not None:
            if bool(gray.any()):
                dark_or_bright = (luma(comp_image) - luma(image)).abs() > self.gray_tol
                bad = torch.where(gray[:, None, None], dark_or_bright, bad)
        return bad

    def failed(self, anchors: "Anchors", image: torch.Tensor, comp_image: torch.Tensor) -> torch.Tensor:
        """``(B, H, W)`` bool: the components of ``anchors`` that the composition with the new slot,
        ``comp_image``, still leaves unexplained but for fewer than ``min_gain`` pixels."""
        gained = (anchors.region & ~self.unexplained(image, comp_image)).sum((1, 2))
        return anchors.region & (gained < self.min_gain)[:, None, None]


@dataclass
class Anchors:
    """Per scene: ``uv (B, 2)`` the anchor pixel (OpenCV convention: pixel centres at integers),
    ``region (B, H, W)`` bool the component it lies in, ``found (B,)`` bool (false: nothing left to
    explain; ``uv`` is then the image centre and ``region`` empty)."""

    uv: torch.Tensor
    region: torch.Tensor
    found: torch.Tensor


def deepest_pixel(region: np.ndarray) -> tuple[float, float]:
    """``(u, v)`` of the pixel farthest from the outside of ``region (H, W)`` bool (Euclidean distance
    transform; the image border does not count as outside); several at the same distance: their mean."""
    dist = cv2.distanceTransform(region.astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    ys, xs = np.nonzero(dist >= dist.max() - 1e-6)
    return float(xs.mean()), float(ys.mean())


@torch.no_grad()
def find_anchors(image: torch.Tensor, comp_image: torch.Tensor, rule: AnchorRule = AnchorRule(),
                 exclude: torch.Tensor | None = None) -> Anchors:
    """The anchors of ``image (B, 3, H, W)`` given the composition so far ``comp_image (B, 3, H, W)``
    (see the module docstring), away from the pixels ``exclude (B, H, W)`` bool (components proposed in vain)."""
    B, _, H, W = image.shape
    region, found = largest_region(rule.unexplained(image, comp_image), rule.open, rule.min_area, exclude)
    uv = torch.tensor([(W - 1) / 2.0, (H - 1) / 2.0], dtype=image.dtype).repeat(B, 1)  # filled on the host
    for b in torch.nonzero(found).flatten().tolist():
        uv[b] = torch.tensor(deepest_pixel(region[b].cpu().numpy()), dtype=image.dtype)
    return Anchors(uv.to(image.device), region, found)
