"""Pre-training the DeepSDF auto-decoder on a shape set (``prismonet shapes pretrain``).

One latent code per training shape is optimised jointly with Phi under DeepSDF's clamped L1 loss
and code regularisation, with Adam and a separate learning rate for the codes. Every step sees
all shapes, each with ``points_per_shape`` of its cached SDF samples.

Checkpoints (``checkpoint.safetensors``: weights, codes, Adam moments, epoch) are written
atomically every ``checkpoint_every`` epochs; a rerun with the same config resumes from the last
one. The sampling order of epoch ``e`` depends only on ``(seed, e)``, so a resumed run ends with
the same weights as an uninterrupted one.
"""

from __future__ import annotations

import json
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import torch

from prismonet.shapes.decoder import SDFDecoder, SDFDecoderConfig
from prismonet.shapes.normalize import shape_bounds
from prismonet.shapes.sdf_samples import SamplingConfig, cached_sdf_samples


@dataclass(frozen=True)
class PretrainConfig:
    """Settings of shape-prior pre-training."""

    decoder: SDFDecoderConfig = field(default_factory=SDFDecoderConfig)
    sampling: SamplingConfig = field(default_factory=SamplingConfig)
    epochs: int = 300
    """Passes over every shape's samples (the paper: 10K; small sets converge far sooner)."""
    points_per_shape: int = 2048
    """Samples of each shape per step; an epoch is ``num_points / points_per_shape`` steps.
    2048 keeps each activation buffer under 32 MB (glibc maps larger ones afresh every step)."""
    lr_decoder: float = 2e-3
    lr_codes: float = 4e-3
    lr_final_ratio: float = 0.02
    """Both learning rates decay by cosine to this fraction of their start."""
    clamp_delta: float = 0.1
    """DeepSDF's clamp: the L1 loss compares SDF values clamped to [-delta, delta]."""
    code_reg: float = 1e-4
    """Weight of the mean code norm, ramped in over the first ``code_reg_ramp`` epochs (DeepSDF)."""
    code_reg_ramp: int = 100
    code_init_std: float = 0.1
    seed: int = 0
    checkpoint_every: int = 1
    """Epochs between checkpoints; one costs milliseconds, so a kill loses at most one epoch."""
    threads: int = 2
    init: str | None = None
    """A prior to start from (a shipped prior's name or a path stem): its decoder weights and codes, instead of a
    fresh start. It must have this config's decoder and the same shapes in the same order; ``None``: from scratch."""


class PriorInitError(ValueError):
    """The prior given as ``init`` does not fit the run: another decoder, or other shapes."""


@dataclass(frozen=True)
class ShapeSet:
    """Training meshes (vertices, faces) with their names, category ids and instance ids."""

    name: str
    meshes: tuple[tuple[np.ndarray, np.ndarray], ...]
    names: tuple[str, ...]
    category_ids: tuple[int, ...]
    instance_ids: tuple[int, ...]


def load_shape_set(name: str = "clevr", split: str = "seen") -> ShapeSet:
    """A shape set: ``"clevr"`` (the 27 Clevr shapes), or a folder of imported meshes
    (``prismonet.shapes.furniture``: ``models.json`` + PLYs) whose ``split`` models it takes."""
    from prismonet.shapes.clevr_set import clevr_shapes, shape_mesh

    if name != "clevr":
        if (Path(name) / "models.json").is_file():
            return _imported_set(Path(name), split)
        raise ValueError(f"unknown shape set {name!r}; expected 'clevr' or a folder made by 'shapes import-furniture'")
    specs = clevr_shapes()
    return ShapeSet(
        name,
        tuple(shape_mesh(s.shape_id) for s in specs),
        tuple(f"{s.category}_{s.instance_id}" for s in specs),
        tuple(s.category_id for s in specs),
        tuple(s.instance_id for s in specs),
    )


def _imported_set(folder: Path, split: str) -> ShapeSet:
    """The ``split`` models of an imported folder (``prismonet.shapes.library``)."""
    from prismonet.shapes.library import shape_library

    lib = shape_library(str(folder), split)
    return ShapeSet(f"{json.loads((folder / 'models.json').read_text())['setting']}:{split}",
                    tuple(lib.mesh(s.shape_id) for s in lib.specs), tuple(Path(f).stem for f in lib.files),
                    tuple(s.category_id for s in lib.specs), tuple(s.instance_id for s in lib.specs))


def clamped_l1(pred: torch.Tensor, target: torch.Tensor, delta: float) -> torch.Tensor:
    return (pred.clamp(-delta, delta) - target.clamp(-delta, delta)).abs().mean()


RESUME_IGNORED = ("checkpoint_every", "threads")
"""Config fields that do not change the result, so a run may resume with other values."""


def _init_prior(cfg: PretrainConfig, names: list[str]):
    """``cfg.init`` loaded and checked against the run (its decoder and shapes), or ``None`` without one."""
    from prismonet.shapes.prior import load_prior

    if cfg.init is None:
        return None
    init = load_prior(cfg.init, frozen=False)
    if asdict(init.decoder.cfg) != asdict(cfg.decoder):
        raise PriorInitError(f"init prior {cfg.init!r}: decoder {asdict(init.decoder.cfg)} differs from the config's {asdict(cfg.decoder)}")
    if list(init.shape_names) != list(names):
        raise PriorInitError(f"init prior {cfg.init!r}: trained on other shapes ({len(init.shape_names)}) than this set ({len(names)}), "
                             "or in another order")
    return init


def _lr_factor(cfg: PretrainConfig, epoch: int) -> float:
    t = min(epoch / max(cfg.epochs, 1), 1.0)
    return cfg.lr_final_ratio + (1 - cfg.lr_final_ratio) * 0.5 * (1 + np.cos(np.pi * t))


def pretrain(
    cfg: PretrainConfig,
    out_dir: str | Path,
    shape_set: str | ShapeSet = "clevr",
    cache_dir: str | Path | None = None,
    progress: bool = True,
    stop_after_epoch: int | None = None,
):
    """Pre-train Phi; returns the ``ShapePrior``. Resumes from ``out_dir/checkpoint.safetensors``.

    Args:
        cfg: settings.
        out_dir: run folder (checkpoint, final prior ``prior.safetensors`` + ``prior.json``).
        shape_set: a ``ShapeSet`` or the name of one (``"clevr"``).
        cache_dir: SDF-sample cache; default ``out_dir/sdf_samples``.
        progress: show a progress bar.
        stop_after_epoch: stop (with a checkpoint) after this epoch, as a kill would; for tests.
    """
    from tqdm import tqdm

    from prismonet.checkpoint import load_checkpoint, load_optimizer, optimizer_tensors, resume_key, save_checkpoint
    from prismonet.shapes.prior import ShapePrior

    torch.set_num_threads(cfg.threads)
    shapes = load_shape_set(shape_set) if isinstance(shape_set, str) else shape_set
    meshes, names, cats, insts = shapes.meshes, list(shapes.names), list(shapes.category_ids), list(shapes.instance_ids)
    init = _init_prior(cfg, names)  # checked before any folder or sample is made
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    cache = out / "sdf_samples" if cache_dir is None else Path(cache_dir)
    samples = [
        cached_sdf_samples(v, f, cfg.sampling, seed=cfg.seed * 1000 + i, cache_dir=cache, name=n)
        for i, ((v, f), n) in enumerate(tqdm(list(zip(meshes, names)), desc="SDF samples", disable=not progress))
    ]
    points = torch.from_numpy(np.stack([s[0] for s in samples]))  # (S, N, 3)
    sdf = torch.from_numpy(np.stack([s[1] for s in samples]))  # (S, N)
    S, N = sdf.shape
    if cfg.points_per_shape > N:
        raise ValueError(f"points_per_shape ({cfg.points_per_shape}) exceeds the samples per shape ({N})")

    torch.manual_seed(cfg.seed)
    decoder = SDFDecoder(cfg.decoder)
    codes = torch.nn.Parameter(torch.randn(S, cfg.decoder.latent_dim, generator=torch.Generator().manual_seed(cfg.seed)) * cfg.code_init_std)
    opt = torch.optim.Adam([{"params": decoder.parameters(), "lr": cfg.lr_decoder}, {"params": [codes], "lr": cfg.lr_codes}])
    base_lrs = [cfg.lr_decoder, cfg.lr_codes]

    ckpt_path = out / "checkpoint.safetensors"
    start_epoch, elapsed = 0, 0.0
    if init is not None and not ckpt_path.is_file():
        decoder.load_state_dict(init.decoder.state_dict())
        with torch.no_grad():
            codes.copy_(init.latents)
    if ckpt_path.is_file():
        tensors, meta = load_checkpoint(ckpt_path)
        if resume_key(meta.get("config", {}), RESUME_IGNORED) != resume_key(json.loads(json.dumps(asdict(cfg))), RESUME_IGNORED) or meta.get("shape_set") != shapes.name:
            raise ValueError(f"{ckpt_path}: was written with another config or shape set; use a new --out folder")
        decoder.load_state_dict({k[8:]: v for k, v in tensors.items() if k.startswith("decoder.")})
        with torch.no_grad():
            codes.copy_(tensors["codes"])
        load_optimizer(opt, tensors, meta["optimizer"])
        start_epoch, elapsed = meta["epoch"] + 1, meta["elapsed_s"]

    def save(epoch: int) -> None:
        tensors, desc = optimizer_tensors(opt)
        tensors.update({f"decoder.{k}": v for k, v in decoder.state_dict().items()})
        tensors["codes"] = codes.detach()
        save_checkpoint(ckpt_path, tensors, {"config": asdict(cfg), "shape_set": shapes.name, "epoch": epoch, "elapsed_s": elapsed, "optimizer": desc})

    steps = N // cfg.points_per_shape
    bar = tqdm(range(start_epoch, cfg.epochs), desc="pretrain", unit="epoch", disable=not progress, initial=start_epoch, total=cfg.epochs)
    loss_value = float("nan")
    for epoch in bar:
        t0 = time.perf_counter()
        for g, lr in zip(opt.param_groups, base_lrs):
            g["lr"] = lr * _lr_factor(cfg, epoch)
        perm = torch.argsort(torch.rand(S, N, generator=torch.Generator().manual_seed(cfg.seed * 100003 + epoch)), dim=1)
        reg_w = cfg.code_reg * min(1.0, epoch / max(cfg.code_reg_ramp, 1))
        for s in range(steps):
            idx = perm[:, s * cfg.points_per_shape : (s + 1) * cfg.points_per_shape]
            x = torch.gather(points, 1, idx[..., None].expand(-1, -1, 3))
            y = torch.gather(sdf, 1, idx)
            pred = decoder(codes[:, None, :], x)
            loss = clamped_l1(pred, y, cfg.clamp_delta) + reg_w * codes.norm(dim=-1).mean()
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            loss_value = loss.item()
        elapsed += time.perf_counter() - t0
        bar.set_postfix(loss=f"{loss_value:.4f}")
        last = epoch == cfg.epochs - 1
        if (epoch + 1) % cfg.checkpoint_every == 0 or last or epoch == stop_after_epoch:
            save(epoch)
        if epoch == stop_after_epoch:
            break
    bar.close()
    info = {"shape_set": shapes.name, "epochs": cfg.epochs, "train_seconds": round(elapsed, 1), "final_loss": loss_value, "config": asdict(cfg),
            "bounds": shape_bounds(meshes)}
    prior = ShapePrior(decoder, codes.detach().clone(), names, cats, insts, info)
    if stop_after_epoch is None or stop_after_epoch >= cfg.epochs - 1:
        prior.save(out / "prior")
    return prior
