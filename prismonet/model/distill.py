"""Self-distillation (beyond the paper, still weakly supervised): the encoder learns to output in one
pass what the test-time pose search and colour fit reach.

1. ``fit_targets``: run the trained model on *training* scenes, then the pose search (against their
   RGB-D) and the colour fit (against their RGB), exactly as ``evaluate --search R --fit-color K``
   does on test scenes. Only the input RGB-D enters; no pose, mask or instance label is read.
   The fitted scale, position, yaw, texture latents and background colour of every slot are the
   targets. Slots keep their order (slot k is encoder step k), so step k learns step k's fit.
2. ``distill_loss``: a regression of the encoder's decoded slots onto those targets, added to the
   paper's losses with weight ``LossConfig.w_distill`` (``TrainConfig.distill`` names the targets).

Targets are written in chunks of ``CHUNK`` scenes, each atomically (``chunk_NNNNN.safetensors``), so
an interrupted run resumes at the first missing chunk and the files of a finished chunk never change.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass
from pathlib import Path

import torch

CHUNK = 256
"""Scenes per target file."""

FIELDS = ("scale", "position", "cos_sin", "z_tex", "bg_color")


class DistillError(ValueError):
    """Targets that are missing, malformed or made for another model or dataset."""


@dataclass(frozen=True)
class DistillWeights:
    """Weights of the distillation terms inside ``distill_loss`` (each a mean over slots)."""

    position: float = 1.0
    """L1 of world positions (x, y, z summed)."""
    scale: float = 1.0
    """L1 of scales."""
    rotation: float = 0.5
    """1 - cos of the yaw difference."""
    texture: float = 0.1
    """Squared L2 of texture latents."""
    background: float = 1.0
    """L1 of the background colour (RGB summed)."""


def weights_digest(model) -> str:
    """SHA-256 (first 16 hex digits) of a model's weights: targets made by different weights never mix,
    even under one name (``shipped`` changes when a new model ships)."""
    import hashlib

    h = hashlib.sha256()
    for name, t in sorted(model.state_dict().items()):
        h.update(name.encode())
        h.update(t.detach().contiguous().cpu().numpy().tobytes())
    return h.hexdigest()[:16]


def fit_targets(model, ds, out_dir: str | Path, count: int, search_cfg, color_cfg, batch_size: int = 16,
                progress: bool = True, meta: dict | None = None) -> dict:
    """Fit targets for scenes ``0 .. count-1`` of ``ds`` into ``out_dir`` (resumable). Returns a summary."""
    from tqdm import tqdm

    from prismonet.checkpoint import save_checkpoint
    from prismonet.model.color_fit import fit_colors
    from prismonet.model.fit_score import fit_score
    from prismonet.model.search import search_latents

    if not 0 < count <= len(ds):
        raise DistillError(f"count must be in 1..{len(ds)} (the split's scenes), got {count}")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    info = {"count": count, "chunk": CHUNK, "num_slots": model.cfg.num_slots, "search": asdict(search_cfg),
            "color_fit": asdict(color_cfg), **(meta or {})}
    info_path = out / "targets.json"
    if info_path.is_file():
        old = json.loads(info_path.read_text())
        if {k: v for k, v in old.items() if k != "count"} != {k: v for k, v in json.loads(json.dumps(info)).items() if k != "count"}:
            raise DistillError(f"{out}: holds targets made with other settings; use a new folder")
    tmp = info_path.with_suffix(".json.tmp")
    tmp.write_text(json.dumps(info, indent=1))
    tmp.replace(info_path)
    model.eval()
    before, after = [], []
    chunks = range(0, count, CHUNK)
    for c0 in tqdm(chunks, desc="distillation targets", unit="chunk", disable=not progress):
        path = out / f"chunk_{c0 // CHUNK:05d}.safetensors"
        if path.is_file():
            continue
        rows: dict[str, list[torch.Tensor]] = {k: [] for k in FIELDS}
        for s in range(c0, min(c0 + CHUNK, count), batch_size):
            b = ds.batch(list(range(s, min(s + batch_size, c0 + CHUNK, count))))
            with torch.no_grad():
                o = model(b.rgb, b.K, b.T_world_cam, b.ground_z)
                before.append(fit_score(o.composite.image, o.composite.depth, b.rgb, b.depth))
                o = search_latents(model, o, b, search_cfg)
            o = fit_colors(model, o, b, color_cfg)
            with torch.no_grad():
                after.append(fit_score(o.composite.image, o.composite.depth, b.rgb, b.depth))
            p = o.latents.params
            for k, v in (("scale", p.scale), ("position", p.position), ("cos_sin", p.cos_sin), ("z_tex", p.z_tex),
                         ("bg_color", o.latents.bg_color)):
                rows[k].append(v.detach().float())
        save_checkpoint(path, {k: torch.cat(v) for k, v in rows.items()}, {"first": c0})
    summary = {"scenes": count, "chunks": len(chunks)}
    if before:
        summary.update(score_before=float(torch.cat(before).mean()), score_after=float(torch.cat(after).mean()))
    return summary


class DistillTargets:
    """Targets of scenes ``0 .. count-1`` (``fit_targets``'s folder), looked up by scene index."""

    def __init__(self, path: str | Path, num_slots: int) -> None:
        from prismonet.checkpoint import load_checkpoint

        root = Path(path)
        info_path = root / "targets.json"
        if not info_path.is_file():
            raise DistillError(f"{root}: no distillation targets here (targets.json); make them with `prismonet distill`")
        info = json.loads(info_path.read_text())
        if info.get("num_slots") != num_slots:
            raise DistillError(f"{root}: targets for {info.get('num_slots')} slots, the model has {num_slots}")
        parts: dict[str, list[torch.Tensor]] = {k: [] for k in FIELDS}
        for i in range(0, info["count"], info["chunk"]):
            f = root / f"chunk_{i // info['chunk']:05d}.safetensors"
            if not f.is_file():
                break  # an unfinished run: use the chunks that are complete
            tensors, _ = load_checkpoint(f)
            for k in FIELDS:
                parts[k].append(tensors[k])
        if not parts["scale"]:
            raise DistillError(f"{root}: no finished chunk of targets yet")
        self.t = {k: torch.cat(v) for k, v in parts.items()}
        self.count = len(self.t["scale"])

    def lookup(self, indices: torch.Tensor) -> tuple[dict[str, torch.Tensor], torch.Tensor]:
        """Targets of scenes ``indices`` (zeros where there are none) and a ``(B,)`` float mask of those that have them."""
        have = indices < self.count
        safe = torch.where(have, indices, torch.zeros_like(indices))
        return {k: v[safe] for k, v in self.t.items()}, have.float()


def distill_loss(params, bg_color: torch.Tensor, targets: dict[str, torch.Tensor], mask: torch.Tensor,
                 w: DistillWeights = DistillWeights()) -> torch.Tensor:
    """``()``: the weighted regression of the decoded slots onto their targets, mean over the scenes
    that have targets (``mask``); 0 when none has."""
    cs = params.cos_sin / params.cos_sin.norm(dim=-1, keepdim=True).clamp_min(1e-6)
    ct = targets["cos_sin"] / targets["cos_sin"].norm(dim=-1, keepdim=True).clamp_min(1e-6)
    per_scene = (
        w.position * (params.position - targets["position"]).abs().sum(-1).mean(1)
        + w.scale * (params.scale - targets["scale"]).abs().mean(1)
        + w.rotation * (1 - (cs * ct).sum(-1)).mean(1)
        + w.texture * ((params.z_tex - targets["z_tex"]) ** 2).sum(-1).mean(1)
        + w.background * (bg_color - targets["bg_color"]).abs().sum(-1)
    )
    return (per_scene * mask).sum() / mask.sum().clamp_min(1.0)
