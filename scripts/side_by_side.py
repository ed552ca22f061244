"""Usage: OUT=DIR [CONFIGS=configs/gpu_chairs] [DEVICE=cuda] [PROBE=30] [ONLY=a,b] python3 scripts/side_by_side.py DEADLINE_EPOCH_S

Run the CONFIGS variants side by side on one GPU until a deadline: a short probe run measures the step time,
then each resumes with as many steps as fit (a cosine tail over them); at the deadline a SIGTERM makes each save its
checkpoint. Each run's model (or checkpoint) and log go to $OUT/NAME.tgz."""
import json, os, signal, subprocess, sys, tarfile, time
from pathlib import Path

deadline = float(sys.argv[1])  # epoch seconds: all runs stopped by then
PROBE = int(os.environ.get("PROBE", "30"))
DEVICE = os.environ.get("DEVICE", "cuda")
CONFIGS = os.environ.get("CONFIGS", "configs/gpu_chairs")
out = Path(os.environ["OUT"])
names = sorted(p.stem for p in Path(CONFIGS).glob("*.json") if not os.environ.get("ONLY") or p.stem in os.environ["ONLY"].split(","))
log = open(out / "drive.txt", "a")

def say(*a):
    print(*a, flush=True); print(*a, file=log, flush=True)

def launch(name, steps, decay_from):
    cmd = [sys.executable, "-m", "prismonet", "train", f"{CONFIGS}/{name}.json", "--out", f"runs/gpu/{name}", "--device", DEVICE,
           "--quiet", "--set", f"steps={steps}", "--set", f"lr_decay_from={decay_from}"]
    return subprocess.Popen(cmd, stdout=open(f"runs/gpu/{name}.out", "a"), stderr=subprocess.STDOUT)

def times(name):
    return {r["step"]: r["time_s"] for r in map(json.loads, Path(f"runs/gpu/{name}/log.jsonl").read_text().splitlines())}

Path("runs/gpu").mkdir(parents=True, exist_ok=True)
t0 = time.time()
procs = {n: launch(n, PROBE, PROBE - 1) for n in names}
for n, p in procs.items():
    p.wait()
    say(n, "probe rc", p.returncode, "after", round(time.time() - t0, 1), "s")
ok = [n for n, p in procs.items() if p.returncode == 0]
for n in set(names) - set(ok):
    say(Path(f"runs/gpu/{n}.out").read_text()[-3000:])
step_s = {}
for n in ok:
    t = times(n)
    first = min(k for k in t if k >= 5)
    step_s[n] = (t[PROBE] - t[first]) / (PROBE - first)
    for f in ("model.safetensors", "model.json"):  # the probe's end: the run goes on from its checkpoint
        Path(f"runs/gpu/{n}/{f}").unlink()
left = deadline - time.time() - 25  # start-up and the last checkpoint
steps = {n: PROBE + max(0, int(left / (step_s[n] * 1.1))) for n in ok}
say(f"step_s ({len(ok)} side by side)", {n: round(v, 4) for n, v in step_s.items()}, "planned steps", steps)
procs = {n: launch(n, steps[n], PROBE) for n in ok}
while time.time() < deadline and any(p.poll() is None for p in procs.values()):
    time.sleep(2)
for n, p in procs.items():
    if p.poll() is None:
        p.send_signal(signal.SIGTERM)
for n, p in procs.items():
    try:
        p.wait(timeout=40)
    except subprocess.TimeoutExpired:
        p.kill()
    t = times(n)
    last = max(t)
    say(n, "rc", p.returncode, "last logged step", last, "train time", t[last], "s")
for n in names:
    run = Path(f"runs/gpu/{n}")
    with tarfile.open(out / f"{n}.tgz", "w:gz") as tf:
        for f in ("model.safetensors", "model.json") if (run / "model.json").is_file() else ("checkpoint.safetensors",):
            if (run / f).is_file():
                tf.add(run / f, arcname=f"{n}/{f}")
        for f in ("log.jsonl",):
            if (run / f).is_file():
                tf.add(run / f, arcname=f"{n}/{f}")
        tf.add(f"runs/gpu/{n}.out", arcname=f"{n}/train.out")
say("packed", round(time.time() - t0, 1), "s")
