"""The latent scene: one inferred scene as data, saved and reloaded as JSON.

A scene is what the model's encoder infers from one image: per object a pose (position, yaw as
(cos, sin), scale), a shape latent and a texture latent; the background colour; and the camera and
ground plane it was seen with. Rendering it needs the model's frozen shape prior Phi and texture
field Psi, so the file records the fingerprint of the prior it belongs to and refuses another.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, replace
from pathlib import Path

import torch

from prismonet.geometry.camera import Camera
from prismonet.render import RenderSettings, SceneParams

SCENE_FORMAT = "prismonet-latent-scene"
SCENE_VERSION = 1


class LatentSceneError(ValueError):
    """A latent-scene file or edit that is malformed or does not fit the model."""


@dataclass
class LatentScene:
    """One scene of K objects (tensors without a batch axis).

    Attributes:
        z_sh: ``(K, D_sh)``; z_tex: ``(K, D_tex)``; position: ``(K, 3)`` world; cos_sin: ``(K, 2)``;
        scale: ``(K,)``; bg_color: ``(3,)`` in [0, 1]; camera: the camera it was inferred from;
        ground_z: height of the ground plane; prior_fingerprint: the shape prior it belongs to.
    """

    z_sh: torch.Tensor
    z_tex: torch.Tensor
    position: torch.Tensor
    cos_sin: torch.Tensor
    scale: torch.Tensor
    bg_color: torch.Tensor
    camera: Camera
    ground_z: float = 0.0
    prior_fingerprint: str = ""

    def __post_init__(self) -> None:
        K = self.z_sh.shape[0] if self.z_sh.dim() == 2 else -1
        shapes = {"z_sh": (K, self.z_sh.shape[-1]), "z_tex": (K, self.z_tex.shape[-1]), "position": (K, 3),
                  "cos_sin": (K, 2), "scale": (K,), "bg_color": (3,)}
        for name, shape in shapes.items():
            t = getattr(self, name)
            if t.dim() != len(shape) or tuple(t.shape) != shape:
                raise LatentSceneError(f"{name}: expected shape {shape} (K = {K} objects), got {tuple(t.shape)}")
            if not torch.isfinite(t).all():
                raise LatentSceneError(f"{name}: contains non-finite values")

    @property
    def num_objects(self) -> int:
        return self.z_sh.shape[0]

    @property
    def yaw(self) -> torch.Tensor:
        """``(K,)`` yaw angles in radians."""
        return torch.atan2(self.cos_sin[:, 1], self.cos_sin[:, 0])

    def params(self) -> SceneParams:
        """The scene as the renderer's ``SceneParams`` (batch of one)."""
        return SceneParams(self.z_sh[None], self.z_tex[None], self.position[None], self.cos_sin[None], self.scale[None])

    def T_world_obj(self) -> torch.Tensor:
        """``(K, 4, 4)`` object-to-world similarity transforms."""
        return self.params().T_world_obj()[0]

    def select(self, keep) -> "LatentScene":
        """The scene with only objects ``keep`` (indices, in that order)."""
        idx = torch.as_tensor(list(keep), dtype=torch.long)
        return replace(self, z_sh=self.z_sh[idx], z_tex=self.z_tex[idx], position=self.position[idx],
                       cos_sin=self.cos_sin[idx], scale=self.scale[idx])

    # -- from the model -------------------------------------------------------------------
    @staticmethod
    def from_output(out, batch, index: int, prior_fingerprint: str = "", slots=None) -> "LatentScene":
        """Scene ``index`` of a model output ``out`` for the input ``batch`` (a ``SceneBatch``).

        ``slots``: the slot indices to take, in that order; by default every slot the encoder decoded
        (all, less those a stopped encoder or pruning left inactive: ``params.active`` false)."""
        p, i = out.latents.params, index
        H, W = batch.rgb.shape[-2:]
        cam = Camera(batch.K[i].detach().float(), batch.T_world_cam[i].detach().float(), int(H), int(W))
        if slots is None:
            slots = range(p.z_sh.shape[1]) if p.active is None else torch.nonzero(p.active[i]).flatten().tolist()
        idx = torch.as_tensor(list(slots), dtype=torch.long)
        d = lambda t: t[i][idx].detach().float().clone()
        return LatentScene(d(p.z_sh), d(p.z_tex), d(p.position), d(p.cos_sin), d(p.scale),
                           out.latents.bg_color[i].detach().float().clone(), cam, float(batch.ground_z[i]), prior_fingerprint)

    # -- rendering --------------------------------------------------------------------------
    def render(self, model, camera: Camera | None = None, settings: RenderSettings | None = None):
        """Render with the model's Phi and Psi from ``camera`` (default: the scene's own).

        Returns ``(Composite, obj_depth (1, K, H, W), obj_mask, obj_color (1, K, 3, H, W), bg_depth)``:
        the same pipeline as the model's forward pass, so the scene's own camera reproduces the
        model's render exactly.
        """
        from prismonet.model.refine import render_latents

        self.check_model(model)
        cam = self.camera if camera is None else camera
        dtype = self.z_sh.dtype
        o = render_latents(model, self.params(), self.bg_color[None], cam.K[None].to(dtype), cam.T_world_cam[None].to(dtype),
                           torch.tensor([self.ground_z], dtype=dtype), cam.height, cam.width, settings)
        return o.composite, o.obj_depth, o.obj_mask, o.obj_color, o.bg_depth

    def check_model(self, model) -> None:
        from prismonet.model.io import prior_fingerprint

        if self.prior_fingerprint and self.prior_fingerprint != prior_fingerprint(model.prior):
            raise LatentSceneError(f"this scene was inferred with shape prior {self.prior_fingerprint}, "
                                   f"the model has {prior_fingerprint(model.prior)}")
        if self.z_sh.shape[1] != model.sh_dim or self.z_tex.shape[1] != model.cfg.tex_dim:
            raise LatentSceneError(f"latent sizes ({self.z_sh.shape[1]}, {self.z_tex.shape[1]}) do not fit the model "
                                   f"({model.sh_dim}, {model.cfg.tex_dim})")

    # -- files ------------------------------------------------------------------------------
    def to_dict(self) -> dict:
        return {
            "format": SCENE_FORMAT, "version": SCENE_VERSION, "prior_fingerprint": self.prior_fingerprint,
            "camera": self.camera.to_dict(), "ground_z": self.ground_z, "bg_color": self.bg_color.tolist(),
            "objects": [{"position": self.position[k].tolist(), "yaw_deg": math.degrees(float(self.yaw[k])),
                         "cos_sin": self.cos_sin[k].tolist(), "scale": float(self.scale[k]),
                         "z_sh": self.z_sh[k].tolist(), "z_tex": self.z_tex[k].tolist()} for k in range(self.num_objects)],
        }

    def save(self, path: str | Path) -> Path:
        """Write the scene as JSON (atomically)."""
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(f".{path.name}.tmp")
        tmp.write_text(json.dumps(self.to_dict(), indent=1))
        tmp.replace(path)
        return path

    @staticmethod
    def from_dict(d: dict, source: str = "scene") -> "LatentScene":
        if d.get("format") != SCENE_FORMAT:
            raise LatentSceneError(f"{source}: format is {d.get('format')!r}, expected {SCENE_FORMAT!r}")
        if d.get("version") != SCENE_VERSION:
            raise LatentSceneError(f"{source}: version {d.get('version')} is not supported (expected {SCENE_VERSION})")
        try:
            objs = d["objects"]
            t = lambda key: torch.tensor([o[key] for o in objs], dtype=torch.float32)
            if not objs:
                raise LatentSceneError(f"{source}: a scene file needs at least one object")
            if not isinstance(objs, list) or not all(isinstance(o, dict) for o in objs):
                raise LatentSceneError(f"{source}: 'objects' must be a list of objects")
            scene = LatentScene(t("z_sh"), t("z_tex"), t("position"), t("cos_sin"), t("scale"),
                                torch.tensor(d["bg_color"], dtype=torch.float32), Camera.from_dict(d["camera"]),
                                float(d.get("ground_z", 0.0)), str(d.get("prior_fingerprint", "")))
            _check_scene(scene, source)
            return scene
        except (KeyError, TypeError, ValueError) as e:
            if isinstance(e, LatentSceneError):
                raise
            raise LatentSceneError(f"{source}: malformed latent scene ({type(e).__name__}: {e})") from None

    @staticmethod
    def load(path: str | Path) -> "LatentScene":
        """Read and validate a latent-scene JSON (``save``'s format)."""
        path = Path(path)
        if not path.is_file():
            raise LatentSceneError(f"{path}: no such latent-scene file")
        from prismonet.files import InputError, read_json

        try:
            d = read_json(path, dict)
        except InputError as e:
            raise LatentSceneError(str(e)) from None
        return LatentScene.from_dict(d, str(path))


def _check_scene(scene: "LatentScene", source: str) -> None:
    """Values a renderer can use: finite numbers, positive scales, a yaw direction, a rigid camera."""
    import math

    for name in ("z_sh", "z_tex", "position", "cos_sin", "scale", "bg_color"):
        if not torch.isfinite(getattr(scene, name)).all():
            raise LatentSceneError(f"{source}: {name} holds a non-finite number")
    if not math.isfinite(scene.ground_z):
        raise LatentSceneError(f"{source}: ground_z is not finite")
    if (scene.scale <= 0).any():
        raise LatentSceneError(f"{source}: every object's scale must be positive, got {scene.scale.tolist()}")
    if (scene.cos_sin.norm(dim=-1) < 1e-6).any():
        raise LatentSceneError(f"{source}: an object's cos_sin is (0, 0): no yaw direction")
    T = scene.camera.T_world_cam.double()
    R = T[:3, :3]
    if not torch.isfinite(T).all() or not torch.allclose(R @ R.T, torch.eye(3, dtype=R.dtype), atol=1e-4) or float(torch.det(R)) < 0:
        raise LatentSceneError(f"{source}: camera T_world_cam is not a rigid transform (rotation part not orthonormal)")
    if not torch.isfinite(scene.camera.K).all() or float(scene.camera.K[0, 0]) <= 0 or float(scene.camera.K[1, 1]) <= 0:
        raise LatentSceneError(f"{source}: camera K must be finite with positive focal lengths")
