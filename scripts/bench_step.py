"""Training-step time of the shipped recipe, each speed change against the code before it, in one run.

    python3 scripts/bench_step.py [--data data/clevr3] [--rounds 6] [--steps 5] [--threads 2] [--variants a,b,...]

A step is what the trainer does (noisy inputs, the recurrent forward pass with soft silhouettes,
every loss of ``configs/clevr3_shipped.json`` at its final schedule, backward, clipping, Adam) on
batch 8 of the training split, starting from the weights of `clevr3_fc` (the shipped encoder without its refinement pass: a trained model's hit pattern,
which is what a fine-tune or distillation run sees). Variants run interleaved, ``--steps`` steps
each per round, on the same batches, so that the host's load drifts over all of them alike; the
table gives medians over every timed step. Variants (cumulative, each adds one change):

- ``previous``: the code before this benchmark's changes (``argmin`` z-buffer, unfused MLP);
- ``zbuffer``: ``min(dim=1).indices`` in the z-buffer;
- ``inplace``: + the in-place no-grad MLP in the root search (``prismonet.shapes.decoder``);
- ``blur``: + the loss's Gaussian blur truncated at 6 sigma (7 taps instead of 17 at sigma 0.5);
- ``blurmm``: + that blur as two matrix products instead of kornia's convolutions, and L_I / L_D blurring
  the difference once instead of each image (session 58; ``prismonet.model.blur``);
- ``fused``: + Adam as one fused kernel (``fused=True``) instead of its per-tensor loop (session 58);
- ``compiled``: + the object and background encoders under ``torch.compile`` (inductor, static shapes; session 62,
  not adopted: slower). Its first round also compiles, which round 0 (the warm-up) absorbs.
- ``poolfirst``: ``fused`` (not ``compiled``) with each encoder block pooling before its ReLU (session 73, the code now;
  exact: ``tests/test_encoder.py``). Every variant before it runs the blocks as conv, ReLU, pool.

The process keeps freed memory for reuse as every ``prismonet`` command does (``prismonet.allocator``;
``PRISMONET_MALLOC=default`` turns it off).
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time

import torch


def _argmin_zbuffer(obj_depth, obj_mask, upto=None):
    """The z-buffer as it was: ``argmin`` (14x slower than ``min().indices`` on CPU)."""
    d = obj_depth[:, :upto].detach()
    m = obj_mask[:, :upto]
    if d.shape[1] == 0:
        B, _, H, W = obj_depth.shape
        return torch.zeros(B, H, W, dtype=torch.long), torch.zeros(B, H, W, dtype=torch.bool)
    d = torch.where(m, d, torch.full_like(d, float("inf")))
    return d.argmin(dim=1), m.any(dim=1)


class ShippedStep:
    """One training step as the trainer takes it (noisy inputs, forward, every loss of
    ``configs/clevr3_shipped.json`` at its final schedule, backward, clipping, Adam), batch 8 of the training
    split, from `clevr3_fc`'s weights; ``step(seed)`` returns its seconds, ``reset()`` restores the weights."""

    def __init__(self, data: str) -> None:
        from prismonet.config import load_config
        from prismonet.data.dataset import SceneDataset
        from prismonet.model.io import load_model
        from prismonet.model.trainer import TrainConfig

        self.cfg = load_config(TrainConfig, "configs/clevr3_shipped.json", [f"data={data}"])
        self.model = load_model("clevr3_fc")[0]  # the encoder-only model: the step the issue profiled has no refiner
        self.model.train()
        self.ds = SceneDataset(self.cfg.data, "train")
        self.params = [p for p in self.model.parameters() if p.requires_grad]
        self.state = {k: v.clone() for k, v in self.model.state_dict().items()}
        self.reset()

    def reset(self, fused: bool = True, compiled: bool = False, pool_first: bool = True) -> None:
        if hasattr(self, "_eager"):  # the eager modules back first, so that the state's names match
            self.model.encoder, self.model.bg_encoder = self._eager
        for enc in (self.model.encoder, self.model.bg_encoder):  # the same modules, in either order
            enc.trunk = _trunk_order(enc.trunk, pool_first)
        self.model.load_state_dict(self.state)
        self.opt = torch.optim.Adam(self.params, lr=1e-6, fused=fused)
        if compiled:
            if not hasattr(self, "_compiled"):  # once: the compiled modules wrap the eager ones and share their weights
                self._eager = (self.model.encoder, self.model.bg_encoder)
                self._compiled = tuple(torch.compile(m, dynamic=False) for m in self._eager)
            self.model.encoder, self.model.bg_encoder = self._compiled

    def __call__(self, seed: int) -> float:
        from prismonet.model.losses import compute_losses
        from prismonet.model.trainer import make_inputs

        cfg, model = self.cfg, self.model
        g = torch.Generator().manual_seed(seed)
        b = self.ds.batch(torch.randint(len(self.ds), (cfg.batch_size,), generator=g).tolist())
        t0 = time.perf_counter()
        image, depth = make_inputs(b, cfg, g)
        out = model(image, b.K, b.T_world_cam, b.ground_z)
        terms = compute_losses(model, out, b, cfg.loss, cfg.steps, depth)
        self.opt.zero_grad(set_to_none=True)
        terms.total.backward()
        torch.nn.utils.clip_grad_norm_(self.params, cfg.grad_clip)
        self.opt.step()
        return time.perf_counter() - t0


def _trunk_order(trunk: torch.nn.Sequential, pool_first: bool) -> torch.nn.Sequential:
    """The trunk's own modules as blocks of (conv, pool, ReLU) with ``pool_first``, else (conv, ReLU, pool)."""
    convs = [m for m in trunk if isinstance(m, torch.nn.Conv2d)]
    pools = [m for m in trunk if isinstance(m, torch.nn.MaxPool2d)]
    relus = [m for m in trunk if isinstance(m, torch.nn.ReLU)]
    if isinstance(trunk[1], torch.nn.MaxPool2d) == pool_first:
        return trunk  # already so: the same object (a compiled wrapper keeps its graph)
    return torch.nn.Sequential(*[m for c, p, r in zip(convs, pools, relus) for m in ((c, p, r) if pool_first else (c, r, p))])


VARIANTS = ("previous", "zbuffer", "inplace", "blur", "blurmm", "fused", "compiled", "poolfirst")
_ORIGINAL: dict = {}


def configure(name: str) -> None:
    """Switch the process to variant ``name`` (module-level switches only; same weights)."""
    from importlib import import_module

    # (``prismonet.render.composite`` the function shadows the module of that name)
    color_fit, composite, renderer, decoder, losses = (import_module(f"prismonet.{m}") for m in (
        "model.color_fit", "render.composite", "render.renderer", "shapes.decoder", "model.losses"))

    rank = VARIANTS.index(name) if name != "poolfirst" else VARIANTS.index("fused")
    _ORIGINAL.setdefault("zbuffer", composite.zbuffer)
    zb = _ORIGINAL["zbuffer"] if rank >= 1 else _argmin_zbuffer
    composite.zbuffer = renderer.zbuffer = color_fit.zbuffer = zb
    decoder.INPLACE_NOGRAD = rank >= 2
    _ORIGINAL.setdefault("blur_kernel_size", losses.blur_kernel_size)
    losses.blur_kernel_size = _ORIGINAL["blur_kernel_size"] if rank >= 3 else (lambda sigma: losses.BLUR_KERNEL)
    _ORIGINAL.setdefault("compute_losses", losses.compute_losses)
    _ORIGINAL.setdefault("blur", losses.blur)
    if rank >= 4:
        losses.blur, losses.compute_losses = _ORIGINAL["blur"], _ORIGINAL["compute_losses"]
    else:
        losses.blur, losses.compute_losses = _kornia_blur, _two_blur_losses


def _kornia_blur(x, cfg, step):
    """The losses' blur as it was: kornia's separable convolutions."""
    import kornia

    from prismonet.model import losses

    if not cfg.blur:
        return x
    s = losses.blur_sigma(cfg, step)
    k = losses.blur_kernel_size(s)
    return kornia.filters.gaussian_blur2d(x, (k, k), (s, s), border_type="replicate")


def _two_blur_losses(model, out, batch, cfg, step, target_depth=None, distill=None):
    """The losses as they were: L_I and L_D blur each image, then subtract (the other terms as now)."""
    from dataclasses import replace

    from prismonet.model import losses

    terms = _ORIGINAL["compute_losses"](model, out, batch, replace(cfg, use_image=False, use_depth=False), step,
                                        target_depth, distill)
    depth_gt = batch.depth if target_depth is None else target_depth
    image = ((losses.blur(out.composite.image, cfg, step) - losses.blur(batch.rgb, cfg, step)) ** 2).sum(1).mean()
    rendered = out.composite.depth.clamp(max=model.cfg.far_depth) if cfg.far_clip else out.composite.depth
    depth = (losses.blur(rendered, cfg, step) - losses.blur(depth_gt, cfg, step)).abs().mean()
    return replace(terms, image=image, depth=depth, total=terms.total + cfg.w_image * image + cfg.w_depth * depth)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", default="data/clevr3")
    ap.add_argument("--rounds", type=int, default=6)
    ap.add_argument("--steps", type=int, default=5)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--variants", default=",".join(VARIANTS))
    args = ap.parse_args(argv)
    names = args.variants.split(",")
    bad = [n for n in names if n not in VARIANTS]
    if bad or args.rounds <= 0 or args.steps <= 0 or args.threads <= 0:
        print(f"bench_step: error: variants must be among {VARIANTS} and counts positive, got {args.variants!r}", file=sys.stderr)
        return 2

    from prismonet.allocator import keep_freed_memory

    keep_freed_memory()  # as every prismonet command does
    torch.set_num_threads(args.threads)
    step = ShippedStep(args.data)

    times: dict[str, list[float]] = {n: [] for n in names}
    for r in range(args.rounds + 1):  # round 0 warms up
        for n in names:
            configure(n)
            step.reset(fused=VARIANTS.index(n) >= 5, compiled=n == "compiled", pool_first=n == "poolfirst")
            for i in range(args.steps):
                t = step(1000 * r + i)
                if r > 0:
                    times[n].append(t)
    print(f"training step, batch {step.cfg.batch_size}, {args.threads} thread(s), {args.rounds} x {args.steps} steps per variant")
    print_table(times, names)
    return 0


def print_table(times: dict[str, list[float]], names: list[str], first: str = "variant") -> None:
    """A markdown table of each variant's step times in ms (median, min, max) and its speed-up against the first's."""
    base = statistics.median(times[names[0]])
    print(f"| {first} | median ms | min | max | speed-up vs {names[0]} |")
    print("|---|---|---|---|---|")
    for n in names:
        m = statistics.median(times[n])
        print(f"| {n} | {1e3 * m:.1f} | {1e3 * min(times[n]):.1f} | {1e3 * max(times[n]):.1f} | {base / m:.2f}x |")


if __name__ == "__main__":
    raise SystemExit(main())
