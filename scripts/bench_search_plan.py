"""Usage: python3 scripts/bench_search_plan.py CONFIG OUT.json [cuda|cpu] [BATCHES, e.g. 8,32,64]

Training-step time of one config on CUDA under search block sizes and chunks (the same result either way; the loss
of each variant on one fixed batch is printed to show it), median of 15 steps after 5 warm-up, in one run."""
import dataclasses, json, statistics, sys, time
import torch
from prismonet.config import load_config
from prismonet.data.dataset import SceneDataset
from prismonet.model.io import load_model
from prismonet.model.losses import compute_losses
from prismonet.model.prismonet import PriSMONet
from prismonet.model.trainer import TrainConfig, make_inputs

cfg = load_config(TrainConfig, sys.argv[1])
device = sys.argv[3] if len(sys.argv) > 3 else "cuda"
ds = SceneDataset(cfg.data, cfg.split)
res = {"config": sys.argv[1], "torch": torch.__version__, "device": device, "rows": []}
VARIANTS = {"block 16K, chunk 4 (the CPU plan)": (16384, 4), "block 2M, chunk 4": (1 << 21, 4),
            "block 2M, all samples at once (the accelerator plan)": (1 << 21, 10_000), "block 256K, chunk 8": (1 << 18, 8)}

def bench(name, B, warm, n):
    block, chunk = VARIANTS[name]
    torch.manual_seed(0)
    model = PriSMONet(cfg.model)
    model.load_state_dict(load_model(cfg.init_from)[0].state_dict())
    model.to(device).train()
    base = model.render_settings
    model.render_settings = lambda: dataclasses.replace(base(), block_points=block, search_chunk=chunk)
    opt = torch.optim.Adam([p for p in model.parameters() if p.requires_grad], lr=1e-4)
    g = torch.Generator().manual_seed(123)
    fixed = ds.batch(torch.randint(len(ds), (B,), generator=g).tolist()).to(device)
    with torch.no_grad():
        out = model(fixed.rgb, fixed.K, fixed.T_world_cam, fixed.ground_z)
        ref = float(compute_losses(model, out, fixed, cfg.loss, 5000, fixed.depth, None).total)
    times = []
    for s in range(warm + n):
        g = torch.Generator().manual_seed(s)
        idx = torch.randint(len(ds), (B,), generator=g)
        if device == "cuda":
            torch.cuda.synchronize()
        t0 = time.perf_counter()
        batch = ds.batch(idx.tolist()).to(device)
        image, depth = make_inputs(batch, cfg, g)
        out = model(image, batch.K, batch.T_world_cam, batch.ground_z)
        terms = compute_losses(model, out, batch, cfg.loss, 5000, depth, None)
        opt.zero_grad(set_to_none=True)
        terms.total.backward()
        opt.step()
        float(terms.total.detach())
        if device == "cuda":
            torch.cuda.synchronize()
        if s >= warm:
            times.append(time.perf_counter() - t0)
    row = {"variant": name, "batch": B, "median_ms": round(1000 * statistics.median(times), 1),
           "images_per_s": round(B / statistics.median(times), 1), "loss_fixed_batch": ref}
    print(row, flush=True)
    res["rows"].append(row)

for B in (int(b) for b in sys.argv[4].split(",")) if len(sys.argv) > 4 else (8, 32, 64):
    for name in VARIANTS:
        bench(name, B, 5 if device == "cuda" else 1, 15 if device == "cuda" else 2)
json.dump(res, open(sys.argv[2], "w"), indent=2)
