"""Amortised refinement (beyond the paper): a learnt second look at every slot after the encoder.

The recurrent encoder places each object before it sees the ones found after it, and it never sees its
own render. The refiner ``g_r`` sees, per slot, the input image, what the composition of all slots
misses of it (``I - I_comp``), the slot's visible and full silhouettes, and the slot's latents, and
outputs a correction: a shift of the position, a turn of the yaw, a factor on the scale and a step of
the texture latent, and with ``shape`` a step of the shape latent (else the shape is left to the encoder), or, with
``shape_codes``, a choice among the prior's training codes and the slot's own latent (``choose_shapes``).
With ``keep`` it also gives a keep logit per slot, trained on whether the search's fit shows the slot: a slot it
drops becomes inactive and renders nothing (a learnt, colour-only counterpart of ``--prune``). Its last layer starts at zero, so a
fresh refiner changes nothing. It reads colour alone, as the encoder does.

It is trained to move the encoder's slots to where the test-time pose search and colour fit put them
(``prismonet.model.refiner_fit``, targets from ``prismonet.model.distill_fit``: only the input RGB-D is
read), so one pass does at the cost of one encoder step per slot and one render what the search does
with hundreds of trial renders.
"""

from __future__ import annotations

from dataclasses import replace

import torch
import torch.nn.functional as F
from torch import nn

from prismonet.geometry.camera import pixel_grid, project
from prismonet.geometry.transforms import invert_similarity, transform_points
from prismonet.model.encoder import conv_trunk
from prismonet.render import SceneParams

IN_CHANNELS = 8
"""Image (3), image minus the composition (3), the slot's visible silhouette (1) and its full silhouette (1)."""
COORD_CHANNELS = 2
"""With ``coords``: each view pixel's image position ``(u, v)``, scaled to [-1, 1] over the image."""
MAX_TURN = 0.6
"""The largest yaw correction in radians (about 34 degrees): ``tanh`` bounds it."""
MAX_LOG_SCALE = 0.4
"""The largest log-factor on the scale (a factor 0.67 to 1.49)."""
KEEP_INIT = 3.0
"""A fresh refiner's keep logit (probability 0.95): it keeps every slot, so it is still the identity."""
OWN_SHAPE_INIT = 3.0
"""With ``shape_codes``: a fresh refiner's logit for the slot's own shape latent (the others start at 0), so that it
keeps every slot's shape: the identity."""


class SlotRefiner(nn.Module):
    """``(R, 8, H, W)`` slot views and ``(R, P)`` slot latents -> ``(R, 5 + D_tex)`` corrections
    (``+ D_sh`` with ``shape``, or ``+ 1 + shape_codes`` shape logits with ``shape`` and ``shape_codes`` > 0: the slot's
    own latent first, then each prior code; ``+ 1``, a last keep logit, with ``keep``)."""

    def __init__(self, sh_dim: int, tex_dim: int, image_size: int, channels: tuple[int, ...] = (32, 32, 64, 64),
                 fc: tuple[int, ...] = (256, 256), coords: bool = False, shape: bool = False, keep: bool = False,
                 shape_codes: int = 0) -> None:
        super().__init__()
        self.tex_dim = tex_dim
        self.trunk = conv_trunk(IN_CHANNELS + (COORD_CHANNELS if coords else 0), channels)
        side = image_size // 2 ** len(channels)
        self.vec_dim = sh_dim + tex_dim + 3 + 2 + 1
        dims = [channels[-1] * side * side + self.vec_dim, *fc]
        mlp: list[nn.Module] = []
        for a, b in zip(dims[:-1], dims[1:]):
            mlp += [nn.Linear(a, b), nn.ReLU(inplace=True)]
        shape_out = (1 + shape_codes if shape_codes > 0 else sh_dim) if shape else 0
        mlp.append(nn.Linear(dims[-1], 5 + tex_dim + shape_out + (1 if keep else 0)))
        self.head = nn.Sequential(*mlp)
        self.head[-1].weight.data.zero_()  # a fresh refiner is the identity
        self.head[-1].bias.data.zero_()
        if shape and shape_codes > 0:
            self.head[-1].bias.data[5 + tex_dim] = OWN_SHAPE_INIT
        if keep:
            self.head[-1].bias.data[-1] = KEEP_INIT

    def forward(self, views: torch.Tensor, latents: torch.Tensor) -> torch.Tensor:
        h = self.trunk(views.contiguous(memory_format=torch.channels_last)).flatten(1)
        return self.head(torch.cat([h, latents], 1))


def active_rows(active: torch.Tensor | None) -> torch.Tensor | None:
    """The flat rows ``b * N + k`` of the active slots of ``active (B, N)``; ``None`` when every slot is active."""
    if active is None or bool(active.all()):
        return None
    return active.reshape(-1).nonzero().squeeze(1)


def on_rows(net: nn.Module, views: torch.Tensor, latents: torch.Tensor, rows: torch.Tensor, total: int) -> torch.Tensor:
    """``net`` on the inputs of slot ``rows`` alone, scattered into ``(total, out)`` rows with zeros elsewhere."""
    out = views.new_zeros(total, net.head[-1].out_features)
    return out.index_copy(0, rows, net(views, latents)) if len(rows) else out


def slot_views(image: torch.Tensor, comp_image: torch.Tensor, instance: torch.Tensor, obj_mask: torch.Tensor,
               rows: torch.Tensor | None = None) -> torch.Tensor:
    """``(B*N, 8, H, W)``: per slot, the image, the image minus the composition, the slot's visible
    silhouette (its id in ``instance (B, H, W)``) and its full silhouette (``obj_mask (B, N, H, W)``).
    With ``rows`` (flat slot rows ``b * N + k``), those slots' views alone, ``(len(rows), 8, H, W)``."""
    B, N, H, W = obj_mask.shape
    if rows is not None:
        b, k = rows // N, rows % N
        visible = (instance[b] == (k + 1)[:, None, None]).to(image.dtype)
        return torch.cat([image[b], (image - comp_image)[b], visible[:, None], obj_mask[b, k][:, None].to(image.dtype)], 1)
    ids = torch.arange(1, N + 1, device=instance.device)[None, :, None, None]
    visible = (instance[:, None] == ids).to(image.dtype)
    per_scene = torch.cat([image, image - comp_image], 1)[:, None].expand(B, N, 6, H, W)
    views = torch.cat([per_scene, visible[:, :, None], obj_mask[:, :, None].to(image.dtype)], 2)
    return views.reshape(B * N, IN_CHANNELS, H, W)


def unit_coords(uv: torch.Tensor, height: int, width: int) -> torch.Tensor:
    """Pixel positions ``uv (..., 2)`` scaled to [-1, 1] over a ``height x width`` image (OpenCV pixel centres;
    ``-1`` and ``1`` are the outer edges, as ``grid_sample`` with ``align_corners=False`` reads them)."""
    return (2 * uv + 1) / torch.tensor([width, height], dtype=uv.dtype, device=uv.device) - 1


def with_coords(views: torch.Tensor, uv: torch.Tensor | None = None) -> torch.Tensor:
    """``views (R, C, H, W)`` with two more channels: each pixel's image position (``unit_coords``). ``uv (R, H, W, 2)``:
    the views' own pixel positions when they are glimpses (``glimpse``), else the image's grid."""
    R, _, H, W = views.shape
    if uv is None:
        uv = pixel_grid(H, W, dtype=views.dtype, device=views.device).expand(R, H, W, 2)
    return torch.cat([views, unit_coords(uv, H, W).permute(0, 3, 1, 2)], 1)


def centre_pixels(position: torch.Tensor, K: torch.Tensor, T_world_cam: torch.Tensor) -> torch.Tensor:
    """``(B, N, 2)`` pixels where the slots' centres ``position (B, N, 3)`` (world) project; a centre behind
    the camera is taken as just in front of it."""
    x_cam = transform_points(invert_similarity(T_world_cam), position)
    x_cam = torch.cat([x_cam[..., :2], x_cam[..., 2:].clamp_min(1e-3)], -1)
    return project(x_cam, K)


def glimpse(views: torch.Tensor, centre_uv: torch.Tensor, frac: float) -> tuple[torch.Tensor, torch.Tensor]:
    """``views (R, C, H, W)`` resampled (bilinear, zeros outside) in a square window of ``frac`` times the image
    side centred on ``centre_uv (R, 2)``, at the same ``H x W``: a zoom of ``1 / frac`` onto each slot. Also
    returns the ``(R, H, W, 2)`` image pixel each view pixel samples."""
    R, _, H, W = views.shape
    local = pixel_grid(H, W, dtype=views.dtype, device=views.device) - torch.tensor([(W - 1) / 2, (H - 1) / 2], dtype=views.dtype, device=views.device)
    uv = centre_uv[:, None, None, :] + frac * local[None]  # (R, H, W, 2) image pixels
    return F.grid_sample(views, unit_coords(uv, H, W), mode="bilinear", padding_mode="zeros", align_corners=False), uv


def refiner_inputs(image: torch.Tensor, comp_image: torch.Tensor, instance: torch.Tensor, obj_mask: torch.Tensor,
                   params: SceneParams, pos_offset: torch.Tensor, pos_scale: torch.Tensor, K: torch.Tensor,
                   T_world_cam: torch.Tensor, coords: bool = False, glimpse_frac: float = 0.0,
                   rows: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """The refiner's two inputs per slot: ``slot_views`` (glimpsed around the slot's projected centre when
    ``glimpse_frac`` > 0, with position channels when ``coords``) and ``slot_latents``. With ``rows`` (flat slot
    rows, e.g. ``active_rows``) only those slots' inputs, the same values: a scene pays for the slots it uses."""
    views = slot_views(image, comp_image, instance, obj_mask, rows)
    latents = slot_latents(params, pos_offset, pos_scale)
    uv = None
    if glimpse_frac > 0:
        centre = centre_pixels(params.position, K, T_world_cam).reshape(-1, 2)
        views, uv = glimpse(views, centre if rows is None else centre[rows], glimpse_frac)
    if coords:
        views = with_coords(views, uv)
    return views, latents if rows is None else latents[rows]


def slot_latents(params: SceneParams, pos_offset: torch.Tensor, pos_scale: torch.Tensor) -> torch.Tensor:
    """``(B*N, P)``: shape and texture latents, the position in the encoder's normalised units, the
    unit (cos, sin) of the yaw and the log scale."""
    cs = params.cos_sin / params.cos_sin.norm(dim=-1, keepdim=True).clamp_min(1e-6)
    pos = (params.position - pos_offset) / pos_scale
    v = torch.cat([params.z_sh, params.z_tex, pos, cs, params.scale.clamp_min(1e-3).log()[..., None]], -1)
    return v.reshape(-1, v.shape[-1])


def split_keep(delta: torch.Tensor, keep: bool) -> tuple[torch.Tensor, torch.Tensor | None]:
    """The refiner's raw output without its keep logit, and the ``(R,)`` logit (``None`` without ``keep``)."""
    return (delta[..., :-1], delta[..., -1]) if keep else (delta, None)


def nearest_code(z: torch.Tensor, codes: torch.Tensor) -> torch.Tensor:
    """``(...)`` long: the index of the row of ``codes (S, D_sh)`` nearest each latent of ``z (..., D_sh)``
    (Euclidean; the first on a tie)."""
    flat = z.reshape(-1, z.shape[-1])
    # exact distances, as the search's shape trials take them: cdist's matmul path leaves a code ~1e-4 from itself
    d = torch.cdist(flat, codes.to(flat), compute_mode="donot_use_mm_for_euclid_dist")
    return d.argmin(1).reshape(z.shape[:-1])


def snap_shapes(params: SceneParams, codes: torch.Tensor) -> SceneParams:
    """``params`` with each slot's shape latent replaced by the nearest row of ``codes (S, D_sh)`` (Euclidean; the
    first on a tie), the prior's training codes: every slot then draws one of the prior's shapes."""
    return replace(params, z_sh=codes.to(params.z_sh)[nearest_code(params.z_sh, codes)])


def hold_cells(before: torch.Tensor, after: torch.Tensor, codes: torch.Tensor) -> torch.Tensor:
    """``(..., D_sh)``: ``after`` where the row of ``codes (S, D_sh)`` nearest it (Euclidean) is the one nearest
    ``before``, else ``before``: a shape step that would make a slot draw nearest another of the prior's shapes is not
    taken."""
    same = nearest_code(before, codes) == nearest_code(after, codes)
    return torch.where(same[..., None], after, before)


def choose_shapes(z_sh: torch.Tensor, logits: torch.Tensor, codes: torch.Tensor) -> torch.Tensor:
    """``(..., D_sh)``: per slot the slot's own ``z_sh (..., D_sh)`` where the first of its ``logits (..., 1 + S)`` is the
    largest, else the row of ``codes (S, D_sh)`` (the prior's training codes) of the largest (the first on a tie)."""
    if logits.shape[-1] != 1 + codes.shape[0]:
        raise ValueError(f"shape logits: expected 1 + {codes.shape[0]} (own latent + prior codes), got {logits.shape[-1]}")
    pick = logits.argmax(-1)
    table = codes.to(z_sh)[(pick - 1).clamp_min(0)]
    return torch.where((pick == 0)[..., None], z_sh, table)


def shape_labels(own: torch.Tensor, target: torch.Tensor, codes: torch.Tensor, tol: float = 1e-4) -> torch.Tensor:
    """``(...)`` long: the class of each target shape ``target (..., D_sh)`` for a refiner with shape codes: 0 where it is
    the slot's ``own`` latent (within ``tol``: the search kept it), else 1 + the index of the nearest of ``codes (S, D)``
    (a search's shape trial sets a code exactly)."""
    nearest = nearest_code(target, codes)
    kept = (target - own).abs().amax(-1) <= tol
    return torch.where(kept, torch.zeros_like(nearest), nearest + 1)


def apply_correction(params: SceneParams, delta: torch.Tensor, pos_scale: torch.Tensor,
                     scale_range: tuple[float, float], keep: bool = False,
                     keep_above: float | None = 0.0, turn: bool = True, codes: torch.Tensor | None = None) -> SceneParams:
    """``params`` moved by the refiner's raw output ``delta (B*N, 5 + D_tex [+ D_sh] [+ 1])``: position + ``pos_scale``
    times the first three, yaw turned by ``MAX_TURN tanh``, scale times ``exp(MAX_LOG_SCALE tanh)``
    (kept in ``scale_range``), texture latent plus the next ``D_tex``, and shape latent plus the next ``D_sh``
    when there are that many more. With ``keep`` the last value is a keep logit: a slot whose logit is not
    above ``keep_above`` (default 0) becomes inactive; ``keep_above=None`` drops none. With ``turn`` ``False`` the yaw
    stays as it is. With ``codes (S, D_sh)`` the values after the texture's are ``1 + S`` shape logits instead of a step
    (``choose_shapes``). Inactive slots keep their latents."""
    B, N = params.scale.shape
    delta, keep_logit = split_keep(delta, keep)
    d = delta.reshape(B, N, -1)
    tex_end = 5 + params.z_tex.shape[-1]
    z_sh = params.z_sh
    if codes is not None:
        z_sh = choose_shapes(z_sh, d[..., tex_end:], codes)
    elif d.shape[-1] > tex_end:
        if d.shape[-1] != tex_end + z_sh.shape[-1]:
            raise ValueError(f"refiner output of {d.shape[-1]} values: expected {tex_end} or {tex_end + z_sh.shape[-1]}")
        z_sh = z_sh + d[..., tex_end:]
    cs = params.cos_sin
    if turn:
        angle = MAX_TURN * torch.tanh(d[..., 3])
        c, s = torch.cos(angle), torch.sin(angle)
        cos_sin = torch.stack([cs[..., 0] * c - cs[..., 1] * s, cs[..., 0] * s + cs[..., 1] * c], -1)
    else:
        cos_sin = cs
    lo, hi = scale_range
    scale = (params.scale * torch.exp(MAX_LOG_SCALE * torch.tanh(d[..., 4]))).clamp(lo, hi)
    active = params.active
    if keep_logit is not None and keep_above is not None:
        kept = keep_logit.reshape(B, N) > keep_above
        active = kept if active is None else active & kept
    new = SceneParams(z_sh=z_sh, z_tex=params.z_tex + d[..., 5:tex_end], position=params.position + pos_scale * d[..., :3],
                      cos_sin=cos_sin, scale=scale, axis=params.axis, active=active)
    if params.active is not None:
        keep_old = ~params.active
        new.position = torch.where(keep_old[..., None], params.position, new.position)
        new.cos_sin = torch.where(keep_old[..., None], params.cos_sin, new.cos_sin)
        new.scale = torch.where(keep_old, params.scale, new.scale)
        new.z_tex = torch.where(keep_old[..., None], params.z_tex, new.z_tex)
        new.z_sh = torch.where(keep_old[..., None], params.z_sh, new.z_sh)
    return new
