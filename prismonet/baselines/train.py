"""Training and evaluating the 2-D baselines on the project's data, with the project's measures.

Training is resumable like the scene model's (one atomic checkpoint with weights, optimiser and step;
Ctrl-C or ``kill`` stop at a step boundary with a checkpoint), with a progress bar, ``log.jsonl`` and
TensorBoard. Evaluation turns each model's slot masks into an instance map (argmax over slots), takes the
slot that covers most ground-truth ground pixels as the background (the PriSMONet paper does not say
how it chose; this is stated in EVALUATION.md), and scores it with ``prismonet.evaluation.metrics``:
the same AP0.5, AR0.5, ARI, ARI-FG and image RMSE as PriSMONet's rows.
"""

from __future__ import annotations

import json
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import torch

from prismonet.baselines.genesis import Genesis, GenesisConfig
from prismonet.baselines.monet import MONet, MONetConfig
from prismonet.baselines.slot_attention import SlotAttentionAutoEncoder, SlotAttentionConfig

BASELINES = ("slot_attention", "monet", "genesis")


@dataclass(frozen=True)
class BaselineTrainConfig:
    name: str = "slot_attention"
    """Which baseline (``BASELINES``)."""
    data: str = "data/clevr3"
    split: str = "train"
    steps: int = 10000
    batch_size: int = 8
    lr: float = 4e-4
    """Adam step (Slot Attention's paper: 4e-4; MONet's uses RMSProp at 1e-4 and GENESIS's Adam at 1e-4: set lr=1e-4)."""
    warmup: int = 1000
    """Linear warm-up steps (the paper: 10K of 500K; scaled to this budget)."""
    decay_half_life: int = 10000
    """The step halves every this many steps after warm-up (the paper: 100K)."""
    seed: int = 0
    checkpoint_every: int = 200
    log_every: int = 25
    slot_attention: SlotAttentionConfig = field(default_factory=SlotAttentionConfig)
    monet: MONetConfig = field(default_factory=MONetConfig)
    genesis: GenesisConfig = field(default_factory=GenesisConfig)

    def __post_init__(self) -> None:
        if self.name not in BASELINES:
            raise ValueError(f"baseline: expected one of {', '.join(BASELINES)}, got {self.name!r}")
        if self.steps < 1 or self.batch_size < 1 or not self.lr > 0 or self.warmup < 0 or self.decay_half_life < 1:
            raise ValueError(f"baseline: steps, batch_size, lr and decay_half_life must be positive, warmup >= 0, got {self}")


def build(cfg: BaselineTrainConfig) -> torch.nn.Module:
    return {"slot_attention": lambda: SlotAttentionAutoEncoder(cfg.slot_attention), "monet": lambda: MONet(cfg.monet),
            "genesis": lambda: Genesis(cfg.genesis)}[cfg.name]()


def image_size(cfg: BaselineTrainConfig) -> int:
    return getattr(cfg, cfg.name).image_size


RESUME_IGNORED = ("steps", "checkpoint_every", "log_every")
"""Fields that may change when a run resumes (the schedule does not depend on ``steps``, so a run can be
stopped at a shared budget or trained for longer)."""


def learning_rate(cfg: BaselineTrainConfig, step: int) -> float:
    warm = min(1.0, (step + 1) / cfg.warmup) if cfg.warmup else 1.0
    return cfg.lr * warm * 0.5 ** (max(0, step - cfg.warmup) / cfg.decay_half_life)


def train_baseline(cfg: BaselineTrainConfig, run_dir: str | Path, progress: bool = True, stop_after: int | None = None) -> dict:
    """Train (or resume) a baseline in ``run_dir``; returns a summary."""
    from tqdm import tqdm

    from prismonet.checkpoint import load_checkpoint, load_optimizer, optimizer_tensors, resume_key, save_checkpoint
    from prismonet.data.dataset import SceneDataset
    from prismonet.model.trainer import TrainingError, _defer_stop_signals, _truncate_log

    ds = SceneDataset(cfg.data, cfg.split)
    if ds.arrays["rgb"].shape[1] != image_size(cfg):
        raise ValueError(f"{cfg.data}: images are {ds.arrays['rgb'].shape[1]} px, the baseline expects {image_size(cfg)}")
    run = Path(run_dir)
    run.mkdir(parents=True, exist_ok=True)
    torch.manual_seed(cfg.seed)
    model = build(cfg)
    opt = torch.optim.Adam(model.parameters(), lr=cfg.lr)
    ckpt, cfg_json = run / "checkpoint.safetensors", json.loads(json.dumps(asdict(cfg)))
    start, elapsed = 0, 0.0
    if ckpt.is_file():
        tensors, meta = load_checkpoint(ckpt)
        if resume_key(meta.get("config", {}), RESUME_IGNORED) != resume_key(cfg_json, RESUME_IGNORED):
            raise TrainingError(f"{ckpt}: was written with another config; use a new run folder or the same config")
        model.load_state_dict({k[6:]: v for k, v in tensors.items() if k.startswith("model.")})
        load_optimizer(opt, tensors, meta["optimizer"])
        start, elapsed = meta["step"], meta["elapsed_s"]
        _truncate_log(run / "log.jsonl", start)

    def save(step: int) -> None:
        tensors, desc = optimizer_tensors(opt)
        tensors.update({f"model.{k}": v for k, v in model.state_dict().items()})
        save_checkpoint(ckpt, tensors, {"config": cfg_json, "step": step, "elapsed_s": elapsed, "optimizer": desc})

    from torch.utils.tensorboard import SummaryWriter

    writer, stop, step = SummaryWriter(str(run / "tb"), purge_step=start), {"signal": None}, start
    previous = _defer_stop_signals(stop)
    try:
        with open(run / "log.jsonl", "a") as log, tqdm(total=cfg.steps, initial=start, desc=cfg.name, unit="step", disable=not progress) as bar:
            while step < cfg.steps:
                t0 = time.perf_counter()
                g = torch.Generator().manual_seed(cfg.seed * 1_000_003 + step)
                rgb = ds.batch(torch.randint(len(ds), (cfg.batch_size,), generator=g).tolist()).rgb
                for group in opt.param_groups:
                    group["lr"] = learning_rate(cfg, step)
                loss = model.loss(rgb, g)
                opt.zero_grad(set_to_none=True)
                loss.backward()
                opt.step()
                step += 1
                elapsed += time.perf_counter() - t0
                bar.update(1)
                if step % cfg.log_every == 0 or step == cfg.steps:
                    row = {"step": step, "time_s": round(elapsed, 2), "lr": learning_rate(cfg, step - 1), "loss": loss.item()}
                    log.write(json.dumps(row) + "\n")
                    log.flush()
                    writer.add_scalar("loss", row["loss"], step)
                if step % cfg.checkpoint_every == 0 or step == cfg.steps or stop["signal"] is not None or step == stop_after:
                    save(step)
                if stop["signal"] is not None or step == stop_after:
                    break
    finally:
        writer.close()
        if previous:
            import signal

            for s, h in previous.items():
                signal.signal(s, h)
    return {"steps": step, "elapsed_s": round(elapsed, 1), "images_seen": step * cfg.batch_size}


def load_baseline(run_dir: str | Path) -> tuple[torch.nn.Module, BaselineTrainConfig]:
    from prismonet.checkpoint import load_checkpoint
    from prismonet.config import _build

    tensors, meta = load_checkpoint(Path(run_dir) / "checkpoint.safetensors")
    cfg = _build(BaselineTrainConfig, meta["config"], "")
    model = build(cfg)
    model.load_state_dict({k[6:]: v for k, v in tensors.items() if k.startswith("model.")})
    return model.eval(), cfg


def instances_from_masks(masks: np.ndarray, gt_instance: np.ndarray) -> np.ndarray:
    """``(B, H, W)`` instance ids from slot masks ``(B, K, H, W)``: argmax over slots; the slot covering
    most ground-truth ground pixels becomes 0 (background), the others 1.. in slot order."""
    arg = masks.argmax(1)
    out = np.zeros_like(arg)
    K = masks.shape[1]
    for b in range(len(arg)):
        ground = np.bincount(arg[b][gt_instance[b] == 0], minlength=K)
        bg = int(ground.argmax())
        ids = np.concatenate([np.arange(bg) + 1, [0], np.arange(bg + 1, K)])  # slot -> id
        out[b] = ids[arg[b]]
    return out


@torch.no_grad()
def evaluate_baseline(run_dir: str | Path, data: str | Path, split: str = "test", limit: int | None = None, batch_size: int = 16) -> dict:
    """The project's measures for a trained baseline on a dataset split."""
    from prismonet.data.dataset import SceneDataset
    from prismonet.evaluation.metrics import ari_metrics, detection_metrics, image_metrics

    model, cfg = load_baseline(run_dir)
    ds = SceneDataset(data, split)
    n = len(ds) if limit is None else min(limit, len(ds))
    pred, gt, img, rgb = [], [], [], []
    for s in range(0, n, batch_size):
        b = ds.batch(list(range(s, min(s + batch_size, n))))
        out = model(b.rgb, torch.Generator().manual_seed(s))
        gi = b.instance.numpy()
        pred.append(instances_from_masks(out.masks.numpy(), gi))
        gt.append(gi)
        img.append(out.image.clamp(0, 1).numpy())
        rgb.append(b.rgb.numpy())
    cat = np.concatenate
    r = {"baseline": cfg.name, "scenes": n}
    r.update(detection_metrics(cat(pred), cat(gt)))
    r.update(ari_metrics(cat(pred), cat(gt)))
    r.update(image_metrics(cat(img), cat(rgb)))
    return r
