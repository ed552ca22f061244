"""Training the colour step (``prismonet.model.color_step``) photometrically, the rest of the model frozen.

1. The trained model decodes the training scenes once, feed-forward with its refinement passes (``geometry_cache``):
   its composite, instance ids, slot silhouettes and latents, and per pixel the slot whose surface wins the z-buffer
   and that surface point in the object's frame. Only the input RGB is read; no mask, pose or depth.
2. The colour step moves each slot's texture latent; the texture field, evaluated at the cached winning points, recolours
   the composite, and the loss is each scene's log mean squared colour error against the input image, averaged over
   the scenes: PSNR's own objective (``-10 log10 MSE``). No ray is cast, so a step costs a few tens of milliseconds.
3. The last ``holdout`` scenes are held out: their PSNR is logged beside the model's own, so a run shows what it gains
   on scenes it did not fit.

Resumable: ``RUN/checkpoint.safetensors`` (colour step, Adam, step) is written atomically every ``checkpoint_every``
steps; rerunning the same command resumes. The result is a whole scene model, ``RUN/model.safetensors`` +
``RUN/model.json`` (every weight of the base model, and the colour step's).
"""

from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import torch

from prismonet.model.io import rebuilt


class ColorStepError(ValueError):
    """A colour-step run that cannot go on as asked (one clear line)."""


@dataclass(frozen=True)
class ColorStepFitConfig:
    """One colour-step training run."""

    steps: int = 3000
    batch_size: int = 32
    """Scenes per step."""
    lr: float = 1e-3
    """Adam; a linear warm-up from 4 % of it over the first ``warmup`` of the steps, then a cosine down to 1 % at
    ``steps``."""
    warmup: float = 0.05
    weight_decay: float = 0.0
    holdout: int = 256
    """The last cached scenes, held out for the logged PSNR."""
    seed: int = 0
    checkpoint_every: int = 250

    def __post_init__(self) -> None:
        if (self.steps <= 0 or self.batch_size <= 0 or self.lr <= 0 or self.holdout < 0 or self.checkpoint_every <= 0
                or self.weight_decay < 0 or not 0 <= self.warmup < 1):
            raise ValueError("colour step fit: steps, batch_size, lr and checkpoint_every must be positive, holdout and weight_decay "
                             f">= 0 and warmup in [0, 1), got {self.steps}, {self.batch_size}, {self.lr}, {self.checkpoint_every}, "
                             f"{self.holdout}, {self.weight_decay}, {self.warmup}")


def learning_rate(cfg: ColorStepFitConfig, step: int) -> float:
    """The step size at ``step``: ``warmup`` of the run rising linearly from 4 % to ``lr``, then a cosine to 1 %."""
    ramp = cfg.warmup * cfg.steps
    if step < ramp:
        return cfg.lr * (0.04 + 0.96 * step / ramp)
    t = (step - ramp) / max(cfg.steps - ramp, 1e-9)
    return cfg.lr * (0.01 + 0.99 * 0.5 * (1 + math.cos(math.pi * t)))


def with_color_step(model, channels: tuple[int, ...] | None = None, fc: tuple[int, ...] | None = None,
                    passes: int | None = None):
    """A copy of a trained scene model with a fresh (identity) colour step of ``passes`` passes; every other weight is
    kept. A colour step the model already has is replaced."""
    fields = {"color_step": True}
    if passes is not None:
        fields["color_step_passes"] = int(passes)
    if channels is not None:
        fields["color_step_channels"] = tuple(channels)
    if fc is not None:
        fields["color_step_fc"] = tuple(fc)
    return rebuilt(model, "color_step.", **fields)


def without_color_step(model):
    """A copy of a scene model without its colour step (``color_step`` off, ``color_step_passes`` back to 1; the other
    weights shared as they are): the model as it was before the step was fitted, bit for bit."""
    return rebuilt(model, "color_step.", color_step=False, color_step_passes=1).train(model.training)


@torch.no_grad()
def geometry_cache(model, ds, count: int, batch_size: int = 64, progress: bool = True) -> dict[str, torch.Tensor]:
    """The model's feed-forward decoding (refinement passes included, no colour step) of scenes ``0 .. count-1`` of
    ``ds``: what the colour step sees (composite colour, instance ids, slot silhouettes, latents) and what it recolours
    (``winner``: the slot whose surface each pixel shows, -1 for the ground; ``x_obj``: that surface point in the
    slot's frame, float16), with the image as uint8."""
    from tqdm import tqdm

    from prismonet.render.composite import zbuffer
    from prismonet.render.renderer import render_objects, winning_hits

    model.eval()
    keys = ("comp", "instance", "obj_mask", "z_sh", "z_tex", "position", "cos_sin", "scale", "active", "bg_color", "winner", "x_obj", "rgb")
    rows: dict[str, list[torch.Tensor]] = {k: [] for k in keys}
    for s in tqdm(range(0, count, batch_size), desc="geometry", unit="batch", disable=not progress):
        b = ds.batch(list(range(s, min(s + batch_size, count))))
        out = model(b.rgb, b.K, b.T_world_cam, b.ground_z, recolor=False)
        p = out.latents.params
        B, N = p.scale.shape
        H, W = b.rgb.shape[-2:]
        obj = out.render
        if obj is None:
            obj = render_objects(model.sdf_fn, None, p, b.K, b.T_world_cam, H, W, model.render_settings())
        winner, hit = zbuffer(obj.depth, obj.mask)
        bi, won = winning_hits(obj, winner, hit)
        x_obj = torch.zeros(B * H * W, 3, dtype=obj.hit_x_obj.dtype)
        x_obj[bi[won] * H * W + obj.hit_pix[won]] = obj.hit_x_obj[won]
        rows["comp"].append(out.composite.image.half())
        rows["instance"].append(out.composite.instance.to(torch.uint8))
        rows["obj_mask"].append(out.obj_mask)
        for name in ("z_sh", "z_tex", "position", "cos_sin", "scale"):
            rows[name].append(getattr(p, name))
        rows["active"].append(p.active if p.active is not None else torch.ones(B, N, dtype=torch.bool))
        rows["bg_color"].append(out.latents.bg_color)
        rows["winner"].append(torch.where(hit, winner, torch.full_like(winner, -1)).reshape(B, H * W).to(torch.int8))
        rows["x_obj"].append(x_obj.reshape(B, H * W, 3).half())
        rows["rgb"].append((b.rgb * 255).round().to(torch.uint8))
    return {k: torch.cat(v) for k, v in rows.items()}


def recolored(model, cache: dict[str, torch.Tensor], idx: torch.Tensor, z_tex: torch.Tensor) -> torch.Tensor:
    """``(B, H*W, 3)`` the cached scenes ``idx`` recoloured with texture latents ``z_tex (B, N, D)``: the texture field at
    each pixel's winning surface point, the background colour elsewhere."""
    winner = cache["winner"][idx].long()
    B, HW = winner.shape
    image = cache["bg_color"][idx][:, None, :].expand(B, HW, 3).clone()
    shown = winner >= 0
    rows = torch.arange(B)[:, None].expand(B, HW)[shown]
    rgb = model.color_fn(z_tex[rows, winner[shown]], cache["x_obj"][idx][shown].to(z_tex.dtype))
    return image.index_put((shown,), rgb)


def scene_mse(cache: dict[str, torch.Tensor], idx: torch.Tensor, image: torch.Tensor) -> torch.Tensor:
    """``(B,)`` each scene's mean squared colour error (over pixels and channels, images in [0, 1])."""
    truth = cache["rgb"][idx].to(image.dtype).div(255).flatten(2).transpose(1, 2)
    return ((image - truth) ** 2).mean((1, 2))


def _step_latents(model, cache, ds, idx: torch.Tensor) -> torch.Tensor:
    """``(B, N, D)`` the cached texture latents of scenes ``idx`` moved by the colour step, each of its
    ``color_step_passes`` passes seeing the image the pass before it made (``PriSMONet.recolor``)."""
    from prismonet.render import SceneParams

    params = SceneParams(*(cache[k][idx] for k in ("z_sh", "z_tex", "position", "cos_sin", "scale")))
    b = ds.batch(idx.tolist())
    B, N = params.scale.shape
    H, W = b.rgb.shape[-2:]
    comp = cache["comp"][idx].float()
    for i in range(model.cfg.color_step_passes):
        if i > 0:
            comp = recolored(model, cache, idx, params.z_tex).transpose(1, 2).reshape(B, 3, H, W)
        step = model.on_slots(model.color_step, b.rgb, comp, cache["instance"][idx].long(), cache["obj_mask"][idx], params,
                              b.K, b.T_world_cam, cache["active"][idx]).reshape(B, N, -1)
        params = replace(params, z_tex=params.z_tex + step)
    return params.z_tex


def held_out_psnr(model, cache, ds, idx: torch.Tensor, batch: int = 128, step: bool = True) -> float:
    """Mean PSNR over the scenes ``idx`` recoloured by the colour step (``step``) or as the model left them."""
    model.color_step.eval()
    got = []
    with torch.no_grad():
        for i in range(0, len(idx), batch):
            j = idx[i:i + batch]
            z = _step_latents(model, cache, ds, j) if step else cache["z_tex"][j]
            got.append(-10 * torch.log10(scene_mse(cache, j, recolored(model, cache, j, z)).double().clamp_min(1e-12)))
    model.color_step.train()
    return float(torch.cat(got).mean()) if got else math.nan


def fit_color_step(model, ds, count: int, out_dir: str | Path, cfg: ColorStepFitConfig = ColorStepFitConfig(),
                   info: dict | None = None, progress: bool = True) -> dict:
    """Train ``model``'s colour step (``model.cfg.color_step``; see ``with_color_step``) on scenes ``0 .. count-1`` of
    ``ds`` (a training split: only their images are read), then save the whole model in ``out_dir``. ``info``: the base
    model's record. Returns a summary."""
    from prismonet.checkpoint import resume_part, save_part
    from prismonet.model.part_fit import append_row, batch_indices, fit_steps, read_rows
    from prismonet.model.io import save_model

    if not model.cfg.color_step:
        raise ColorStepError("the model has no colour step (color_step false): start from with_color_step(model)")
    count = min(count, len(ds))
    if count <= cfg.holdout:
        raise ColorStepError(f"{count} scenes: need more than the {cfg.holdout} held out")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    fit = {k: v for k, v in asdict(cfg).items() if k != "steps"}  # ``steps`` may change when a run resumes
    record = {"fit": fit, "scenes": count, "data": str(getattr(ds, "path", "")),
              "channels": list(model.cfg.color_step_channels), "fc": list(model.cfg.color_step_fc),
              "passes": model.cfg.color_step_passes}
    ckpt = out / "checkpoint.safetensors"
    for q in model.parameters():
        q.requires_grad_(False)
    for q in model.color_step.parameters():
        q.requires_grad_(True)
    opt = torch.optim.AdamW(model.color_step.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    step = resume_part(ckpt, "color_step.", model.color_step, opt, record, ColorStepError)
    # a finished run resumed has no step left to take: no cache to make (minutes of decoding)
    cache = geometry_cache(model, ds, count, progress=progress) if not 0 < cfg.steps <= step else None
    train_n = count - cfg.holdout
    held = torch.arange(train_n, count)
    log = out / "log.jsonl"
    if step == 0:
        log.write_text("")
        append_row(log, {"step": 0, "held_out_psnr": held_out_psnr(model, cache, ds, held, step=False)})  # the model's own colours

    def loss_at(at: int) -> torch.Tensor:
        idx = batch_indices(cfg.seed, at, train_n, cfg.batch_size)
        return scene_mse(cache, idx, recolored(model, cache, idx, _step_latents(model, cache, ds, idx))).clamp_min(1e-8).log().mean()

    def report(at: int, train: float) -> str:
        row = {"step": at, "train_psnr": -10 / math.log(10) * train, "held_out_psnr": held_out_psnr(model, cache, ds, held)}
        append_row(log, row)
        return f"held_out={row['held_out_psnr']:.3f} dB"

    model.color_step.train()
    t0 = time.perf_counter()
    step = fit_steps(step, cfg.steps, opt, lambda at: learning_rate(cfg, at), loss_at, cfg.checkpoint_every, report,
                     lambda at: save_part(ckpt, "color_step.", model.color_step, opt, at, record), "colour step", progress)
    model.eval()
    save_model(model, out / "model", {**(info or {}), "color_step_fit": record})
    rows = read_rows(log)
    return {"steps": step, "held_out_psnr_start": rows[0]["held_out_psnr"], "held_out_psnr_end": rows[-1]["held_out_psnr"],
            "seconds": time.perf_counter() - t0}
