"""Making self-distillation targets: the trained model's test-time steps (``InferenceConfig``) run on
training scenes, their fitted slots saved in chunks (the format and the loss: ``prismonet.model.distill``).
Kept apart from the loss, which the training losses import, so that the loss never imports the
test-time steps (which import the training losses)."""

from __future__ import annotations

import json
import sys
from dataclasses import asdict
from pathlib import Path

import torch

from prismonet import threads
from prismonet.files import write_atomic
from prismonet.model import distill
from prismonet.model.distill import FIELDS, DistillError


def weights_digest(model, skip: str | None = None) -> str:
    """SHA-256 (first 16 hex digits) of a model's weights: targets made by different weights never mix,
    even under one name (``shipped`` changes when a new model ships). ``skip``: leave out the weights whose names
    start with it."""
    import hashlib

    h = hashlib.sha256()
    for name, t in sorted(model.state_dict().items()):
        if skip is not None and name.startswith(skip):
            continue
        h.update(name.encode())
        h.update(t.detach().contiguous().cpu().numpy().tobytes())
    return h.hexdigest()[:16]


def encoder_digest(model) -> str:
    """``weights_digest`` of the model without its refinement pass: equal to the digest of the model the refiner was
    fitted on, so targets made by a refined model can be matched to its encoder."""
    return weights_digest(model, skip="refiner.")


def true_pose_search(cfg):
    """``cfg`` (an ``InferenceConfig``) with the search's pose trials off (scale 1 only, no shifts, no yaws): its shape
    trials and the colour fit are what remain, for targets at the true poses (``fit_targets(..., true_poses=True)``)."""
    from dataclasses import replace

    return replace(cfg, search=replace(cfg.search, scales=(1.0,), shifts=(), yaws=()))


def fit_targets(model, ds, out_dir: str | Path, count: int, cfg, batch_size: int = 16,
                progress: bool = True, meta: dict | None = None, loss_cfg=None, true_poses: bool = False,
                device: torch.device | str = "cpu", lane: tuple[int, int] = (0, 1)) -> dict:
    """Fit targets for scenes ``0 .. count-1`` of ``ds`` into ``out_dir`` (resumable) with the
    test-time steps of ``cfg`` (an ``InferenceConfig`` without extra slots: slot k must stay encoder
    step k; ``loss_cfg``: the training losses any refinement uses). ``distill.CHUNK`` scenes a file.

    ``true_poses`` (the + 3D pose variant, supervised): the steps start from the encoder's slots put on the scenes'
    true poses (``pose_targets.start_at_truth``; a slot no object takes is hidden), so that what they fit (shape
    trials, colours) is fitted at the truth. The search's pose trials must then be off (``true_pose_search``).

    ``lane = (i, n)``: fit only chunks ``i, i + n, i + 2n, ...`` (0 <= i < n), so that n processes of one thread each
    fill one folder side by side (on a 2-core CPU a chunk took 90 s on one thread and 94 s on two, EVALUATION.md's
    session 100, so two one-thread lanes make targets about twice as fast); interleaved, the lanes' finished chunks
    make one unbroken prefix of scenes, which is what ``DistillTargets`` reads when a run is stopped early. A chunk
    another lane finished is skipped. Returns a summary."""
    from tqdm import tqdm

    from prismonet.checkpoint import save_checkpoint
    from prismonet.model.fit_score import fit_score
    from prismonet.model.inference import infer

    if cfg.extra_slots:
        raise DistillError("distillation targets keep encoder order (slot k is step k): extra slots cannot be used")
    if cfg.reseed.grow:
        raise DistillError("--reseed-grow cannot make distillation targets: the targets hold one row per slot of the model")
    periods = None
    if true_poses:
        from prismonet.model.pose_targets import start_at_truth, yaw_periods_of

        if cfg.search.trials_per_slot:
            raise DistillError("--true-poses: the poses are given, so the search may only try shapes (no scale, shift or yaw trials)")
        periods = yaw_periods_of(ds)
    if not (0 <= lane[0] < lane[1]):
        raise DistillError(f"lane must be I of N with 0 <= I < N, got {lane[0]} of {lane[1]}")
    if not 0 < count <= len(ds):
        raise DistillError(f"count must be in 1..{len(ds)} (the split's scenes), got {count}")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    info = {"count": count, "chunk": distill.CHUNK, "num_slots": model.cfg.num_slots, "search": asdict(cfg.search),
            "color_fit": asdict(cfg.color_fit), **(meta or {})}
    if cfg.refine.steps:  # recorded only when used, so targets made before these settings existed still resume
        info["refine"] = asdict(cfg.refine)
    if cfg.reseed.rounds:
        info["reseed"] = asdict(cfg.reseed)
    if not cfg.use_depth:
        info["use_depth"] = False
    if true_poses:
        info["true_poses"] = True
    info_path = out / "targets.json"
    if info_path.is_file():
        old = json.loads(info_path.read_text())
        if isinstance(old.get("search"), dict):  # search settings added since those targets were made: at their defaults
            from prismonet.model.search import SearchConfig

            old["search"] = {**json.loads(json.dumps(asdict(SearchConfig(rounds=old["search"].get("rounds", 0))))), **old["search"]}
        if {k: v for k, v in old.items() if k != "count"} != {k: v for k, v in json.loads(json.dumps(info)).items() if k != "count"}:
            raise DistillError(f"{out}: holds targets made with other settings; use a new folder")
    write_atomic(info_path, json.dumps(info, indent=1))  # a temporary file per process: lanes write it side by side
    model.to(device).eval()
    before, after = [], []
    chunks = range(0, count, distill.CHUNK)[lane[0]::lane[1]]
    # shape codes are targets only when the search could change them (else they would anchor the encoder to its own)
    shapes = cfg.search.rounds > 0 and (cfg.search.shape_trials or cfg.search.shape_nearest > 0)
    fields = (*FIELDS, distill.VISIBLE, *((distill.SHAPE,) if shapes else ()))
    for c0 in tqdm(chunks, desc="distillation targets", unit="chunk", disable=not progress):
        path = out / f"chunk_{c0 // distill.CHUNK:05d}.safetensors"
        if path.is_file():
            continue
        n = threads.follow_load()  # a run of hours takes the cores that other work frees (or leaves them to it)
        if n is not None:
            print(f"prismonet: the machine's load changed: running on {n} thread{'s' * (n > 1)}", file=sys.stderr)
        rows: dict[str, list[torch.Tensor]] = {k: [] for k in fields}
        for s in range(c0, min(c0 + distill.CHUNK, count), batch_size):
            b = ds.batch(list(range(s, min(s + batch_size, c0 + distill.CHUNK, count)))).to(device)

            def score_encoder(name, o, b=b):
                if name == "encoder":
                    before.append(fit_score(o.composite.image, o.composite.depth, b.rgb, b.depth))

            start = None if periods is None else (lambda o, b=b: start_at_truth(model, o, b, periods))
            o = infer(model, b, cfg, loss_cfg, on_step=score_encoder, start=start)
            with torch.no_grad():
                after.append(fit_score(o.composite.image, o.composite.depth, b.rgb, b.depth))
            p = o.latents.params
            K = p.scale.shape[1]
            won = torch.stack([(o.composite.instance == k + 1).flatten(1).sum(1) for k in range(K)], 1)  # (B, K) pixels
            for k, v in (("scale", p.scale), ("position", p.position), ("cos_sin", p.cos_sin), ("z_tex", p.z_tex),
                         ("bg_color", o.latents.bg_color), (distill.VISIBLE, won), (distill.SHAPE, p.z_sh)):
                if k in rows:
                    rows[k].append(v.detach().float().cpu())
        save_checkpoint(path, {k: torch.cat(v) for k, v in rows.items()}, {"first": c0})
    summary = {"scenes": count, "chunks": len(chunks)}
    if before:
        summary.update(score_before=float(torch.cat(before).mean()), score_after=float(torch.cat(after).mean()))
    return summary
