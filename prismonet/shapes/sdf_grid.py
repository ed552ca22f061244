"""A shape decoder tabulated on a lattice: trilinear look-ups in place of the MLP where the shape latents
stay fixed and the same shapes are rendered many times (the test-time pose search moves, scales and turns
each slot a hundred times without changing its shape).

    grid = SdfGrid.tabulate(model.sdf_fn, z_sh.reshape(-1, D), model.prior.bounds, resolution=32)
    obj = render_objects(grid, model.color_fn, replace(params, z_sh=grid.codes.view(B, K, 1)), ...)

The grid is itself an ``SdfFn``: its "latent" is a one-number code, the row of the shape in the table, so
any renderer that passes latents through to its SDF renders from the table unchanged. Trilinear
interpolation is exact for functions affine in each coordinate (planes, tested); elsewhere its error
is the curvature's within one cell (the shipped Clevr prior at 32 nodes per axis:
``tests/test_sdf_grid.py``).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F

Box = tuple[tuple[float, float, float], tuple[float, float, float]]

TABULATE_POINTS = 1 << 18
"""SDF evaluations per decoder call while tabulating (keeps the MLP's activations a few MB)."""


@dataclass
class SdfGrid:
    """``values (N, G, G, G)``: N shapes' signed distances at the nodes of a ``G^3`` lattice spanning
    ``box`` (nodes on its faces), indexed ``[n, i_x, i_y, i_z]``."""

    values: torch.Tensor
    box: Box

    @staticmethod
    @torch.no_grad()
    def tabulate(sdf_fn, z: torch.Tensor, box: Box, resolution: int) -> "SdfGrid":
        """Evaluate ``sdf_fn(z (R, D), x (R, S, 3)) -> (R, S)`` for each row of ``z (N, D)`` at the
        ``resolution^3`` lattice nodes of ``box``."""
        if resolution < 2:
            raise ValueError(f"SdfGrid: resolution must be at least 2 nodes per axis, got {resolution}")
        axes = [torch.linspace(box[0][i], box[1][i], resolution, dtype=z.dtype, device=z.device) for i in range(3)]
        nodes = torch.stack(torch.meshgrid(*axes, indexing="ij"), -1).reshape(1, -1, 3)  # (1, G^3, 3)
        G3 = nodes.shape[1]
        rows = max(1, TABULATE_POINTS // G3)
        out = [sdf_fn(z[i : i + rows], nodes.expand(len(z[i : i + rows]), G3, 3)) for i in range(0, len(z), rows)]
        values = torch.cat(out) if out else z.new_zeros(0, G3)
        return SdfGrid(values.reshape(len(z), resolution, resolution, resolution), box)

    @property
    def resolution(self) -> int:
        return self.values.shape[-1]

    @property
    def codes(self) -> torch.Tensor:
        """``(N, 1)``: each shape's code for ``__call__``, its row in the table."""
        return torch.arange(self.values.shape[0], dtype=self.values.dtype, device=self.values.device)[:, None]

    def __call__(self, z: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
        """``z (R, 1)`` codes (from ``codes``), ``x (R, S, 3)`` object-frame points -> ``(R, S)`` signed
        distances, trilinear between the lattice nodes; points outside the box take the value at its
        nearest face (the renderer samples only inside it)."""
        N, G = self.values.shape[0], self.resolution
        lo, hi = (torch.tensor(b, dtype=x.dtype, device=x.device) for b in self.box)
        u = ((x - lo) * ((G - 1) / (hi - lo))).clamp(0, G - 1)  # (R, S, 3) in node units
        # one volume of the N tables stacked along x: a clamped point never blends two shapes' nodes
        ux = u[..., 0] + z[:, 0].round()[:, None] * G
        scale = lambda t, size: t * (2.0 / (size - 1)) - 1  # node index -> grid_sample's [-1, 1]
        g = torch.stack([scale(u[..., 2], G), scale(u[..., 1], G), scale(ux, N * G)], -1)  # (W, H, D) order
        vol = self.values.reshape(1, 1, N * G, G, G).to(x.dtype)
        out = F.grid_sample(vol, g.reshape(1, -1, 1, 1, 3), mode="bilinear", padding_mode="border", align_corners=True)
        return out.reshape(x.shape[:-1])
