"""Checkpoints as safetensors (never pickles), written atomically.

One file holds the tensors (model weights, latent codes, optimizer moments) and a JSON
metadata string (config, epoch, optimizer hyper-parameters). It is written to a temporary file
in the same folder and moved into place with ``os.replace``, so a kill leaves either the old
checkpoint or the new one, never half of one.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import torch

from prismonet.files import pid_alive

META_KEY = "prismonet"


def optimizer_tensors(opt: torch.optim.Optimizer) -> tuple[dict[str, torch.Tensor], dict]:
    """Flatten an optimizer's state into tensors plus a JSON-able description."""
    sd = opt.state_dict()
    tensors, scalars = {}, {}
    for idx, state in sd["state"].items():
        for k, v in state.items():
            if isinstance(v, torch.Tensor):
                tensors[f"optim.{idx}.{k}"] = v.detach().clone().contiguous()
            else:
                scalars[f"{idx}.{k}"] = v
    return tensors, {"param_groups": sd["param_groups"], "scalars": scalars}


def load_optimizer(opt: torch.optim.Optimizer, tensors: dict[str, torch.Tensor], desc: dict) -> None:
    state: dict[int, dict] = {}
    for key, v in tensors.items():
        if key.startswith("optim."):
            _, idx, k = key.split(".", 2)
            state.setdefault(int(idx), {})[k] = v
    for key, v in desc["scalars"].items():
        idx, k = key.split(".", 1)
        state.setdefault(int(idx), {})[k] = v
    opt.load_state_dict({"state": state, "param_groups": desc["param_groups"]})


def resume_key(config: dict, ignored: tuple[str, ...]) -> dict:
    """A run's config without the fields that may change when it resumes (``ignored``: e.g. ``steps``,
    ``threads``): two configs with equal keys train the same run."""
    return {k: v for k, v in config.items() if k not in ignored}


def save_checkpoint(path: str | Path, tensors: dict[str, torch.Tensor], meta: dict) -> None:
    """Atomically write ``tensors`` and ``meta`` (JSON-able) to one safetensors file."""
    from safetensors.torch import save_file

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    for stale in path.parent.glob(f".{path.name}.tmp-*"):  # left by a process killed while saving
        if stale.name != f".{path.name}.tmp-{os.getpid()}" and not pid_alive(stale.name.rsplit("-", 1)[-1]):
            stale.unlink(missing_ok=True)
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    try:
        save_file({k: v.detach().cpu().contiguous() for k, v in tensors.items()}, str(tmp), metadata={META_KEY: json.dumps(meta)})
        with open(tmp, "rb") as f:  # on disk before it replaces the old file: a power cut leaves one or the other
            os.fsync(f.fileno())
        os.replace(tmp, path)
        try:
            dir_fd = os.open(path.parent, os.O_RDONLY)
            try:
                os.fsync(dir_fd)
            finally:
                os.close(dir_fd)
        except OSError:
            pass  # some file systems cannot sync a folder
    finally:
        tmp.unlink(missing_ok=True)


def load_checkpoint(path: str | Path) -> tuple[dict[str, torch.Tensor], dict]:
    """Read a file written by ``save_checkpoint``: ``(tensors, meta)``."""
    from safetensors import safe_open
    from safetensors.torch import load_file

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such checkpoint")
    try:
        with safe_open(str(path), framework="pt") as f:
            meta = json.loads((f.metadata() or {}).get(META_KEY, "{}"))
        return load_file(str(path)), meta
    except Exception as e:  # safetensors raises its own error types for damaged files
        raise ValueError(f"{path}: not a readable safetensors checkpoint ({e})") from None


def save_part(path: str | Path, prefix: str, module: torch.nn.Module, opt: torch.optim.Optimizer, step: int, record: dict) -> None:
    """Atomically checkpoint one trained part of a model (``module``'s weights under ``prefix``, e.g. ``"refiner."``),
    its optimiser and the step, with the run's ``record`` (what a resume must match)."""
    t, d = optimizer_tensors(opt)
    save_checkpoint(path, {**{f"{prefix}{k}": v for k, v in module.state_dict().items()}, **t},
                    {"step": step, "record": record, "optimizer": d})


def resume_part(path: str | Path, prefix: str, module: torch.nn.Module, opt: torch.optim.Optimizer, record: dict,
                error: type[Exception] = ValueError) -> int:
    """The step a ``save_part`` checkpoint at ``path`` reached, with ``module`` and ``opt`` restored from it; 0 when there is
    none. A checkpoint of a run with another ``record`` raises ``error`` (one line: use a new folder)."""
    path = Path(path)
    if not path.is_file():
        return 0
    tensors, meta = load_checkpoint(path)
    if meta.get("record") != json.loads(json.dumps(record)):
        raise error(f"{path}: a run with other settings; use a new folder")
    module.load_state_dict({k[len(prefix):]: v for k, v in tensors.items() if k.startswith(prefix)})
    load_optimizer(opt, tensors, meta["optimizer"])
    return int(meta["step"])
