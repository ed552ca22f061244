"""Saving and loading trained scene models: ``model.safetensors`` + ``model.json``."""

from __future__ import annotations

import json
from dataclasses import asdict, replace
from pathlib import Path

import torch

from prismonet.model.config import ModelConfig


class CheckpointError(ValueError):
    """A model checkpoint that is missing, damaged, or made for another configuration."""


def weights_fingerprint(module: torch.nn.Module) -> str:
    """A short hash of a module's weights (names and float32 values)."""
    import hashlib

    h = hashlib.sha256()
    for k, v in sorted(module.state_dict().items()):
        h.update(k.encode())
        h.update(v.detach().float().cpu().numpy().tobytes())
    return h.hexdigest()[:16]


def prior_fingerprint(prior) -> str:
    """A short hash of the prior's weights: a model is only valid with the prior it was trained on."""
    return weights_fingerprint(prior.decoder)


OWN_KEYS = ("model", "prior_fingerprint", "weights_of", "note")
"""The keys of a model file that describe that model alone, never carried into a model written from it."""


def save_model(model, stem: str | Path, info: dict) -> tuple[Path, Path]:
    """Write ``stem.safetensors`` (the model's weights) and ``stem.json`` (its configuration and ``info``). ``info``
    may be the record of the model a fit or script started from, as it loaded: the keys of it that describe that model,
    not this one, are left out (``OWN_KEYS``): its ``"model"`` and ``"prior_fingerprint"`` (written anew here), its
    ``"weights_of"`` (e.g. a fine-tune of ``clevr5``, which ships as the default's weights: loading would otherwise read
    those weights instead of the ones written here) and its ``"note"`` (a shipped model's description, written when it
    ships; the start is recorded by ``"init_from"``)."""
    from prismonet.checkpoint import save_checkpoint

    stem = Path(stem)
    save_checkpoint(stem.with_suffix(".safetensors"), dict(model.state_dict()), {"kind": "prismonet_model"})
    info = {k: v for k, v in info.items() if k not in OWN_KEYS}
    desc = {"model": asdict(model.cfg), "prior_fingerprint": prior_fingerprint(model.prior), **info}
    tmp = stem.with_name(f".{stem.name}.json.tmp")
    tmp.write_text(json.dumps(desc, indent=2))
    tmp.replace(stem.with_suffix(".json"))
    return stem.with_suffix(".safetensors"), stem.with_suffix(".json")


def weights_file(stem: Path, info: dict) -> Path:
    """The ``.safetensors`` that holds a model's weights: its own, or, for a model file that names
    ``"weights_of": {"model": NAME, "sha256": HEX}``, the shipped model ``NAME``'s, checked byte for byte (a model that
    is another one's weights with other settings, e.g. the default with more slots, ships as a JSON file alone)."""
    ref = info.get("weights_of")
    if ref is None:
        return stem.with_suffix(".safetensors")
    from prismonet.assets import named_model
    from prismonet.files import sha256_file

    try:
        base, sha = named_model(str(ref["model"])), str(ref["sha256"])
    except (KeyError, TypeError):
        raise CheckpointError(f"{stem}.json: 'weights_of' must name a shipped model and its sha256, got {ref!r}") from None
    if base is None:
        raise CheckpointError(f"{stem}.json: takes the weights of {ref['model']!r}, which is not installed")
    path = base.with_suffix(".safetensors")
    if not path.is_file() or sha256_file(path) != sha:
        raise CheckpointError(f"{stem}.json: takes the weights of {ref['model']!r}, but {path.name} is not the file it was "
                              f"measured with (sha256 {sha[:12]}...): that model was shipped again")
    return path


def load_model(path: str | Path, num_slots: int | None = None):
    """Load ``(model, info)`` from a run folder, a ``.safetensors``/``.json`` path, a stem, or the name
    of a model that ships with the package (``prismonet.assets.MODELS``; ``"shipped"`` is the
    3-object Clevr model). A run folder still training loads its last checkpoint."""
    from prismonet.assets import model_names, named_model
    from prismonet.checkpoint import load_checkpoint
    from prismonet.config import _build
    from prismonet.model.prismonet import PriSMONet

    p = named_model(str(path)) or Path(path)
    stem = p / "model" if p.is_dir() else (p.with_suffix("") if p.suffix in (".safetensors", ".json") else p)
    config = stem.with_suffix(".json")
    if p.is_dir() and not config.is_file() and (p / "checkpoint.safetensors").is_file():
        return _load_training_checkpoint(p / "checkpoint.safetensors", num_slots)
    if not config.is_file():
        raise CheckpointError(f"{config}: no such model config (expected model.json beside model.safetensors); "
                              f"shipped models by name: {', '.join(['shipped'] + model_names())}")
    try:
        info = json.loads(config.read_text())
        cfg = _build(ModelConfig, info["model"], "model.")
    except (json.JSONDecodeError, KeyError, TypeError, ValueError) as e:
        raise CheckpointError(f"{config}: corrupted or incompatible model config ({e})") from None
    if num_slots is not None:
        cfg = ModelConfig(**{**asdict(cfg), "num_slots": num_slots})
    model = PriSMONet(cfg)
    if info.get("prior_fingerprint") != prior_fingerprint(model.prior):
        raise CheckpointError(f"{config}: trained with another shape prior (fingerprint {info.get('prior_fingerprint')})")
    try:
        weights = weights_file(stem, info)
        tensors, _ = load_checkpoint(weights)
    except (FileNotFoundError, ValueError) as e:
        raise CheckpointError(str(e)) from None
    load_fitting(model, tensors, str(weights))
    model.eval()
    return model, info


def _load_training_checkpoint(path: Path, num_slots: int | None):
    """``(model, info)`` from a run that is still training: its last resumable checkpoint, with the
    model configuration recorded there. ``info["checkpoint_step"]`` says which step it is."""
    from prismonet.checkpoint import load_checkpoint
    from prismonet.config import _build
    from prismonet.model.prismonet import PriSMONet

    try:
        tensors, meta = load_checkpoint(path)
        train = json.loads(meta["config"]) if isinstance(meta["config"], str) else meta["config"]
        cfg = _build(ModelConfig, train.get("model", {}), "model.")
    except (FileNotFoundError, ValueError, KeyError, TypeError) as e:
        raise CheckpointError(f"{path}: not a readable training checkpoint ({e})") from None
    if num_slots is not None:
        cfg = ModelConfig(**{**asdict(cfg), "num_slots": num_slots})
    model = PriSMONet(cfg)
    load_fitting(model, {k[len("model."):]: v for k, v in tensors.items() if k.startswith("model.")}, str(path))
    model.eval()
    return model, {"train": train, "checkpoint_step": int(meta.get("step", 0))}


def load_fitting(model, tensors: dict, where: str) -> None:
    """Load ``tensors`` into ``model`` after checking that names and shapes fit; ``CheckpointError`` if not."""
    expected = model.state_dict()
    missing = sorted(set(expected) - set(tensors))
    unexpected = sorted(set(tensors) - set(expected))
    if missing or unexpected:
        raise CheckpointError(f"{where}: does not fit this configuration (missing {missing[:3]}, unexpected {unexpected[:3]})")
    for name, t in expected.items():
        if t.shape != tensors[name].shape:
            raise CheckpointError(f"{where}: does not fit this configuration: {name} has shape "
                                  f"{tuple(tensors[name].shape)}, expected {tuple(t.shape)}")
        if tensors[name].is_floating_point() and not torch.isfinite(tensors[name]).all():
            raise CheckpointError(f"{where}: weights {name} hold NaN or infinite values")
    model.load_state_dict(tensors)


HEAD = "encoder.head.4"
"""The object encoder's output layer: rows ``[z_sh, z_tex, position 3, cos/sin 2, scale 1, axis 3?, presence 1?]``."""


def _head_rows(model) -> dict[str, range]:
    d_sh, d_tex = model.sh_dim, model.cfg.tex_dim
    rows = {"z_sh": range(0, d_sh), "z_tex": range(d_sh, d_sh + d_tex), "pose": range(d_sh + d_tex, d_sh + d_tex + 6)}
    if model.cfg.full_rotation:
        rows["axis"] = range(d_sh + d_tex + 6, d_sh + d_tex + 9)
    if model.cfg.presence:
        rows["presence"] = range(model.out_dim - 1, model.out_dim)
    return rows


def rebuilt(model, fresh: str, **fields):
    """A copy of a trained scene model with ``fields`` of its ``ModelConfig`` changed: the part whose weights start with
    ``fresh`` (``"refiner."``, ``"color_step."``) starts afresh where the new config has one (or is gone), every other
    weight is the model's. Adds, replaces or removes one learnt part of a model."""
    from prismonet.model.prismonet import PriSMONet

    new = PriSMONet(replace(model.cfg, **fields), prior=model.prior)
    own = {k: v for k, v in new.state_dict().items() if k.startswith(fresh)}
    new.load_state_dict({**{k: v for k, v in model.state_dict().items() if not k.startswith(fresh)}, **own})
    return new


def transfer_weights(model, source) -> list[str]:
    """Start ``model`` from another trained model whose latent sizes, prior or outputs differ (``init_transfer``).

    Every tensor of the same name and shape is copied: the encoders' convolutions and fully connected
    layers, and the texture field where ``D_tex`` agrees. Of the object encoder's output layer, the rows of
    the pose (position, cos/sin, scale) and of the rotation axis and the presence, where both have one, are copied; so are
    the texture-latent rows where ``D_tex`` agrees and the shape-latent rows where both use the same prior.
    The rest keeps its fresh initialisation: a latent of another prior means something else. Returns the
    names of what was left fresh.
    """
    dst, src = model.state_dict(), source.state_dict()
    fresh = []
    with torch.no_grad():
        for name, t in dst.items():
            if name.startswith(HEAD):
                continue
            if name in src and src[name].shape == t.shape:
                t.copy_(src[name])
            else:
                fresh.append(name)
        rows_dst, rows_src = _head_rows(model), _head_rows(source)
        same = {"pose": True, "axis": "axis" in rows_src, "presence": "presence" in rows_src,
                "z_tex": model.cfg.tex_dim == source.cfg.tex_dim,
                "z_sh": prior_fingerprint(model.prior) == prior_fingerprint(source.prior)}
        for key, r in rows_dst.items():
            if not same[key]:
                fresh.append(f"{HEAD} ({key} rows)")
                continue
            for part in ("weight", "bias"):
                dst[f"{HEAD}.{part}"][list(r)] = src[f"{HEAD}.{part}"][list(rows_src[key])]
    model.load_state_dict(dst)
    return fresh


def widen_weights(model, source) -> list[str]:
    """Start ``model``, a wider copy of ``source``'s architecture, as the same function (``init_widen``; Net2Net's
    zero-padding, Chen et al. 2016).

    Every tensor of ``source`` goes into the leading block of the tensor of the same name, which must be at least
    as large in every dimension. In a weight, the columns of the new inputs (new channels of the layer before,
    or of the flattened feature map, which the encoder flattens channel-major so that the new channels come last)
    are zero, so the old units compute what they did; the rows of the new units keep their fresh initialisation,
    so they train from the first step (the next layer's zero columns get gradients at once). Returns the names
    of the tensors that grew. ``CheckpointError`` when a tensor is missing or smaller than the source's.
    """
    dst, src = model.state_dict(), source.state_dict()
    unmatched = sorted(set(dst) ^ set(src))
    if unmatched:
        raise CheckpointError(f"init_widen: the two models differ in more than widths (tensors {unmatched[:3]})")
    grown = []
    with torch.no_grad():
        for name, t in dst.items():
            s = src[name]
            if t.dim() != s.dim() or any(a < b for a, b in zip(t.shape, s.shape)):
                raise CheckpointError(f"init_widen: {name} has shape {tuple(t.shape)}, smaller than the source's {tuple(s.shape)}")
            if t.shape == s.shape:
                t.copy_(s)
                continue
            grown.append(name)
            lead = tuple(slice(0, n) for n in s.shape)
            if t.dim() >= 2:  # old outputs read nothing from the new inputs
                t[: s.shape[0], s.shape[1]:] = 0
            t[lead] = s
    model.load_state_dict(dst)
    return grown


def anchor_start(model) -> None:
    """Zero the object encoder's position rows of an anchored ``model`` started from an unanchored one: there they
    held world positions, here they are offsets from the anchor, so every slot starts at its anchor."""
    r = _head_rows(model)["pose"]
    rows = list(r)[:3]
    with torch.no_grad():
        model.state_dict()[f"{HEAD}.weight"][rows] = 0.0
        model.state_dict()[f"{HEAD}.bias"][rows] = 0.0


def remap_position_outputs(model, source_cfg) -> list[int]:
    """Keep the encoder's decoded positions when ``model`` (its ``cfg.position_offset`` / ``position_scale`` new) starts
    from the weights of a model trained with ``source_cfg``'s: each decoded coordinate ``o + s * raw`` stays what it was,
    by ``raw' = (s / s') raw + (o - o') / s'`` on the head's position rows. A camera-frame or anchored model decodes only
    the height (row 2) with them; a world-frame model all three. Returns the rows changed.

    A model with a refiner is refused: its inputs and corrections are in the old units too."""
    o, s = torch.tensor(source_cfg.position_offset), torch.tensor(source_cfg.position_scale)
    o2, s2 = torch.tensor(model.cfg.position_offset), torch.tensor(model.cfg.position_scale)
    own = [2] if model.cfg.pose_frame == "camera" or model.cfg.anchor else [0, 1, 2]
    axes = [i for i in own if float(o[i]) != float(o2[i]) or float(s[i]) != float(s2[i])]
    if not axes:
        return []
    if model.cfg.refine_passes:
        raise ValueError("a new position_offset / position_scale for a model with a refiner: its inputs and corrections "
                         "are in the start model's units; fit the refiner again on the new model instead")
    first = _head_rows(model)["pose"][0]
    w, b = model.state_dict()[f"{HEAD}.weight"], model.state_dict()[f"{HEAD}.bias"]
    with torch.no_grad():
        for i in axes:
            k = float(s[i] / s2[i])
            w[first + i] *= k
            b[first + i] = k * b[first + i] + float((o[i] - o2[i]) / s2[i])
    return [first + i for i in axes]


def training_camera(model, info: dict):
    """``(Camera, ground_z)`` the model was trained with: from the checkpoint's record, or for a
    checkpoint without one, the default CLEVR camera at the model's image size."""
    import torch

    from prismonet.geometry.camera import Camera

    s = model.cfg.image_size
    if "camera_K" in info and "camera_T_world_cam" in info:
        cam = Camera(torch.tensor(info["camera_K"], dtype=torch.float32), torch.tensor(info["camera_T_world_cam"], dtype=torch.float32), s, s)
        return cam, float(info.get("ground_z", 0.0))
    from prismonet.data.clevr import ClevrConfig, clevr_camera

    return clevr_camera(ClevrConfig(image_size=s)), 0.0


def training_loss_config(info: dict):
    """The ``LossConfig`` a checkpoint was trained with (defaults for what it does not record)."""
    from prismonet.config import _build
    from prismonet.model.losses import LossConfig

    try:
        return _build(LossConfig, info.get("train", {}).get("loss", {}), "loss.")
    except (TypeError, ValueError):
        return LossConfig()
