"""The losses' Gaussian blur as two small matrix products.

A separable Gaussian blur with replicated borders is linear in each image axis, so it is
``B_H @ x @ B_W^T`` with two banded ``(n, n)`` matrices that hold the normalised taps (the border
taps folded onto the edge pixel). On 64x64 images this is the same function as
``kornia.filters.gaussian_blur2d(x, (k, k), (s, s), border_type="replicate")`` to float rounding,
and several times cheaper on CPU, backward included: oneDNN's convolution is slow on 1- and
3-channel maps (BENCHMARKS.md, "Session 58: the losses' Gaussian blur as two matrix products").

Example:
    >>> x = torch.zeros(1, 1, 5, 5); x[..., 2, 2] = 1
    >>> y = gaussian_blur(x, 1.0, 5)
    >>> round(float(y.sum()), 6), bool(torch.allclose(y, y.transpose(-1, -2)))
    (1.0, True)
"""

from __future__ import annotations

import functools

import torch


def blur_matrices(n: int, sigma: torch.Tensor, taps: int) -> torch.Tensor:
    """``(B, n, n)``: for each of ``sigma (B,)``, row ``i`` holds the ``taps`` normalised Gaussian weights of output
    pixel ``i``, with replicated borders (taps past an edge land on the edge pixel); on ``sigma``'s device and dtype."""
    if n <= 0 or taps <= 0 or taps % 2 == 0 or not bool((sigma > 0).all()):
        raise ValueError(f"blur: size and taps must be positive, taps odd and every sigma > 0, got {n}, {taps}, {sigma}")
    r, dev = taps // 2, sigma.device
    offsets = torch.arange(-r, r + 1, dtype=sigma.dtype, device=dev)
    w = torch.exp(-(offsets**2) / (2 * sigma[:, None] ** 2))
    w = w / w.sum(1, keepdim=True)  # (B, taps)
    cols = (torch.arange(n, device=dev)[:, None] + torch.arange(-r, r + 1, device=dev)).clamp(0, n - 1)  # (n, taps)
    one_hot = torch.nn.functional.one_hot(cols, n).to(sigma.dtype)  # (n, taps, n): where each tap lands
    return torch.einsum("bt,itj->bij", w, one_hot)


@functools.lru_cache(maxsize=16)
def _blur_matrix(n: int, sigma: float, taps: int, dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    # built in float64 on the host whatever the default device, then moved
    host = torch.tensor([sigma], dtype=torch.float64, device=torch.device("cpu"))
    return blur_matrices(n, host, taps)[0].to(dtype=dtype, device=device)


def blur_matrix(n: int, sigma: float, taps: int, dtype: torch.dtype = torch.float32,
                device: torch.device | str = "cpu") -> torch.Tensor:
    """``(n, n)``: ``blur_matrices`` for one ``sigma``. Cached per arguments; do not modify the result in place."""
    if not sigma > 0:  # (NaN too) before the cache sees it
        raise ValueError(f"blur: size and taps must be positive, taps odd and sigma > 0, got {n}, {taps}, {sigma}")
    return _blur_matrix(int(n), float(sigma), int(taps), dtype, torch.device(device))


def gaussian_blur(x: torch.Tensor, sigma: float | torch.Tensor, taps: int) -> torch.Tensor:
    """``x (..., H, W)`` blurred by an isotropic Gaussian of ``sigma`` pixels and ``taps`` taps per axis, borders
    replicated (kornia's ``gaussian_blur2d`` with ``border_type="replicate"``). ``sigma`` is a number, or a tensor
    ``(B,)`` of one per image of ``x (B, C, H, W)``."""
    H, W = x.shape[-2:]
    if isinstance(sigma, torch.Tensor):
        if x.dim() != 4 or sigma.shape != (x.shape[0],):
            raise ValueError(f"blur: one sigma per image of a (B, C, H, W) batch, got sigma {tuple(sigma.shape)} for {tuple(x.shape)}")
        s = sigma.to(x.dtype)
        bh = blur_matrices(H, s, taps)[:, None]
        bw = bh if W == H else blur_matrices(W, s, taps)[:, None]
    else:
        bh = blur_matrix(H, sigma, taps, x.dtype, x.device)
        bw = bh if W == H else blur_matrix(W, sigma, taps, x.dtype, x.device)
    return torch.matmul(torch.matmul(bh, x), bw.transpose(-1, -2))
