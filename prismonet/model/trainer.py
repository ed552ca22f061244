"""Training the scene model from RGB-D alone (``prismonet train CONFIG``).

- Batches: step ``t`` draws its scene indices and its input noise from generators seeded with
  ``(seed, t)``, so a resumed run sees exactly what an uninterrupted one would.
- Checkpoints (weights, Adam moments, step, counters) are written atomically to
  ``RUN/checkpoint.safetensors`` every ``checkpoint_every`` steps and on Ctrl-C; rerunning the
  same command resumes.
- Logs: TensorBoard scalars in ``RUN/tb``, the same scalars in ``RUN/log.jsonl``, and image grids
  in ``RUN/images``.
- A non-finite loss skips its step; more than ``max_nonfinite`` of them stop training with an error.
- ``device``: ``"cpu"`` (the default), ``"cuda"`` or ``"auto"`` (CUDA when there is one). Batches are
  drawn and their noise is made on the host either way, so a run may resume on another device.
- Under ``torchrun`` (``WORLD_SIZE`` > 1) it runs DistributedDataParallel (gloo on CPUs, NCCL on
  CUDA, one GPU per rank): each rank takes a share of the global batch, rank 0 writes.
"""

from __future__ import annotations

import json
import math
import os
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import torch

from prismonet.files import write_image
from prismonet.model.config import ModelConfig
from prismonet.model.losses import LossConfig, compute_losses


class TrainingError(RuntimeError):
    """Training cannot go on (too many non-finite losses, a mismatched resume)."""


@dataclass(frozen=True)
class TrainConfig:
    """One training run."""

    data: str = "data/clevr3"
    """A packed dataset (``prismonet data clevr``) or a folder dataset."""
    split: str = "train"
    model: ModelConfig = field(default_factory=ModelConfig)
    loss: LossConfig = field(default_factory=LossConfig)
    steps: int = 20_000
    batch_size: int = 8
    """Global batch size (split across DDP ranks)."""
    lr: float = 1e-4
    """Adam learning rate (the paper: 1e-4)."""
    lr_decay_from: int | None = None
    """Step from which the learning rate follows a cosine from ``lr`` down to ``lr * lr_final_ratio``
    at ``steps``, or at the first of ``lr_restarts`` (``None``: constant). Like ``steps`` it may be set
    when resuming, to add a decay tail."""
    lr_final_ratio: float = 0.01
    lr_restarts: tuple[int, ...] = ()
    """Warm restarts (SGDR): at each of these steps the rate jumps back to ``lr`` and a new cosine runs
    down to ``lr * lr_final_ratio`` at the next restart or at ``steps``. They come after ``lr_decay_from``,
    whose tail then ends at the first restart, so extending a finished run with a restart leaves the
    schedule of the steps already taken unchanged."""
    init_from: str | None = None
    """A trained model (run folder or ``.safetensors``) whose weights start the run, e.g. to fine-tune a
    3-object model on scenes with 4 or 5 objects (the encoder is shared across slots)."""
    init_keep_positions: bool = False
    """With ``init_from`` and ``model.position_offset`` / ``position_scale`` other than that model's (e.g. stacked
    blocks, taller than the tabletop scenes of the model they start from): remap its position outputs so that every
    slot starts where it was (``prismonet.model.io.remap_position_outputs``). Off, the outputs are copied as they are
    and the slots start elsewhere, as the shipped recipes that change the units (`blocktowers`) were trained."""
    init_transfer: bool = False
    """With ``init_from``: start from a model with other latent sizes, prior or outputs (e.g. the Clevr model
    for a ShapeNet-style setting, or for the full-rotation variant): what fits is copied, the latent outputs
    start fresh (``prismonet.model.io.transfer_weights``)."""
    init_widen: bool = False
    """With ``init_from``: the model is a wider copy of that one (more encoder channels or fully connected
    units, ``model.channels`` / ``model.fc`` / ``model.bg_channels``) and starts as the same function
    (``prismonet.model.io.widen_weights``)."""
    distill: str | None = None
    """Folder of self-distillation targets (``prismonet distill``, ``prismonet.model.distill``) for
    the first scenes of the split; used with ``loss.w_distill > 0``."""
    input_noise: float = 0.02
    """Std of the Gaussian noise added to input images (the paper adds noise; its level is not given)."""
    input_noise_max: float = 0.0
    """> input_noise: each image's noise std is drawn from U(input_noise, input_noise_max) (sensor noise)."""
    input_blur: float = 0.0
    """> 0: each input image is blurred by a Gaussian of std U(0, input_blur) pixels (focus, motion); the
    losses still compare with the sharp image."""
    gray_share: float = 0.0
    """Share of training images made grey (their luminance, ``prismonet.data.gray.LUMA``, in all three channels), input and image
    target alike, as a greyscale photo is: a model trained on colour alone reads grey photos badly (EVALUATION.md,
    session 53). Each image is drawn on its own. With distillation, the background target is made grey too; a
    texture-latent target cannot be, so ``loss.distill_texture`` must then be 0."""
    hue_rotate: float = 0.0
    """> 0: each training image's colours are turned about the grey axis by an angle drawn from U(-hue_rotate,
    hue_rotate) degrees, input and image target alike (``prismonet.data.hue``: exact for the Lambertian scenes; greys
    stay). Takes away the colour shortcut of sets where each model has its own colour (the ShapeNet-style ones). With
    distillation the background target is turned too; a texture-latent target cannot be, so ``loss.distill_texture``
    must then be 0."""
    recolor_objects: float = 0.0
    """Share of training images whose objects get new colours, each region off the ground plane its own, found from
    the depth alone (``prismonet.data.recolor``: exact for the Lambertian scenes), input and image target alike. Takes
    away the colour shortcut that a hue turn leaves for grey objects. With distillation ``loss.distill_texture`` must
    be 0, as with ``hue_rotate``."""
    depth_noise_eta: float = 0.0
    """Noisy-depth ablation: noise with sigma = eta d^2 on the target depth (the paper: 0.001)."""
    depth_clip: float = 12.0
    grad_clip: float = 10.0
    """Global gradient-norm clip (0 = off)."""
    seed: int = 0
    device: str = "cpu"
    """Where to train: ``"cpu"``, ``"cuda"`` (``"cuda:N"``) or ``"auto"`` (CUDA if available). It may change when a run
    resumes."""
    threads: int = 2
    """Compute threads per process; 0: chosen by measuring, between 1 and the machine's cores, again
    every few hundred steps (``prismonet.threads``: on a shared 2-core machine two threads are 1.4x
    faster when it is quiet and 2.6x slower under load). Fixed counts keep a run bit-reproducible."""
    log_every: int = 25
    image_every: int = 500
    checkpoint_every: int = 200
    max_nonfinite: int = 20

    def __post_init__(self) -> None:
        if self.steps <= 0 or self.batch_size <= 0 or self.lr <= 0:
            raise ValueError(f"steps, batch_size and lr must be positive, got {self.steps}, {self.batch_size}, {self.lr}")
        for name in ("log_every", "image_every", "checkpoint_every"):
            if getattr(self, name) <= 0:
                raise ValueError(f"{name} must be positive, got {getattr(self, name)}")
        if (self.init_transfer or self.init_widen or self.init_keep_positions) and self.init_from is None:
            raise ValueError("init_transfer, init_widen and init_keep_positions need init_from (the trained model to start from)")
        if self.init_transfer and self.init_widen:
            raise ValueError("init_transfer and init_widen exclude each other")
        if self.loss.w_keep > 0 and not (self.model.refine_passes and self.model.refiner_keep and self.distill):
            raise ValueError("loss.w_keep needs a refiner that keeps or drops slots (model.refine_passes >= 1, "
                             "model.refiner_keep) and distillation targets (distill) that say which slots the fit shows")
        check_device_name(self.device)
        if self.threads < 0:
            raise ValueError(f"threads must be positive, or 0 to choose by measuring, got {self.threads}")
        if not 0 <= self.gray_share <= 1:
            raise ValueError(f"gray_share must be in [0, 1], got {self.gray_share}")
        if self.gray_share > 0 and self.loss.w_distill > 0 and self.loss.distill_texture > 0:
            raise ValueError("gray_share > 0 with distillation needs loss.distill_texture = 0: the texture-latent "
                             "targets are the colour scene's, and a grey image cannot match them")
        if not 0 <= self.hue_rotate <= 180:
            raise ValueError(f"hue_rotate must be in [0, 180] degrees, got {self.hue_rotate}")
        if not 0 <= self.recolor_objects <= 1:
            raise ValueError(f"recolor_objects must be in [0, 1], got {self.recolor_objects}")
        if (self.hue_rotate > 0 or self.recolor_objects > 0) and self.loss.w_distill > 0 and self.loss.distill_texture > 0:
            raise ValueError("hue_rotate or recolor_objects > 0 with distillation needs loss.distill_texture = 0: the "
                             "texture-latent targets are the scene's own colours")
        if self.input_noise < 0 or self.depth_noise_eta < 0 or self.input_noise_max < 0 or self.input_blur < 0:
            raise ValueError("input_noise, input_noise_max, input_blur and depth_noise_eta must be non-negative")
        if self.lr_decay_from is not None and not 0 <= self.lr_decay_from < self.steps:
            raise ValueError(f"lr_decay_from must be in [0, steps={self.steps}), got {self.lr_decay_from}")
        if not 0 <= self.lr_final_ratio <= 1:
            raise ValueError(f"lr_final_ratio must be in [0, 1], got {self.lr_final_ratio}")
        if self.lr_restarts:
            if self.lr_decay_from is None:
                raise ValueError("lr_restarts needs lr_decay_from (the first cosine ends at the first restart)")
            marks = (self.lr_decay_from, *self.lr_restarts, self.steps)
            if any(not isinstance(m, int) for m in self.lr_restarts) or any(a >= b for a, b in zip(marks, marks[1:])):
                raise ValueError(f"lr_restarts must be integers increasing strictly from lr_decay_from="
                                 f"{self.lr_decay_from} to below steps={self.steps}, got {list(self.lr_restarts)}")


RESUME_IGNORED = ("device", "threads", "log_every", "image_every", "checkpoint_every", "steps", "max_nonfinite", "lr_decay_from",
                  "lr_final_ratio", "lr_restarts")
"""Fields that may change between a run and its resumption (e.g. to train for longer, with a decay tail)."""


def learning_rate(cfg: TrainConfig, step: int) -> float:
    """The learning rate of step ``step`` (0-based): constant, then an optional cosine tail, which
    each warm restart begins again."""
    if cfg.lr_decay_from is None or step < cfg.lr_decay_from:
        return cfg.lr
    marks = (cfg.lr_decay_from, *cfg.lr_restarts, cfg.steps)
    k = max(i for i in range(len(marks) - 1) if step >= marks[i])
    t = min(1.0, (step - marks[k]) / (marks[k + 1] - marks[k]))
    lo = cfg.lr * cfg.lr_final_ratio
    return lo + 0.5 * (cfg.lr - lo) * (1.0 + math.cos(math.pi * t))


def _normalised(saved: dict) -> dict:
    """A saved config rebuilt through ``TrainConfig``: fields added since it was written take
    their defaults, so older checkpoints still resume; unknown or invalid ones stay a mismatch."""
    from prismonet.config import ConfigError, _build

    try:
        return json.loads(json.dumps(asdict(_build(TrainConfig, saved, ""))))
    except (ConfigError, TypeError, ValueError):
        return saved


def _dist(backend: str = "gloo") -> tuple[int, int]:
    world = int(os.environ.get("WORLD_SIZE", "1"))
    if world > 1 and not torch.distributed.is_initialized():
        torch.distributed.init_process_group(backend)
    return (torch.distributed.get_rank() if world > 1 else 0), world


def check_device_name(name: str) -> None:
    """A ``ValueError`` (one line) unless ``name`` is ``auto`` or a device PyTorch knows (``cpu``, ``cuda``, ``cuda:N``)."""
    if name != "auto":
        try:
            torch.device(name)
        except RuntimeError:
            raise ValueError(f"device must be 'cpu', 'cuda', 'cuda:N' or 'auto', got {name!r}") from None


def training_device(name: str, world: int = 1) -> torch.device:
    """The device a run trains on: ``"auto"`` is CUDA where there is one, else the CPU; under DDP on CUDA each rank
    takes the GPU of its ``LOCAL_RANK``. Asking for CUDA on a machine without it is an error, not a silent CPU run."""
    check_device_name(name)
    if name == "auto":
        name = "cuda" if torch.cuda.is_available() else "cpu"
    device = torch.device(name)
    if device.type == "cuda":
        if not torch.cuda.is_available():
            raise TrainingError(f"device {name!r}: this machine has no CUDA device (use device=cpu or device=auto)")
        if world > 1 and device.index is None:
            device = torch.device("cuda", int(os.environ.get("LOCAL_RANK", "0")))
        if device.index is not None:
            torch.cuda.set_device(device)
    return device


def _defer_stop_signals(stop: dict):
    """Ctrl-C (SIGINT) and ``kill`` (SIGTERM, a scheduler's stop) end training at the next step
    boundary, with a checkpoint: the handler only records the signal in ``stop["signal"]``, so the
    weights, the optimiser and the step counter are always saved together (a signal between
    ``opt.step()`` and the counter's increment once saved them one step apart). A second signal
    stops at once, without a checkpoint (the last periodic one stays).

    Background jobs started by a non-interactive shell ignore SIGINT, so ``kill`` is the usual
    way to stop them. Returns the previous handlers, or ``None`` off the main thread."""
    import signal
    import threading

    if threading.current_thread() is not threading.main_thread():
        return None

    def handler(signum, frame):
        if stop.get("signal") is not None:
            raise KeyboardInterrupt(f"signal {signum} (second)")
        stop["signal"] = signum

    wanted = [signal.SIGTERM] + ([signal.SIGINT] if signal.getsignal(signal.SIGINT) is not signal.SIG_IGN else [])
    return {s: signal.signal(s, handler) for s in wanted}


def _truncate_log(path: Path, step: int) -> None:
    """Drop the lines of ``log.jsonl`` past ``step`` (written after the checkpoint a run resumes
    from), so a resumed run's log lists each step once."""
    if not path.is_file():
        return
    keep = []
    for line in path.read_text().splitlines():
        try:
            if json.loads(line).get("step", 0) <= step:
                keep.append(line)
        except json.JSONDecodeError:
            continue  # a line cut short by a kill
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text("".join(k + "\n" for k in keep))
    os.replace(tmp, path)


def check_dataset_fits(ds, cfg: TrainConfig) -> None:
    H, W = ds.arrays["rgb"].shape[1:3]
    if (H, W) != (cfg.model.image_size, cfg.model.image_size):
        raise ValueError(f"{cfg.data}: images are {W}x{H} but the model expects {cfg.model.image_size}x{cfg.model.image_size}")
    if len(ds) < 1:
        raise ValueError(f"{cfg.data}: split {cfg.split!r} is empty")
    import numpy as np

    depth = ds.arrays["depth"]
    if not np.isfinite(depth).all():
        raise ValueError(f"{cfg.data}: split {cfg.split!r} has NaN or infinite depth; training needs valid RGB-D")
    if not (np.asarray(depth[: min(len(ds), 256)]) > 0).any():
        raise ValueError(f"{cfg.data}: split {cfg.split!r} has no depth (all zero); training needs RGB-D")


def gray_batch(batch, targets, cfg: TrainConfig, g: torch.Generator):
    """With ``cfg.gray_share``: the batch with a random share of its images grey (input and target), the
    distillation targets' background colours of those scenes grey too, and the ``(B,)`` bool of which (``None``
    without ``gray_share``: nothing drawn, the batch unchanged)."""
    if cfg.gray_share <= 0:
        return batch, targets, None
    from dataclasses import replace

    from prismonet.data.gray import to_gray

    which = torch.rand(batch.rgb.shape[0], generator=g) < cfg.gray_share
    batch = replace(batch, rgb=to_gray(batch.rgb, which))
    if targets is not None:
        t, mask = targets
        targets = ({**t, "bg_color": to_gray(t["bg_color"], which)}, mask)
    return batch, targets, which


def hue_batch(batch, targets, cfg: TrainConfig, g: torch.Generator):
    """With ``cfg.hue_rotate``: the batch with each image's colours turned about the grey axis by its own random
    angle (input and target), and the distillation targets' background colours turned alike (without it nothing is
    drawn and the batch is unchanged)."""
    if cfg.hue_rotate <= 0:
        return batch, targets
    from dataclasses import replace

    from prismonet.data.hue import random_angles, rotate_hue

    angle = random_angles(batch.rgb.shape[0], cfg.hue_rotate, g)
    batch = replace(batch, rgb=rotate_hue(batch.rgb, angle))
    if targets is not None:
        t, mask = targets
        targets = ({**t, "bg_color": rotate_hue(t["bg_color"], angle)}, mask)
    return batch, targets


def recolor_batch(batch, cfg: TrainConfig, g: torch.Generator):
    """With ``cfg.recolor_objects``: the batch with the objects of a random share of its images recoloured, region
    by region, from the depth (``prismonet.data.recolor``); without it nothing is drawn and the batch is unchanged."""
    if cfg.recolor_objects <= 0:
        return batch
    from dataclasses import replace

    from prismonet.data.recolor import batch_regions, recolor_regions

    which = torch.rand(batch.rgb.shape[0], generator=g) < cfg.recolor_objects
    return replace(batch, rgb=recolor_regions(batch.rgb, batch_regions(batch, cfg.model.far_depth), g, which=which))


def make_inputs(batch, cfg: TrainConfig, g: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
    """The noisy input image and the (clipped, optionally noisy) target depth of a batch."""
    image = batch.rgb
    B = image.shape[0]
    if cfg.input_blur > 0:
        from prismonet.model.blur import gaussian_blur

        sigma = (torch.rand(B, generator=g, dtype=image.dtype) * cfg.input_blur).clamp_min(1e-3).to(image.device)
        image = gaussian_blur(image, sigma, 2 * math.ceil(3 * cfg.input_blur) + 1)
    noise = cfg.input_noise
    if cfg.input_noise_max > cfg.input_noise:
        noise = cfg.input_noise + (cfg.input_noise_max - cfg.input_noise) * torch.rand(B, 1, 1, 1, generator=g, dtype=image.dtype).to(image.device)
    # the noise is drawn from the host generator ``g`` whatever the device, so that every device sees the same inputs
    image = image + torch.randn(batch.rgb.shape, generator=g).to(image.device) * noise
    depth = batch.depth.clamp(max=cfg.depth_clip)
    if cfg.depth_noise_eta > 0:
        depth = (depth + torch.randn(depth.shape, generator=g).to(depth.device) * cfg.depth_noise_eta * depth**2).clamp(0, cfg.depth_clip)
    return image, depth


def _step_inputs(ds, targets, cfg: TrainConfig, step: int, device: torch.device, rank: int = 0, world: int = 1):
    """Step ``step``'s batch, distillation targets, noisy input image and target depth, for ``rank`` of ``world``.

    Every random quantity is drawn for the whole global batch from the step's generator (scene indices, colour
    augmentations, noise), and each rank then keeps its share (rows ``rank::world``): the processes of a distributed
    run see exactly the inputs that one process would, so its gradient (the ranks' mean) is the single-process one
    up to rounding for every loss that is a mean over the batch's scenes. The distillation terms average over the
    scenes that have targets, so where the shares hold different numbers of those, the ranks' mean weighs them
    differently from one process."""
    g = torch.Generator().manual_seed(cfg.seed * 1_000_003 + step)
    idx = torch.randint(len(ds), (cfg.batch_size,), generator=g)
    batch = ds.batch(idx.tolist()).to(device)
    looked_up = None if targets is None else targets.lookup(idx.to(device))
    # colours first, so that an image made grey afterwards stays grey (no draw when they are off)
    batch, looked_up = hue_batch(batch, looked_up, cfg, g)
    batch = recolor_batch(batch, cfg, g)
    batch, looked_up, grey = gray_batch(batch, looked_up, cfg, g)
    image, target_depth = make_inputs(batch, cfg, g)
    if grey is not None:  # a greyscale sensor's noise is one channel's: the grey inputs stay grey
        from prismonet.data.gray import to_gray

        image = to_gray(image, grey)
    if world == 1:
        return batch, looked_up, image, target_depth
    share = slice(rank, None, world)
    if looked_up is not None:
        looked_up = ({k: v[share] for k, v in looked_up[0].items()}, looked_up[1][share])
    return batch.rows(share), looked_up, image[share], target_depth[share]


def _finite_everywhere(total: torch.Tensor, world: int) -> bool:
    """Whether the loss is finite on every rank (one all-reduce when ``world`` > 1): a rank that skipped its backward
    alone would leave the others waiting in DDP's gradient all-reduce for good."""
    finite = math.isfinite(float(total.detach()))
    if world == 1:
        return finite
    flag = torch.tensor([1.0 if finite else 0.0], device=total.device)
    torch.distributed.all_reduce(flag, op=torch.distributed.ReduceOp.MIN)
    return bool(flag.item() > 0)


def _mean_over_ranks(scalars: dict[str, float], device: torch.device) -> dict[str, float]:
    """The ranks' mean of each logged loss scalar: each rank's loss is its share's mean, so theirs is the batch's."""
    keys = sorted(scalars)
    v = torch.tensor([float(scalars[k]) for k in keys], dtype=torch.float64, device=device)
    torch.distributed.all_reduce(v)
    v /= torch.distributed.get_world_size()
    return dict(zip(keys, v.tolist()))


def image_grid(batch, out, path: Path, n: int = 4) -> None:
    """PNG: per scene, input | reconstruction | depth target | depth | instances, each panel labelled."""
    import numpy as np

    from prismonet.viz.contact_sheet import colorize_depth, colorize_instances
    from prismonet.viz.decomposition import labelled_panel

    rows = []
    for i in range(min(n, len(batch))):
        to8 = lambda t: (t.detach().clamp(0, 1).permute(1, 2, 0).cpu().numpy() * 255).round().astype(np.uint8)
        d_gt, d = batch.depth[i, 0].cpu().numpy(), out.composite.depth[i, 0].detach().cpu().numpy()
        lo, hi = float(d_gt[d_gt > 0].min()), float(d_gt.max())
        panels = {"input": to8(batch.rgb[i]), "reconstruction": to8(out.composite.image[i]),
                  "depth target": colorize_depth(d_gt, lo, hi), "depth": colorize_depth(d, lo, hi),
                  "instances": colorize_instances(out.composite.instance[i].cpu().numpy())}
        rows.append(np.concatenate([labelled_panel(p, name, (128, 128)) for name, p in panels.items()], 1))
    path.parent.mkdir(parents=True, exist_ok=True)
    write_image(path, np.concatenate(rows, 0)[..., ::-1])


def train(cfg: TrainConfig, run_dir: str | Path, progress: bool = True, stop_after: int | None = None) -> dict:
    """Train (or resume) a run; returns a summary. ``stop_after``: stop after that step (as a kill would)."""
    from tqdm import tqdm

    from prismonet.checkpoint import load_checkpoint, load_optimizer, optimizer_tensors, resume_key, save_checkpoint
    from prismonet.data.dataset import SceneDataset
    from prismonet.model.io import save_model
    from prismonet.model.prismonet import PriSMONet

    world = int(os.environ.get("WORLD_SIZE", "1"))
    device = training_device(cfg.device, world)
    rank, world = _dist("nccl" if device.type == "cuda" else "gloo")
    if cfg.batch_size % world:
        raise ValueError(f"batch_size {cfg.batch_size} must be divisible by the number of processes {world}")
    governor = None
    if cfg.threads > 0:
        torch.set_num_threads(max(1, cfg.threads // world))
    else:
        from prismonet.threads import ThreadGovernor

        cores = max(1, len(os.sched_getaffinity(0)) // world)
        governor = ThreadGovernor(tuple(range(1, cores + 1)) if cores <= 2 else (1, cores // 2, cores))
    torch.manual_seed(cfg.seed)
    run = Path(run_dir)
    ds = SceneDataset(cfg.data, cfg.split)
    check_dataset_fits(ds, cfg)  # before the run folder exists: a run that cannot start leaves nothing
    if rank == 0:
        run.mkdir(parents=True, exist_ok=True)
    model = PriSMONet(cfg.model)
    ckpt = run / "checkpoint.safetensors"
    init_weights = None  # the starting weights' fingerprint: names like "shipped" move when a new model ships
    if cfg.init_from is not None and not ckpt.is_file():
        from prismonet.model.io import (load_fitting, load_model, remap_position_outputs, transfer_weights, weights_fingerprint,
                                        widen_weights)

        source = load_model(cfg.init_from)[0]
        init_weights = weights_fingerprint(source)
        if cfg.init_widen:
            grown = widen_weights(model, source)
            if rank == 0:
                print(f"init_from {cfg.init_from}: widened {len(grown)} tensors, the same function at the start")
        elif cfg.init_transfer:
            fresh = transfer_weights(model, source)
            if rank == 0 and fresh:
                print(f"init_from {cfg.init_from}: fresh where it does not fit: {', '.join(fresh)}")
        else:
            load_fitting(model, source.state_dict(), f"init_from {cfg.init_from}")
        if cfg.model.anchor and not source.cfg.anchor:
            from prismonet.model.io import anchor_start

            anchor_start(model)
            if rank == 0:
                print(f"init_from {cfg.init_from}: an unanchored model; position outputs zeroed (every slot starts at its anchor)")
        elif cfg.init_keep_positions and remap_position_outputs(model, source.cfg) and rank == 0:
            print(f"init_from {cfg.init_from}: position outputs remapped to model.position_offset / position_scale "
                  f"(the same positions at the start)")
    targets = None
    if cfg.distill is not None and (cfg.loss.w_distill > 0 or cfg.loss.w_keep > 0):
        from prismonet.model.distill import VISIBLE, DistillTargets

        targets = DistillTargets(cfg.distill, cfg.model.num_slots)
        if cfg.loss.w_keep > 0 and VISIBLE not in targets.t:
            raise TrainingError(f"{cfg.distill}: these targets do not say which slots the fit shows, so loss.w_keep has "
                                "nothing to learn from; make them again with `prismonet distill`")
    model.to(device)
    params = [p for p in model.parameters() if p.requires_grad]
    # fused: one kernel over every parameter (about 4x faster than the per-tensor loop on the CPU; BENCHMARKS.md)
    opt = torch.optim.Adam(params, lr=cfg.lr, fused=True)
    cfg_json = json.loads(json.dumps(asdict(cfg)))

    start, nonfinite, elapsed = 0, 0, 0.0
    if ckpt.is_file():
        tensors, meta = load_checkpoint(ckpt)
        if resume_key(_normalised(meta.get("config", {})), RESUME_IGNORED) != resume_key(cfg_json, RESUME_IGNORED):
            raise TrainingError(f"{ckpt}: was written with another config; use a new run folder or the same config")
        model.load_state_dict({k[6:]: v for k, v in tensors.items() if k.startswith("model.")})
        load_optimizer(opt, tensors, meta["optimizer"])
        start, nonfinite, elapsed = meta["step"], meta["nonfinite"], meta["elapsed_s"]
        init_weights = meta.get("init_weights")
        if rank == 0:
            _truncate_log(run / "log.jsonl", start)
    net = model
    if world > 1:
        net = torch.nn.parallel.DistributedDataParallel(model, device_ids=[device.index] if device.type == "cuda" else None)

    def save(step: int) -> None:
        if rank != 0:
            return
        tensors, desc = optimizer_tensors(opt)
        tensors.update({f"model.{k}": v for k, v in model.state_dict().items()})
        save_checkpoint(ckpt, tensors, {"config": cfg_json, "step": step, "nonfinite": nonfinite, "elapsed_s": elapsed, "optimizer": desc,
                                          **({"init_weights": init_weights} if init_weights else {})})

    writer = None
    if rank == 0:
        from torch.utils.tensorboard import SummaryWriter

        writer = SummaryWriter(str(run / "tb"), purge_step=start)
    log = open(run / "log.jsonl", "a") if rank == 0 else None
    bar = tqdm(total=cfg.steps, initial=start, desc="train", unit="step", disable=not progress or rank != 0)
    step = start
    last = {}
    stop: dict = {"signal": None}
    previous_handlers = _defer_stop_signals(stop)
    try:
        while step < cfg.steps:
            if governor is not None:
                governor.before_step()
            t0 = time.perf_counter()
            batch, looked_up, image, target_depth = _step_inputs(ds, targets, cfg, step, device, rank, world)
            for group in opt.param_groups:
                group["lr"] = learning_rate(cfg, step)
            net.train()
            out = net(image, batch.K, batch.T_world_cam, batch.ground_z)
            terms = compute_losses(model, out, batch, cfg.loss, step, target_depth, looked_up)
            opt.zero_grad(set_to_none=True)
            if not _finite_everywhere(terms.total, world):  # every rank skips the step together, or none does
                nonfinite += 1
                if nonfinite > cfg.max_nonfinite:
                    raise TrainingError(f"stopping at step {step}: {nonfinite} non-finite losses (max_nonfinite={cfg.max_nonfinite})")
            else:
                terms.total.backward()
                if cfg.grad_clip > 0:
                    torch.nn.utils.clip_grad_norm_(params, cfg.grad_clip)
                opt.step()
            step += 1
            dt = time.perf_counter() - t0
            elapsed += dt
            if governor is not None:
                governor.after_step(dt)
            last = terms.scalars()
            logged = step % cfg.log_every == 0 or step == cfg.steps
            if logged and world > 1:  # the global batch's losses, not rank 0's share (every rank takes part)
                last = _mean_over_ranks(last, device)
            if rank == 0:
                bar.update(1)
                if logged:
                    for k, v in last.items():
                        writer.add_scalar(f"loss/{k}", v, step)
                    writer.add_scalar("train/nonfinite", nonfinite, step)
                    writer.add_scalar("train/lr", opt.param_groups[0]["lr"], step)
                    writer.add_scalar("train/threads", torch.get_num_threads(), step)
                    log.write(json.dumps({"step": step, "time_s": round(elapsed, 2), "nonfinite": nonfinite,
                                          "lr": opt.param_groups[0]["lr"], "threads": torch.get_num_threads(), **last}) + "\n")
                    log.flush()
                    bar.set_postfix(loss=f"{last['total']:.4f}")
                if step % cfg.image_every == 0 or step == cfg.steps:
                    image_grid(batch, out, run / "images" / f"step_{step:07d}.png")
            if step % cfg.checkpoint_every == 0 or step == cfg.steps:
                save(step)
            if stop_after is not None and step >= stop_after:
                break
            if stop["signal"] is not None:
                save(step)  # nothing lost: rerun the same command to resume from here
                raise KeyboardInterrupt(f"signal {stop['signal']}")
    finally:
        if previous_handlers is not None:
            import signal

            for s, h in previous_handlers.items():
                signal.signal(s, h)
        bar.close()
        if writer is not None:
            writer.close()
        if log is not None:
            log.close()
    summary = {"steps": step, "elapsed_s": round(elapsed, 1), "nonfinite": nonfinite, "last": last, "world_size": world,
               **({"init_weights": init_weights} if init_weights else {})}
    if rank == 0 and step >= cfg.steps:
        b0 = ds.batch([0])
        save_model(model, run / "model", {"train": cfg_json, "summary": summary, "camera_K": b0.K[0].tolist(),
                                          "camera_T_world_cam": b0.T_world_cam[0].tolist(), "ground_z": float(b0.ground_z[0])})
    if world > 1:
        torch.distributed.barrier()
    return summary
