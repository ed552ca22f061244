"""Files that ship with the package: the pre-trained Clevr shape prior, the trained scene models
(each with its training config and log), and a few test scenes."""

from __future__ import annotations

from importlib import resources
from pathlib import Path

CLEVR3_MODEL = "clevr3_model"
"""Stem of ``clevr3``, the default scene model of sessions 56-91 (``"shipped"`` until session 92):
``clevr3_model.safetensors`` + ``clevr3_model.json`` (since session 56): the keep recipe of session 47 (below) with its
refiner fitted to 13,312 search targets instead of 8,192, made on new training scenes (``data clevr --objects 3 --seed 7
--split 24576,0,0``), for 6,000 steps instead of 3,000. Stage 1 ``prismonet refiner clevr3_fc data/clevr3_x ... --steps
6000 --glimpse 0.375 --coords --keep`` (its log: ``clevr3_keep13k_fit_log.jsonl``), stage 2
``configs/clevr3_keep13k.json`` (``clevr3_keep13k_config.json``, ``clevr3_keep13k_log.jsonl``); applied twice,
``refine_passes`` 2. Since session 57 with a learnt colour step (``model.color_step``: ``prismonet color-step clevr3
data/clevr3_x --count 8192 --steps 2000``, its log ``clevr3_keep13k_color_log.jsonl``): the same detections, depth and
masks bit for bit, test PSNR 25.61 -> 25.90. The session-56 model is this one with ``color_step`` off."""
FIT13K_MODEL = "clevr3_fit13k_model"
"""``clevr3``'s stage 1 alone (session 56): ``clevr3_fc`` with the keep refiner fitted to the 13,312 targets for
6,000 steps (its log: ``clevr3_keep13k_fit_log.jsonl``), applied twice; no stage 2. Not the default: better on PSNR
(test 26.02 against 25.61; 26.63 with ``evaluate --supersample 3``) and mAP, worse on allObj and the count."""
COLOR_MODEL = "clevr3_color_model"
"""Session 57: ``clevr3``'s stage 1 fitted to more search targets, with a learnt colour step; the one model that
meets every feed-forward target of issue 25 (test: AP0.5 0.977 unfiltered, AR0.5 0.968, allObj 0.917, PSNR 26.52,
996K images seen). ``clevr3_fc`` with the keep refiner fitted to 20,736 targets for 9,000 steps
(``clevr3_color_fit_log.jsonl``), applied twice, then a colour step (``model.color_step``, ``prismonet color-step``)
trained photometrically, 1,500 steps of batch 24 (session 58, on 8,192 training images: PSNR 26.52; since session 105
three passes on 24,576 seed-7 images: test PSNR 26.59, the same 996K images seen) (``clevr3_color_step_log.jsonl``).
Not the default: below it on allObj (0.917 against 0.939) and the count."""
SHARP_MODEL = "clevr3_sharp_model"
"""The 3-object model that draws cubes as cubes feed-forward (session 89; refitted on 1.5x the targets in session 91;
its colour step three passes since session 105, two since 92), every command's default (``"shipped"``) in sessions
92-107. ``clevr3_fc`` with a keep refiner that also corrects each slot's shape latent (``--keep --shape``), fitted for
9,000 steps to 20,736 training scenes of targets from the demo's search with shape trials (``prismonet distill clevr3_fc
... --shape-trials --search-grid 24`` on ``data/clevr3`` joined with 12,288 seed-7 scenes, ``prismonet data join``;
``clevr3_sharp_fit_log.jsonl``), applied twice, then a colour step that looks three times (``color-step --passes 3``:
1,500 steps of batch 24 on 24,576 seed-7 training images, ``clevr3_sharp_step_log.jsonl``); the whole route is
``scripts/sharp_refit.sh``, 996K images seen. Test, feed-forward: AP0.5 0.988 (0.987 unfiltered), AR0.5 0.977, allObj
0.939, mAP 0.754, PSNR 26.57 (26.52 with session 92's two-pass step, 26.47 with session 91's one-pass step), 77 % of
cubes drawn as cubes: every feed-forward target of issue 25 in one model that draws cubes; above ``clevr3`` on all of
these, 0.7 points below on the count (EVALUATION.md, sessions 91-92 and 104-105)."""
R4_MODEL = "clevr3_r4_model"
"""Every command's default (``"shipped"``, ``DEFAULT_MODEL``) since session 108: ``clevr3_sharp`` (below) with its
refiner fine-tuned on search targets of 9,216 4-object scenes (``data clevr --objects 4 --seed 7``; targets from
``clevr3_fc`` decoded with 4 slots, ``distill ... --search 3 --fit-color 50 --search-far-clip --shape-trials
--search-grid 24``), with the second-pass term and the held-out minimum kept (``prismonet refiner --fine-tune --steps
2750 --batch 16 --lr 1e-4 --holdout 512 --second-pass 1.0 --keep-best``; ``clevr3_r4_fit_log.jsonl``); the encoder and
the colour step are ``clevr3_sharp``'s bit for bit. Shipped as ``clevr4`` in session 107 (4 slots); decoded with 3 slots
since session 108, and ``clevr2``, ``clevr4`` and ``clevr5`` are these weights with 2, 4 and 5 slots. Test,
feed-forward: AP0.5 0.987 unfiltered, AR0.5 0.978, allObj 0.942, mAP 0.776, PSNR 27.06, SSIM 0.918 (``clevr3_sharp``:
0.987, 0.977, 0.939, 0.754, 26.57, 0.911), 77 % of cubes drawn as cubes: above the paper's 3/3 row on every measure
(EVALUATION.md, "Session 108")."""
DEFAULT_NAME, DEFAULT_MODEL = "clevr3_r4", R4_MODEL
"""The name and stem that ``"shipped"`` names: the default model of every command (``clevr3_r4`` since session 108;
``clevr3_sharp`` in sessions 92-107, ``clevr3`` in sessions 56-91). Names like ``"shipped"`` move when a new model
ships: a run records the weights' fingerprint."""
PHOTO_NAME = "tabletop_keep"
"""The default model of the ``real`` commands and of ``realdata``'s photo functions (since session 93): the
real-tabletop model (1-8 objects, randomised ground, light and camera, a keep refiner; ``configs/tabletop.json``,
sessions 48-72). ``"shipped"`` (``DEFAULT_NAME``) is a 3-object Clevr model of one camera and one light: on the five
labelled photos it finds 7 of 55 objects at box AP0.5 0.004 and AR0.5 0.018, this model 27 at 0.059 and 0.164 (encoder
only; EVALUATION.md, "Session 93"), so a photo command that named it by default gave nothing a user could use.
``--model shipped`` still runs it (the calibrated rig's Clevr scenes do)."""
KEEP_MODEL = "clevr3_keep_model"
"""The model shipped in sessions 47-55: the glimpse-refiner recipe of session 46 (below) with a refiner that also learns
which slots to keep (``model.refiner_keep``: a keep logit per slot, fitted to whether the search's fit shows the slot; a
dropped slot becomes inactive and renders nothing). Stage 1 ``prismonet refiner clevr3_fc ... --glimpse 0.375 --coords
--keep`` on 8,192 targets, stage 2 ``configs/clevr3_keep.json`` (its config and logs: ``clevr3_keep_config.json``,
``clevr3_keep_log.jsonl``, ``clevr3_keep_fit_log.jsonl``); applied twice, ``refine_passes`` 2."""
GLIMPSE_MODEL = "clevr3_glimpse_model"
"""The model shipped in session 46: ``clevr3_fc`` with the glimpse refiner, two stages (``configs/clevr3_glimpse.json``;
its config and logs are ``clevr3_glimpse_config.json``, ``clevr3_glimpse_log.jsonl``, ``clevr3_glimpse_fit_log.jsonl``),
applied twice."""
REFINER_MODEL = "clevr3_refiner_model"
"""The model shipped in sessions 43-45: the far-clipped distilled model with a whole-image refiner, one pass
(``configs/clevr3_refiner.json``; its config and logs are ``clevr3_refiner_config.json``, ``clevr3_refiner_log.jsonl``
and ``clevr3_refiner_fit_log.jsonl``). What ``configs/clevr3_anchor.json`` starts from."""
FC_MODEL = "clevr3_fc_model"
"""The far-clipped distilled model (shipped on 2026-11-25 before session 43; the far-clip + seek model below plus
4K steps of far clip + seek + self-distillation from its own far-clipped search targets,
``configs/clevr3_seek_distill_fc.json``): what the refiner of ``configs/clevr3_refiner.json`` was fitted to."""
SEEK_MODEL = "clevr3_seek_model"
"""The far-clip + seek model (shipped 2026-11-24 to 11-25; the self-distilled model below plus 16K steps of
``configs/clevr3_seek.json``): what ``configs/clevr3_seek_distill_fc.json`` starts from."""
DISTILLED_MODEL = "clevr3_distilled_model"
"""The self-distilled model (shipped 2026-11-23 to 11-24; the 60K-step model plus 4K steps of
``configs/clevr3_distill.json``): what ``configs/clevr3_seek.json`` starts from."""
PREVIOUS_MODEL = "clevr3_60k_model"
"""The 60K-step model (shipped until 2026-11-23; what ``configs/clevr3_distill.json`` starts from)."""
SHIPPED_SAMPLES = "samples/clevr3"
"""16 scenes of the 3-object test split (packed, split ``test``)."""


MODELS = {
    "clevr3": CLEVR3_MODEL,
    "clevr3_keep": KEEP_MODEL,
    "clevr3_fit13k": FIT13K_MODEL,
    "clevr3_color": COLOR_MODEL,
    "clevr3_r4": R4_MODEL,
    "clevr3_sharp": SHARP_MODEL,
    "clevr3_glimpse": GLIMPSE_MODEL,
    "clevr3_refiner": REFINER_MODEL,
    "clevr3_fc": FC_MODEL,
    "clevr3_60k": PREVIOUS_MODEL,
    "clevr3_seek": SEEK_MODEL,
    "clevr3_distilled": DISTILLED_MODEL,
    # clevr2, clevr4, clevr5: the default (clevr3_r4, whose refiner was fine-tuned on 4-object targets) decoded with
    # 2, 4 and 5 slots, each a model file alone that names its weights and their SHA-256 ("weights_of",
    # prismonet.model.io.weights_file)
    "clevr2": "clevr2_model",
    "clevr4": "clevr4_model",
    "clevr5": "clevr5_model",
    "blocktowers": "blocktowers_model",
    "cars": "cars_model",
    "cars_glimpse": "cars_glimpse_model",
    "cars_keep": "cars_keep_model",
    "cars_seek": "cars_seek_model",
    "cars_distill": "cars_distill_model",
    "cars_20k": "cars_20k_model",
    "chairs": "chairs_model",
    "chairs_refiner": "chairs_refiner_model",
    "chairs_depth01": "chairs_depth01_model",
    "chairs_pose_keep": "chairs_pose_keep_model",
    "tableware": "tableware_model",
    "tableware_keep": "tableware_keep_model",
    "tableware_pose_keep": "tableware_pose_keep_model",
    "clevr1to8": "clevr1to8_model",
    "clevr1to8_seek16k": "clevr1to8_seek16k_model",
    "clevr1to8_30k": "clevr1to8_30k_model",
    "clevr1to8_anchor": "clevr1to8_anchor_model",
    "clevr1to8_keep": "clevr1to8_keep_model",
    "clevr1to8_refit": "clevr1to8_refit_model",
    "clevr1to8_anchor8k": "clevr1to8_anchor8k_model",
    "tabletop": "tabletop_model",
    "tabletop_anchor": "tabletop_anchor_model",
    "tabletop_keep": "tabletop_keep_model",
    "tabletop_wide": "tabletop_wide_model",
    "blocks": "blocks_model",
    "blocks_keep": "blocks_keep_model",
}
"""Scene models by name (``load_model(NAME)``, ``--model NAME``); ``"shipped"`` is ``"clevr3_r4"``
(``DEFAULT_NAME``)."""


PRIORS = {
    "clevr": "clevr_prior",
    "cars": "cars_prior",
    "chairs": "chairs_prior",
    "tableware": "tableware_prior",
    "blocks": "blocks_prior",
}
"""Shape priors by name (``ModelConfig.prior``, ``load_prior(NAME)``); ``"shipped"`` is ``"clevr"``. ``tableware`` is
the paper's ShapeNet "tabletop" setting (mugs, bottles, cans; ``data/furniture/tabletop``): the name ``tabletop``
belongs to the randomised real-tabletop Clevr setting of ``configs/tabletop.json``. ``blocks``: the wooden blocks of
``prismonet shapes blocks`` (``prismonet.shapes.blocks``; made here, no third-party data), D_sh 8."""


MODEL_SAMPLES = {
    "clevr2": "samples/clevr2",
    "clevr4": "samples/clevr4",
    "clevr5": "samples/clevr5",
    "blocktowers": "samples/towers",
    "cars": "samples/cars",
    "cars_glimpse": "samples/cars",
    "cars_keep": "samples/cars",
    "cars_seek": "samples/cars",
    "cars_distill": "samples/cars",
    "cars_20k": "samples/cars",
    "chairs": "samples/chairs",
    "chairs_refiner": "samples/chairs",
    "chairs_depth01": "samples/chairs",
    "chairs_pose_keep": "samples/chairs",
    "tableware": "samples/tableware",
    "tableware_keep": "samples/tableware",
    "tableware_pose_keep": "samples/tableware",
    "clevr1to8": "samples/clevr1to8",
    "clevr1to8_seek16k": "samples/clevr1to8",
    "clevr1to8_30k": "samples/clevr1to8",
    "clevr1to8_anchor": "samples/clevr1to8",
    "clevr1to8_keep": "samples/clevr1to8",
    "clevr1to8_refit": "samples/clevr1to8",
    "clevr1to8_anchor8k": "samples/clevr1to8",
    "tabletop": "samples/tabletop",
    "tabletop_anchor": "samples/tabletop",
    "tabletop_keep": "samples/tabletop",
    "tabletop_wide": "samples/tabletop",
    "blocks": "samples/stacks",
    "blocks_keep": "samples/stacks",
}
"""The shipped test scenes of each model's setting (``demo --model NAME``); any other model: ``samples/clevr3``."""


def samples_for(model: str | Path) -> Path:
    """The shipped scenes that suit ``model`` (a name of ``MODELS`` or anything else: the 3-object ones)."""
    return asset_path(MODEL_SAMPLES.get(str(model), SHIPPED_SAMPLES))


def named_prior(name: str) -> Path | None:
    """The stem of the shipped prior called ``name``, or ``None``."""
    stem = PRIORS.get("clevr" if name == "shipped" else name)
    return asset_path(stem) if stem is not None and asset_path(stem + ".json").is_file() else None


def asset_path(name: str) -> Path:
    """The path of a shipped file or folder inside the installed package."""
    return Path(str(resources.files("prismonet.assets").joinpath(name)))


def shipped_model() -> Path:
    """The stem of the default scene model (``"shipped"``)."""
    return asset_path(DEFAULT_MODEL)


def shipped_samples() -> Path:
    return asset_path(SHIPPED_SAMPLES)


def model_name(name: str | Path) -> str:
    """The name a model goes by in records: ``"shipped"`` resolved to the default's name; anything else as given."""
    return DEFAULT_NAME if str(name) == "shipped" else str(name)


def model_names() -> list[str]:
    """The names of the shipped scene models whose files are installed."""
    return [n for n, stem in MODELS.items() if asset_path(stem + ".json").is_file()]


def named_model(name: str) -> Path | None:
    """The stem of the shipped model called ``name`` (``"shipped"``: the default), or ``None``."""
    stem = DEFAULT_MODEL if name == "shipped" else MODELS.get(name)
    return asset_path(stem) if stem is not None and asset_path(stem + ".json").is_file() else None
