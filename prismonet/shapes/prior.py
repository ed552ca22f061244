"""A shape prior: the decoder Phi, its training latents, and what they stand for.

Stored as ``NAME.safetensors`` (weights and latents) plus ``NAME.json`` (decoder config, shape
names, category and instance ids, training record). The Clevr prior ships inside the package:
``load_prior()`` with no argument loads it.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field
from importlib import resources
from pathlib import Path

import torch

from prismonet.shapes.decoder import SDFDecoder, SDFDecoderConfig
from prismonet.shapes.sdf_grid import SdfGrid

SHIPPED_PRIOR = "clevr_prior"


@dataclass
class ShapePrior:
    """Phi with the latent codes of its training shapes.

    Attributes:
        decoder: the SDF network (frozen once pre-trained).
        latents: ``(N, D)`` one code per training shape.
        shape_names: N names; ``category_ids`` / ``instance_ids``: N ints.
        info: training record (epochs, time, quality), JSON-able.
    """

    decoder: SDFDecoder
    latents: torch.Tensor
    shape_names: list[str]
    category_ids: list[int]
    instance_ids: list[int]
    info: dict = field(default_factory=dict)

    def sdf(self, z: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
        return self.decoder(z, x)

    @property
    def bounds(self) -> tuple[tuple[float, float, float], tuple[float, float, float]]:
        """Object-frame box ``(lo, hi)`` of its training shapes with their padding (``info["bounds"]``,
        written by pre-training); the padded cube for a prior without one, such as the Clevr prior."""
        from prismonet.shapes.normalize import PADDED_CUBE

        b = self.info.get("bounds")
        return (tuple(b[0]), tuple(b[1])) if b else PADDED_CUBE

    def code_extents(self) -> tuple[torch.Tensor, torch.Tensor]:
        """``(radius (N,), depth (N,))`` of the training shapes' codes (``prismonet.shapes.extents``), computed on first
        use and kept: the decoder is frozen, and a moved copy (``to``) computes its own."""
        if "_code_extents" not in self.__dict__:
            from prismonet.shapes.extents import shape_extents

            self.__dict__["_code_extents"] = shape_extents(lambda z, x: self.decoder(z[:, None, :], x), self.latents.detach(),
                                                           self.bounds)
        return self.__dict__["_code_extents"]

    def code_table(self, resolution: int) -> SdfGrid:
        """The training shapes' codes tabulated on a ``resolution``-cubed lattice of ``bounds``
        (``SdfGrid.tabulate``; the shape trials' table, ``prismonet.model.search``), computed on first use per
        resolution and kept, as ``code_extents`` is."""
        tables = self.__dict__.setdefault("_code_tables", {})
        if resolution not in tables:
            tables[resolution] = SdfGrid.tabulate(lambda z, x: self.decoder(z[:, None, :], x), self.latents.detach(),
                                                  self.bounds, resolution)
        return tables[resolution]

    def frozen(self) -> "ShapePrior":
        """Put the decoder in eval mode with gradients off for its weights (not its inputs)."""
        self.decoder.eval()
        for p in self.decoder.parameters():
            p.requires_grad_(False)
        return self

    def to(self, device: torch.device | str) -> "ShapePrior":
        """This prior on ``device``: itself if it is there already, else a moved copy (a prior may be
        shared by several models, so it is never moved in place)."""
        device = torch.device(device)
        if self.latents.device == device:
            return self
        import copy

        from dataclasses import replace

        return replace(self, decoder=copy.deepcopy(self.decoder).to(device), latents=self.latents.to(device))

    def save(self, path_stem: str | Path) -> tuple[Path, Path]:
        """Write ``<stem>.safetensors`` and ``<stem>.json`` atomically."""
        from prismonet.checkpoint import save_checkpoint

        stem = Path(path_stem)
        tensors = {f"decoder.{k}": v for k, v in self.decoder.state_dict().items()}
        tensors["latents"] = self.latents.detach()
        weights = stem.with_suffix(".safetensors")
        config = stem.with_suffix(".json")
        desc = {
            "decoder": asdict(self.decoder.cfg),
            "shape_names": self.shape_names,
            "category_ids": self.category_ids,
            "instance_ids": self.instance_ids,
            "info": self.info,
        }
        save_checkpoint(weights, tensors, {"kind": "shape_prior"})
        tmp = config.with_name(f".{config.name}.tmp")
        tmp.write_text(json.dumps(desc, indent=2))
        tmp.replace(config)
        return weights, config


def load_prior(path_stem: str | Path | None = None, frozen: bool = True) -> ShapePrior:
    """Load a prior from ``<stem>.safetensors`` + ``<stem>.json``, or a shipped one by name
    (``prismonet.assets.PRIORS``: ``"clevr"``, ``"cars"``, ...); default: the shipped Clevr prior."""
    from prismonet.assets import named_prior
    from prismonet.checkpoint import load_checkpoint

    if path_stem is None:
        stem = Path(str(resources.files("prismonet.assets").joinpath(SHIPPED_PRIOR)))
    elif named_prior(str(path_stem)) is not None:
        stem = named_prior(str(path_stem))
    else:
        stem = Path(path_stem)
        if stem.suffix in (".safetensors", ".json"):
            stem = stem.with_suffix("")
    config = stem.with_suffix(".json")
    if not config.is_file():
        raise FileNotFoundError(f"{config}: no such shape-prior config")
    desc = json.loads(config.read_text())
    tensors, _ = load_checkpoint(stem.with_suffix(".safetensors"))
    decoder = SDFDecoder(SDFDecoderConfig(**desc["decoder"]))
    decoder.load_state_dict({k[len("decoder.") :]: v for k, v in tensors.items() if k.startswith("decoder.")})
    prior = ShapePrior(decoder, tensors["latents"], desc["shape_names"], desc["category_ids"], desc["instance_ids"], desc.get("info", {}))
    return prior.frozen() if frozen else prior
