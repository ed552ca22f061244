"""Greyscale images: what a greyscale camera records of a scene, for training (``TrainConfig.gray_share``) and for
measuring a model on grey input (``prismonet evaluate --gray``). Two of the five labelled photos are grey
(EVALUATION.md, session 53)."""

from __future__ import annotations

from dataclasses import replace

import torch

LUMA = (0.299, 0.587, 0.114)
"""Rec. 601 luma weights: what ``cv2.cvtColor(..., COLOR_RGB2GRAY)`` and most greyscale photos record."""


GRAY_SPREAD = 0.01
"""An image is grey (``is_gray``) where no pixel's channels differ by more than this (about 2.5 / 255: rounding)."""


def luma(rgb: torch.Tensor) -> torch.Tensor:
    """``(B, ...)``: the luminance of ``rgb (B, 3, ...)`` (``LUMA``)."""
    w = torch.tensor(LUMA, dtype=rgb.dtype, device=rgb.device).reshape(1, 3, *([1] * (rgb.dim() - 2)))
    return (rgb * w).sum(1)


def is_gray(image: torch.Tensor) -> torch.Tensor:
    """``(B,)`` bool: the images of ``image (B, 3, H, W)`` whose every pixel has equal channels (within
    ``GRAY_SPREAD``): a greyscale photo, which records luminance alone."""
    return (image.amax(1) - image.amin(1)).flatten(1).amax(1) <= GRAY_SPREAD


def to_gray(rgb: torch.Tensor, which: torch.Tensor | None = None) -> torch.Tensor:
    """``rgb (B, 3, ...)`` with the images where ``which (B,)`` is true (all, without it) replaced by their luminance
    in all three channels (``LUMA``); the others unchanged."""
    gray = luma(rgb).unsqueeze(1).expand_as(rgb)
    if which is None:
        return gray.contiguous()
    return torch.where(which.reshape(-1, *([1] * (rgb.dim() - 1))).to(rgb.device), gray, rgb)


class GrayScenes:
    """A view of a ``SceneDataset`` whose images are grey; everything else (depth, labels, cameras) as it is.
    ``share`` < 1: only that share of the scenes, each drawn once from ``(seed, index)``, so that a scene reads the
    same wherever and however often it is asked for (fits that cache a model's decoding, ``refiner_fit``)."""

    def __init__(self, ds, share: float = 1.0, seed: int = 0) -> None:
        if not 0 < share <= 1:
            raise ValueError(f"grey scenes: share must be in (0, 1], got {share}")
        self.ds, self.share, self.seed = ds, share, seed

    def grey(self, index: int) -> bool:
        """Whether scene ``index`` is shown grey."""
        if self.share >= 1:
            return True
        g = torch.Generator().manual_seed(self.seed * 1_000_003 + int(index))
        return bool(torch.rand((), generator=g) < self.share)

    def __getattr__(self, name):
        return getattr(self.ds, name)

    def __len__(self) -> int:
        return len(self.ds)

    def batch(self, indices):
        b = self.ds.batch(indices)
        which = None if self.share >= 1 else torch.tensor([self.grey(i) for i in indices])
        return replace(b, rgb=to_gray(b.rgb, which))
