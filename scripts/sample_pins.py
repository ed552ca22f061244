"""The figures ``tests/test_shipped_model.py`` pins, measured on the 16 shipped 3-object test scenes for each model named.

    python3 scripts/sample_pins.py [MODEL ...]        # default: shipped clevr3

Per model: feed-forward AP0.5, AR0.5, depth RMSE, PSNR and the count; the cubes drawn as cubes (and the objects of
each category matched); PSNR with 3 x 3 rays per pixel; AP0.5, depth RMSE and PSNR with ``--search 3 --fit-color 50``.
About 40 s per model on two threads. Prints JSON.
"""

import argparse
import json
import sys

from prismonet.assets import shipped_samples
from prismonet.data.dataset import SceneDataset
from prismonet.evaluation.evaluate import evaluate_model
from prismonet.model.inference import InferenceConfig
from prismonet.model.io import load_model, training_loss_config


def pins(name: str, ds: SceneDataset) -> dict:
    model, info = load_model(name)
    ff = evaluate_model(model, ds, batch_size=16, progress=False)
    aa = evaluate_model(model, ds, batch_size=16, progress=False, supersample=3)
    se = evaluate_model(model, ds, batch_size=16, progress=False, loss_cfg=training_loss_config(info),
                        inference=InferenceConfig.of(search=3, fit_color=50))
    return {"ff": {k: ff[k] for k in ("AP0.5", "AR0.5", "depth_RMSE", "PSNR", "count_exact")},
            "ff_cubes": [ff["shape_category"]["cube"], ff["shape_category"]["objects"]],
            "aa_PSNR": aa["PSNR"], "search": {k: se[k] for k in ("AP0.5", "depth_RMSE", "PSNR")}}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("models", nargs="*", default=["shipped", "clevr3"])
    args = ap.parse_args()
    ds = SceneDataset(shipped_samples(), split="test")
    try:  # a bad name or a damaged model: one line (CheckpointError is a ValueError)
        rows = {name: pins(name, ds) for name in args.models}
    except (ValueError, FileNotFoundError) as e:
        sys.exit(f"sample_pins: error: {str(e).splitlines()[0]}")
    print(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
