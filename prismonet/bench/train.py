"""``prismonet bench train``: training-step time (batch 8, 64x64, 3 objects) and inference time.

A step is what the trainer does: noisy inputs, the recurrent forward pass with rendering, every
loss, backward, gradient clipping and Adam. Data come from a small generated dataset, or
``--data``. Medians after warm-up.
"""

from __future__ import annotations

import shutil
import statistics
import tempfile
import time
from pathlib import Path

import torch


def step_from(cfg, init_from: str | None = None, device: str = "cpu"):
    """A model of ``cfg.model`` (with ``init_from``'s weights) on ``device`` in training mode, an Adam over it, and the
    config's training split: what ``timed_step`` steps."""
    from prismonet.data.dataset import SceneDataset
    from prismonet.model.io import load_model
    from prismonet.model.prismonet import PriSMONet

    torch.manual_seed(0)
    model = PriSMONet(cfg.model)
    if init_from is not None:
        model.load_state_dict(load_model(init_from)[0].state_dict())
    model.to(device).train()
    opt = torch.optim.Adam([p for p in model.parameters() if p.requires_grad], lr=1e-6)
    return model, opt, SceneDataset(cfg.data, cfg.split)


def timed_step(model, opt, ds, cfg, batch: int, seed: int, loss_step: int = 5000) -> float:
    """Seconds of one training step on the model's device, the batch's reading and transfer included: noisy inputs,
    forward, every loss of ``cfg.loss`` at ``loss_step``, backward, Adam (no clipping), synchronised on CUDA."""
    from prismonet.model.losses import compute_losses
    from prismonet.model.trainer import make_inputs

    device = next(model.parameters()).device
    g = torch.Generator().manual_seed(seed)
    idx = torch.randint(len(ds), (batch,), generator=g).tolist()
    if device.type == "cuda":
        torch.cuda.synchronize()
    t0 = time.perf_counter()
    b = ds.batch(idx).to(device)
    image, depth = make_inputs(b, cfg, g)
    out = model(image, b.K, b.T_world_cam, b.ground_z)
    terms = compute_losses(model, out, b, cfg.loss, loss_step, depth, None)
    opt.zero_grad(set_to_none=True)
    terms.total.backward()
    opt.step()
    float(terms.total.detach())
    if device.type == "cuda":
        torch.cuda.synchronize()
    return time.perf_counter() - t0


def bench_train(data: str | None, steps: int, batch: int, objects: int, threads: int = 2) -> dict:
    from prismonet.data.clevr import ClevrConfig
    from prismonet.data.dataset import SceneDataset
    from prismonet.data.generate import generate_clevr
    from prismonet.model.config import ModelConfig
    from prismonet.model.losses import compute_losses
    from prismonet.model.prismonet import PriSMONet
    from prismonet.model.trainer import TrainConfig, make_inputs

    torch.set_num_threads(threads)
    tmp = None
    if data is None:
        tmp = Path(tempfile.mkdtemp(prefix="prismonet-bench-"))
        data = tmp / "ds"
        generate_clevr(data, ClevrConfig(num_objects=objects), split=(64, 0, 0), seed=0, workers=1, progress=False)
    try:
        ds = SceneDataset(data, "train")
        cfg = TrainConfig(data=str(data), batch_size=batch, model=ModelConfig(num_slots=objects))
        torch.manual_seed(0)
        model = PriSMONet(cfg.model)
        params = [p for p in model.parameters() if p.requires_grad]
        opt = torch.optim.Adam(params, lr=cfg.lr)
        times, rays = [], []
        for s in range(steps + 3):
            g = torch.Generator().manual_seed(s)
            b = ds.batch(torch.randint(len(ds), (batch,), generator=g).tolist())
            t0 = time.perf_counter()
            image, depth = make_inputs(b, cfg, g)
            out = model(image, b.K, b.T_world_cam, b.ground_z)
            terms = compute_losses(model, out, b, cfg.loss, s, depth)
            opt.zero_grad(set_to_none=True)
            terms.total.backward()
            torch.nn.utils.clip_grad_norm_(params, cfg.grad_clip)
            opt.step()
            if s >= 3:
                times.append(time.perf_counter() - t0)
                rays.append(int(out.obj_mask.sum()))
        model.eval()
        inf = []
        one = ds.batch([0])
        with torch.no_grad():
            for s in range(13):
                t0 = time.perf_counter()
                model(one.rgb, one.K, one.T_world_cam, one.ground_z)
                if s >= 3:
                    inf.append(time.perf_counter() - t0)
        step = statistics.median(times)
        return {"step_ms": 1e3 * step, "step_ms_min": 1e3 * min(times), "step_ms_max": 1e3 * max(times),
                "steps_per_hour": 3600 / step, "infer_ms": 1e3 * statistics.median(inf), "steps": steps,
                "object_pixels_per_batch": statistics.median(rays)}
    finally:
        if tmp is not None:
            shutil.rmtree(tmp, ignore_errors=True)
