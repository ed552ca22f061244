"""The paper's differentiable SDF renderer: per-object raycasting, then z-buffer composition.

Fast path (``render_scene``), each step leaving the result unchanged:
- rays only inside each object's projected box, and only over the ray's exact segment inside
  the box (slab test);
- the root search without autograd, in blocks of ``block_points`` SDF evaluations;
- only the two samples around the crossing re-evaluated under autograd;
- the texture field evaluated only at pixels that win the z-buffer (unless the per-object
  colours are asked for, as the recurrent encoder needs them for partial compositions);
- inactive slots and off-screen boxes cast no rays.

``render_scene_reference`` does the same with every pixel and every sample under autograd.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import torch

from prismonet.geometry.pose import T_world_obj_from_extrinsics
from prismonet.geometry.transforms import invert_similarity
from prismonet.render.composite import Composite, composite, zbuffer
from prismonet.render.raymarch import SdfFn, find_crossings, interpolate_surface, linear_root
from prismonet.render.rays import FULL_BOX, Box, object_rays

ColorFn = Callable[[torch.Tensor, torch.Tensor], torch.Tensor]
"""``color_fn(z_tex (n, D), x_obj (n, 3)) -> (n, 3)`` RGB at surface points (object frame)."""

MIN_SCALE = 1e-4
"""Scales are clamped to at least this before the pose is inverted (which divides by s^2), so a
degenerate scale gives a huge but finite object frame rather than inf/NaN."""


class RenderInputError(ValueError):
    """A renderer input of the wrong shape or dtype; names expected and received."""


@dataclass
class SceneParams:
    """Object-wise scene representation, B scenes of K slots.

    Attributes:
        z_sh: ``(B, K, D_sh)`` shape latents.  z_tex: ``(B, K, D_tex)`` texture latents.
        position: ``(B, K, 3)`` world.  cos_sin: ``(B, K, 2)``.  scale: ``(B, K)``.
        axis: optional ``(B, K, 3)`` rotation axis (full-6-DoF variant).
        active: optional ``(B, K)`` bool; inactive slots are skipped.
    """

    z_sh: torch.Tensor
    z_tex: torch.Tensor
    position: torch.Tensor
    cos_sin: torch.Tensor
    scale: torch.Tensor
    axis: torch.Tensor | None = None
    active: torch.Tensor | None = None

    def check(self) -> tuple[int, int]:
        if self.z_sh.dim() != 3:
            raise RenderInputError(f"z_sh: expected shape (B, K, D_sh), got {tuple(self.z_sh.shape)}")
        B, K = self.z_sh.shape[:2]
        expect = {
            "z_tex": (B, K, self.z_tex.shape[-1] if self.z_tex.dim() == 3 else -1),
            "position": (B, K, 3), "cos_sin": (B, K, 2), "scale": (B, K),
        }
        for name, shape in expect.items():
            t = getattr(self, name)
            if tuple(t.shape) != shape:
                raise RenderInputError(f"{name}: expected shape {shape}, got {tuple(t.shape)}")
        if self.axis is not None and tuple(self.axis.shape) != (B, K, 3):
            raise RenderInputError(f"axis: expected shape {(B, K, 3)}, got {tuple(self.axis.shape)}")
        if self.active is not None and (tuple(self.active.shape) != (B, K) or self.active.dtype != torch.bool):
            raise RenderInputError(f"active: expected bool of shape {(B, K)}, got {self.active.dtype} {tuple(self.active.shape)}")
        dtypes = {t.dtype for t in (self.z_sh, self.z_tex, self.position, self.cos_sin, self.scale)}
        if len(dtypes) != 1 or not next(iter(dtypes)).is_floating_point:
            raise RenderInputError(f"scene params: expected one floating dtype, got {sorted(map(str, dtypes))}")
        devices = {t.device for t in (self.z_sh, self.z_tex, self.position, self.cos_sin, self.scale)}
        if len(devices) != 1:
            raise RenderInputError(f"scene params: expected one device, got {sorted(map(str, devices))}")
        return B, K

    def T_world_obj(self) -> torch.Tensor:
        return T_world_obj_from_extrinsics(self.position, self.cos_sin, self.scale.clamp_min(MIN_SCALE), self.axis)


@dataclass(frozen=True)
class RenderSettings:
    """Renderer settings."""

    samples: int = 12
    """Equidistant SDF samples per ray (the paper: 12)."""
    refine_steps: int = 0
    """Bisection steps on the bracket after the search (no autograd); 2-4 cut the depth error 20-300x."""
    interval: str = "ray"
    """``"ray"``: each ray's exact segment inside the object's box; ``"object"``: the box's depth range."""
    far_depth: float = 12.0
    """Depth given to a pixel where an object is missed (the paper's "large constant")."""
    block_points: int = 0
    """SDF evaluations per block in the no-grad search (0: by device, ``raymarch.search_plan``: 16384 on the CPU,
    2M on an accelerator)."""
    search_chunk: int = 0
    """Samples per ray evaluated at a time in the search (0: by device, ``raymarch.search_plan``: 4 on the CPU, all
    on an accelerator); ``>= samples`` evaluates all at once. Same result either way."""
    soft_mask_tau: float = 0.0
    """If > 0, also render differentiable soft silhouettes: 1 on hits, sigmoid(-s f_min / tau) on
    rays that miss, with f_min the least SDF along the ray (world units, tau too). For L_mask."""
    box: Box = FULL_BOX
    """Object-frame box ``(lo, hi)`` the shapes lie in: the padded cube, or a prior's tighter
    ``ShapePrior.bounds``; rays are cast and sampled only inside it."""


@dataclass
class ObjectRender:
    """Per-object renders of B scenes with K slots.

    Attributes:
        depth: ``(B, K, H, W)`` camera z, ``far_depth`` where missed.  mask: ``(B, K, H, W)`` bool.
        color: ``(B, K, 3, H, W)`` or ``None`` when colours were only computed for z-buffer winners.
        hit_slot, hit_pix: ``(n,)`` flattened slot (``b*K + k``) and pixel of every hit.
        hit_x_obj: ``(n, 3)`` surface points in the object frame (with gradients).
        stats: ray and SDF-evaluation counts.
        soft_mask: ``(B, K, H, W)`` soft silhouettes, or ``None`` (see ``RenderSettings.soft_mask_tau``).
    """

    depth: torch.Tensor
    mask: torch.Tensor
    color: torch.Tensor | None
    hit_slot: torch.Tensor
    hit_pix: torch.Tensor
    hit_x_obj: torch.Tensor
    stats: dict = field(default_factory=dict)
    soft_mask: torch.Tensor | None = None


def _check_camera(K: torch.Tensor, T_world_cam: torch.Tensor, B: int, dtype) -> None:
    if tuple(K.shape) != (B, 3, 3):
        raise RenderInputError(f"K: expected shape {(B, 3, 3)}, got {tuple(K.shape)}")
    if tuple(T_world_cam.shape) != (B, 4, 4):
        raise RenderInputError(f"T_world_cam: expected shape {(B, 4, 4)}, got {tuple(T_world_cam.shape)}")
    if K.dtype != dtype or T_world_cam.dtype != dtype:
        raise RenderInputError(f"camera: expected dtype {dtype} like the scene params, got {K.dtype} and {T_world_cam.dtype}")


def _frames(params: SceneParams, T_world_cam: torch.Tensor):
    B, K = params.z_sh.shape[:2]
    T_world_obj = params.T_world_obj()  # (B, K, 4, 4)
    T_obj_cam = invert_similarity(T_world_obj) @ T_world_cam[:, None]
    T_cam_obj = invert_similarity(T_world_cam)[:, None] @ T_world_obj
    return T_obj_cam.reshape(B * K, 4, 4), T_cam_obj.reshape(B * K, 4, 4)


def _active(params: SceneParams, B: int, K: int) -> torch.Tensor:
    return torch.ones(B * K, dtype=torch.bool, device=params.z_sh.device) if params.active is None else params.active.reshape(-1)


def _cast(params: SceneParams, K: torch.Tensor, T_world_cam: torch.Tensor, height: int, width: int,
          settings: RenderSettings, cull: bool):
    """Checks, object frames (with gradients) and the rays of every active slot (detached)."""
    B, Kslots = params.check()
    _check_camera(K, T_world_cam, B, params.z_sh.dtype)
    T_obj_cam, T_cam_obj = _frames(params, T_world_cam)
    Kn = K[:, None].expand(B, Kslots, 3, 3).reshape(B * Kslots, 3, 3)
    rays = object_rays(T_obj_cam.detach(), T_cam_obj.detach(), Kn, _active(params, B, Kslots), height, width,
                       cull=cull, interval=settings.interval, box=settings.box)
    return B, Kslots, T_obj_cam, rays, params.z_sh.reshape(B * Kslots, -1)


def _object_render(params: SceneParams, color_fn: ColorFn | None, slot, pix, t_star, x_obj, shape, far_depth, stats) -> ObjectRender:
    """Scatter the hits into dense per-object depth, mask and (optionally) colour images."""
    B, Kslots, H, W = shape
    flat = slot * (H * W) + pix
    n = B * Kslots * H * W
    depth = torch.full((n,), far_depth, dtype=t_star.dtype, device=t_star.device).index_put((flat,), t_star)
    mask = torch.zeros(n, dtype=torch.bool, device=t_star.device).index_put((flat,), torch.ones_like(flat, dtype=torch.bool))
    out = ObjectRender(depth.reshape(B, Kslots, H, W), mask.reshape(B, Kslots, H, W), None, slot, pix, x_obj, stats)
    if color_fn is not None:
        out.color = shade_objects(color_fn, params, out)
    return out


def shade_objects(color_fn: ColorFn, params: SceneParams, obj: ObjectRender) -> torch.Tensor:
    """Per-object colours ``(B, K, 3, H, W)``: the texture field of ``params.z_tex`` at every hit of
    ``obj`` (zero where an object is missed). With ``obj``'s own latents this is ``obj.color``; with
    other texture latents it recolours the same geometry without casting a ray."""
    B, Kslots, H, W = obj.depth.shape
    rgb = color_fn(params.z_tex.reshape(B * Kslots, -1)[obj.hit_slot], obj.hit_x_obj)
    color = torch.zeros(B * Kslots * H * W, 3, dtype=rgb.dtype, device=rgb.device).index_put((obj.hit_slot * (H * W) + obj.hit_pix,), rgb)
    return color.reshape(B, Kslots, H, W, 3).permute(0, 1, 4, 2, 3)


def render_objects(
    sdf_fn: SdfFn, color_fn: ColorFn | None, params: SceneParams, K: torch.Tensor, T_world_cam: torch.Tensor,
    height: int, width: int, settings: RenderSettings = RenderSettings(),
) -> ObjectRender:
    """Raycast every active slot (fast path). Colours per object if ``color_fn`` is given."""
    B, Kslots, T_obj_cam, rays, z_sh = _cast(params, K, T_world_cam, height, width, settings, cull=True)
    A = T_obj_cam[:, :3, :3]
    o_all = T_obj_cam[:, :3, 3]
    # the search (detached)
    o_r = o_all.detach()[rays.obj]
    d_r = torch.einsum("rij,rj->ri", A.detach()[rays.obj], rays.d_cam)
    soft = settings.soft_mask_tau > 0
    cr = find_crossings(sdf_fn, z_sh.detach()[rays.obj], o_r, d_r, rays.t_near, rays.t_far,
                        settings.samples, settings.refine_steps, settings.block_points, track_min=soft,
                        chunk=settings.search_chunk)
    # the differentiable part: two SDF evaluations per hit ray
    slot = rays.obj[cr.ray]
    pix = rays.pix[cr.ray]
    o_h = o_all[slot]
    d_h = torch.einsum("rij,rj->ri", A[slot], rays.d_cam[cr.ray])
    t_star = interpolate_surface(sdf_fn, z_sh[slot], o_h, d_h, cr.t_a, cr.t_b)
    x_obj = o_h + t_star[:, None] * d_h
    stats = {"rays": len(rays), "hits": int(slot.numel()), "sdf_evals": cr.sdf_evals + 2 * int(slot.numel())}
    out = _object_render(params, color_fn, slot, pix, t_star, x_obj, (B, Kslots, height, width), settings.far_depth, stats)
    if soft:
        # one autograd SDF evaluation per missed ray, at its sample of least SDF
        mslot = rays.obj[cr.miss_ray]
        x_min = o_all[mslot] + cr.t_min[:, None] * torch.einsum("rij,rj->ri", A[mslot], rays.d_cam[cr.miss_ray])
        f_world = sdf_fn(z_sh[mslot], x_min[:, None, :])[:, 0] * params.scale.reshape(-1).clamp_min(MIN_SCALE)[mslot]
        HW = height * width
        dense = torch.zeros(B * Kslots * HW, dtype=t_star.dtype, device=t_star.device)
        dense = dense.index_put((slot * HW + pix,), torch.ones_like(t_star))
        dense = dense.index_put((mslot * HW + rays.pix[cr.miss_ray],), torch.sigmoid(-f_world / settings.soft_mask_tau))
        out.soft_mask = dense.reshape(B, Kslots, height, width)
        out.stats["sdf_evals"] += int(mslot.numel())
    return out


def winning_hits(obj: ObjectRender, winner: torch.Tensor, hit: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``(n,)`` each hit of ``obj``'s scene, and whether it wins the z-buffer (``zbuffer``'s ``winner``, ``hit``)."""
    B, Kslots = obj.depth.shape[:2]
    b, k = obj.hit_slot // Kslots, obj.hit_slot % Kslots
    return b, hit.reshape(B, -1)[b, obj.hit_pix] & (winner.reshape(B, -1)[b, obj.hit_pix] == k)


def shade_winners(color_fn: ColorFn, params: SceneParams, obj: ObjectRender, bg_color: torch.Tensor, winner, hit) -> torch.Tensor:
    """Image ``(B, 3, H, W)``: the texture field evaluated only at the hits that win the z-buffer."""
    B, Kslots, H, W = obj.depth.shape
    b, win = winning_hits(obj, winner, hit)
    rgb = color_fn(params.z_tex.reshape(B * Kslots, -1)[obj.hit_slot[win]], obj.hit_x_obj[win])
    image = bg_color[:, None, :].expand(B, H * W, 3).reshape(-1, 3)
    image = image.index_put((b[win] * H * W + obj.hit_pix[win],), rgb)
    return image.reshape(B, H, W, 3).permute(0, 3, 1, 2)


def render_scene(
    sdf_fn: SdfFn, color_fn: ColorFn, params: SceneParams, bg_color: torch.Tensor, bg_depth: torch.Tensor,
    K: torch.Tensor, T_world_cam: torch.Tensor, settings: RenderSettings = RenderSettings(), per_object_color: bool = False,
) -> tuple[Composite, ObjectRender]:
    """Render and compose a scene (fast path).

    Args:
        sdf_fn, color_fn: Phi and Psi as callables (see ``SdfFn``, ``ColorFn``).
        params: the object-wise scene representation.
        bg_color: ``(B, 3)``; bg_depth: ``(B, 1, H, W)`` depth of the known ground plane.
        K, T_world_cam: ``(B, 3, 3)``, ``(B, 4, 4)``.
        per_object_color: also colour every object's hits (needed for partial compositions,
            ``composite(..., upto=i)``); otherwise Psi runs only at z-buffer winners.
    """
    B, _ = params.check()
    if bg_depth.dim() != 4 or bg_depth.shape[:2] != (B, 1):
        raise RenderInputError(f"bg_depth: expected shape (B={B}, 1, H, W), got {tuple(bg_depth.shape)}")
    if tuple(bg_color.shape) != (B, 3):
        raise RenderInputError(f"bg_color: expected shape {(B, 3)}, got {tuple(bg_color.shape)}")
    H, W = bg_depth.shape[-2:]
    obj = render_objects(sdf_fn, color_fn if per_object_color else None, params, K, T_world_cam, H, W, settings)
    if per_object_color:
        return composite(obj.depth, obj.mask, obj.color, bg_color, bg_depth), obj
    winner, hit = zbuffer(obj.depth, obj.mask)
    depth = torch.where(hit[:, None], torch.gather(obj.depth, 1, winner[:, None]), bg_depth)
    image = shade_winners(color_fn, params, obj, bg_color, winner, hit)
    instance = torch.where(hit, winner + 1, torch.zeros_like(winner))
    return Composite(image, depth, hit[:, None].to(image.dtype), instance), obj


def render_scene_reference(
    sdf_fn: SdfFn, color_fn: ColorFn, params: SceneParams, bg_color: torch.Tensor, bg_depth: torch.Tensor,
    K: torch.Tensor, T_world_cam: torch.Tensor, settings: RenderSettings = RenderSettings(),
) -> tuple[Composite, ObjectRender]:
    """The straightforward renderer: every pixel of every slot, every sample under autograd.

    Same sample positions and interpolation as the fast path (no refinement), so the two agree
    up to float rounding, in values and gradients.
    """
    H, W = bg_depth.shape[-2:]
    B, Kslots, T_obj_cam, rays, z_sh = _cast(params, K, T_world_cam, H, W, settings, cull=False)
    A = T_obj_cam[:, :3, :3]
    o = T_obj_cam[rays.obj, :3, 3]
    d = torch.einsum("rij,rj->ri", A[rays.obj], rays.d_cam)
    frac = torch.linspace(0.0, 1.0, settings.samples, dtype=o.dtype, device=o.device)
    t = rays.t_near[:, None] + (rays.t_far - rays.t_near)[:, None] * frac  # (R, S) constants
    f = sdf_fn(z_sh[rays.obj], o[:, None, :] + t[..., None] * d[:, None, :])  # (R, S) under autograd
    pos = f.detach() > 0
    change = pos[:, :-1] & ~pos[:, 1:]
    has = change.any(1)
    j = change.to(torch.uint8).argmax(1)
    rows = torch.nonzero(has, as_tuple=False).flatten()
    jr = j[rows]
    t_star = linear_root(t[rows, jr], t[rows, jr + 1], f[rows, jr], f[rows, jr + 1])
    x_obj = o[rows] + t_star[:, None] * d[rows]
    stats = {"rays": len(rays), "hits": int(rows.numel()), "sdf_evals": len(rays) * settings.samples}
    obj = _object_render(params, color_fn, rays.obj[rows], rays.pix[rows], t_star, x_obj, (B, Kslots, H, W), settings.far_depth, stats)
    return composite(obj.depth, obj.mask, obj.color, bg_color, bg_depth), obj
