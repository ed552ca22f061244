"""Shape extents read off tabulated signed distances (``prismonet.shapes.extents``)."""

import numpy as np
import torch

from prismonet.shapes.clevr_set import clevr_shapes
from prismonet.shapes.extents import shape_extents

BOX = ((-1.1, -1.1, -1.1), (1.1, 1.1, 1.1))


def _spheres(z: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """Exact signed distances of spheres of radius ``z[:, 0]`` centred ``z[:, 1]`` above the origin."""
    c = torch.zeros_like(x)
    c[..., 2] = z[:, 1:2]
    return (x - c).norm(dim=-1) - z[:, :1]


def test_extents_of_exact_spheres():
    """A sphere of radius R centred h above the frame's origin reaches R sideways and R - h below the centre of the
    frame; with a node on the plane through its centre, the lattice reading is exact. A shape with nothing inside
    reads 0."""
    z = torch.tensor([[0.5, 0.0], [0.8, 0.0], [0.3, 0.275], [-1.0, 0.0]], dtype=torch.float64)
    radius, depth = shape_extents(_spheres, z, BOX, resolution=33)  # nodes every 2.2 / 32 = 0.06875, one at 0 and 0.275
    assert torch.allclose(radius, torch.tensor([0.5, 0.8, 0.3, 0.0], dtype=torch.float64), atol=1e-12)
    assert torch.allclose(depth, torch.tensor([0.5, 0.8, 0.3 - 0.275, 0.0], dtype=torch.float64), atol=1e-12)


def test_extents_of_the_clevr_prior_match_its_shapes(shipped):
    """The shipped prior's 27 codes against the Clevr shapes they were trained on: footprint radius and half-height
    within 0.03 (the prior's own error included)."""
    model, _, _ = shipped
    radius, depth = shape_extents(model.sdf_fn, model.prior.latents.detach(), model.prior.bounds)
    specs = clevr_shapes()
    assert np.abs(radius.numpy() - [s.footprint_radius() for s in specs]).max() < 0.03
    assert np.abs(depth.numpy() - [s.half_extents[2] for s in specs]).max() < 0.03


def test_prior_keeps_its_codes_extents(shipped):
    """``ShapePrior.code_extents`` is ``shape_extents`` of its codes, computed once (the same tensors come back)."""
    model, _, _ = shipped
    first = model.prior.code_extents()
    direct = shape_extents(model.sdf_fn, model.prior.latents.detach(), model.prior.bounds)
    assert all(torch.equal(a, b) for a, b in zip(first, direct))
    again = model.prior.code_extents()
    assert all(a is b for a, b in zip(first, again))


def test_prior_keeps_its_codes_table_per_resolution(shipped):
    """``ShapePrior.code_table`` is ``SdfGrid.tabulate`` of its codes, computed once per resolution (the same table
    comes back); another resolution is another table."""
    from prismonet.shapes.sdf_grid import SdfGrid

    model, _, _ = shipped
    first = model.prior.code_table(6)
    direct = SdfGrid.tabulate(model.sdf_fn, model.prior.latents.detach(), model.prior.bounds, 6)
    assert torch.equal(first.values, direct.values) and first.box == direct.box
    assert model.prior.code_table(6) is first
    assert model.prior.code_table(5).values.shape == (27, 5, 5, 5)
