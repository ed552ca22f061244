"""Hue rotation about the grey axis: the same scene with every object's colour turned, for training
(``TrainConfig.hue_rotate``).

Why: in the ShapeNet-style sets every mesh keeps its own material colour, so each seen model has a colour no other
seen model has, and an encoder can tell the model by its colour instead of its outline. On the novel cars it does:
the yellow Beetle is found at IoU 0.5 in 57 % of its appearances and the grey Peugeot in 39 %, but recoloured to a
seen car's red (the same pixels, each scaled by the ratio of the albedos) in 93 % and 90 % (EVALUATION.md,
session 73). Turning the colours in training takes that shortcut away.

The turn is a rotation of RGB space about the grey axis ``(1, 1, 1) / sqrt(3)``, by Rodrigues' formula. It is exact
for the scenes' shading: a Lambertian pixel under white light is ``albedo * shading`` per channel with one scalar
shading, and a linear map commutes with that scalar, so the turned image is the scene rendered with turned albedos.
Greys (the ground, the background) are its fixed points, and brightness (the mean of the channels) is kept. Values
are clamped to ``[0, 1]`` afterwards (a saturated colour can leave the cube); the scenes' albedos are dull enough
that this rarely bites.
"""

from __future__ import annotations

import math

import torch


def hue_rotation(angle: torch.Tensor) -> torch.Tensor:
    """``(..., 3, 3)`` rotation matrices about the grey axis by ``angle (...)`` radians (right-handed about
    ``(1, 1, 1)``)."""
    c, s = torch.cos(angle)[..., None, None], torch.sin(angle)[..., None, None]
    k = torch.full((3,), 1.0 / math.sqrt(3.0), dtype=angle.dtype, device=angle.device)
    kx = torch.zeros(3, 3, dtype=angle.dtype, device=angle.device)  # the cross-product matrix [k]x
    kx[0, 1], kx[0, 2], kx[1, 0], kx[1, 2], kx[2, 0], kx[2, 1] = -k[2], k[1], k[2], -k[0], -k[1], k[0]
    eye = torch.eye(3, dtype=angle.dtype, device=angle.device)
    return c * eye + s * kx + (1 - c) * torch.outer(k, k)


def rotate_hue(rgb: torch.Tensor, angle: torch.Tensor) -> torch.Tensor:
    """``rgb (B, 3, ...)`` with each image's colours rotated about the grey axis by ``angle (B,)`` radians, clamped
    to ``[0, 1]``."""
    if rgb.shape[1] != 3 or angle.shape != rgb.shape[:1]:
        raise ValueError(f"expected rgb (B, 3, ...) and angle (B,), got {tuple(rgb.shape)} and {tuple(angle.shape)}")
    R = hue_rotation(angle.to(rgb.dtype).to(rgb.device))  # (B, 3, 3)
    flat = rgb.reshape(rgb.shape[0], 3, -1)
    return torch.bmm(R, flat).reshape(rgb.shape).clamp(0.0, 1.0)


def random_angles(n: int, max_degrees: float, g: torch.Generator) -> torch.Tensor:
    """``(n,)`` angles in radians drawn uniformly from ``[-max_degrees, max_degrees]``."""
    return (torch.rand(n, generator=g, dtype=torch.float64) * 2 - 1) * math.radians(max_degrees)
