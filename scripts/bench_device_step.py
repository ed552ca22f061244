"""Usage: python3 scripts/bench_device_step.py CONFIG OUT.json

Median training-step time (forward, losses, backward, Adam) of a config, on CUDA at several batch sizes and on the
host CPU, in one run. Writes JSON to argv[2]."""
import json, statistics, sys, time
import torch
from prismonet.config import load_config
from prismonet.data.dataset import SceneDataset
from prismonet.model.io import load_model
from prismonet.model.losses import compute_losses
from prismonet.model.prismonet import PriSMONet
from prismonet.model.trainer import TrainConfig, make_inputs

cfg = load_config(TrainConfig, sys.argv[1])
ds = SceneDataset(cfg.data, cfg.split)
res = {"config": sys.argv[1], "torch": torch.__version__, "gpu": torch.cuda.get_device_name(0) if torch.cuda.is_available() else None, "rows": []}

def bench(device, B, warm, n, threads=2):
    torch.set_num_threads(threads)
    torch.manual_seed(0)
    model = PriSMONet(cfg.model)
    model.load_state_dict(load_model(cfg.init_from)[0].state_dict())
    model.to(device).train()
    opt = torch.optim.Adam([p for p in model.parameters() if p.requires_grad], lr=1e-4)
    times = []
    for s in range(warm + n):
        g = torch.Generator().manual_seed(s)
        idx = torch.randint(len(ds), (B,), generator=g)
        t0 = time.perf_counter()
        batch = ds.batch(idx.tolist()).to(device)
        image, depth = make_inputs(batch, cfg, g)
        out = model(image, batch.K, batch.T_world_cam, batch.ground_z)
        terms = compute_losses(model, out, batch, cfg.loss, 5000, depth, None)
        opt.zero_grad(set_to_none=True)
        terms.total.backward()
        opt.step()
        float(terms.total)
        if device == "cuda":
            torch.cuda.synchronize()
        if s >= warm:
            times.append(time.perf_counter() - t0)
    row = {"device": device, "batch": B, "threads": threads, "steps": n, "median_ms": round(1000 * statistics.median(times), 1),
           "images_per_s": round(B / statistics.median(times), 1)}
    print(row, flush=True)
    res["rows"].append(row)

for B in ((8, 32, 64) if torch.cuda.is_available() else ()):
    bench("cuda", B, 5, 15)
bench("cpu", 8, 2, 5)
json.dump(res, open(sys.argv[2], "w"), indent=2)
