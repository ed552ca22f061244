"""The scene model: image in, object-wise 3-D scene representation and its renders out.

Objects are encoded one after another by the same encoder g_o, which sees the image, the
difference to the composition of the objects found so far, and their occlusion mask; each new
object is rendered right away so that the next step can see it (Fig. 2-3 of the paper).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import torch
from torch import nn

from prismonet.geometry.transforms import invert_similarity, transform_points
from prismonet.model.color_step import ColorStep
from prismonet.model.config import ModelConfig
from prismonet.model.encoder import ConvEncoder
from prismonet.model.pose_frame import camera_heading, centre_from_pixel, rotate_about_z
from prismonet.model.refiner import (COORD_CHANNELS, IN_CHANNELS, SlotRefiner, active_rows, apply_correction,
                                     hold_cells, on_rows, refiner_inputs, snap_shapes, split_keep)
from prismonet.model.rescue import rescue_keep
from prismonet.model.stopping import BoundStop, StopRule
from prismonet.model.texture import TextureField
from prismonet.model.unexplained import AnchorRule, find_anchors
from prismonet.render import RenderSettings, SceneParams, composite, render_objects
from prismonet.render.renderer import ObjectRender, shade_objects
from prismonet.render.background import plane_depth
from prismonet.render.composite import Composite, presence_composite
from prismonet.shapes.prior import ShapePrior, load_prior


PRESENCE_INIT_LOGIT = 3.0
"""A fresh presence output starts every slot present (sigmoid 3 = 0.95), as a model without one."""


@dataclass
class SceneLatents:
    """The inferred representation of B scenes with N slots (``params.active``: ``None``, or ``False``
    for the slots a stopped encoder never decoded)."""

    params: SceneParams
    bg_color: torch.Tensor  # (B, 3)


@dataclass
class ModelOutput:
    """Latents, the composed renders, and per-object renders (``obj_*``: ``(B, N, ...)``)."""

    latents: SceneLatents
    composite: Composite
    obj_depth: torch.Tensor
    obj_mask: torch.Tensor
    obj_color: torch.Tensor
    bg_depth: torch.Tensor
    obj_soft_mask: torch.Tensor | None = None
    """``(B, N, H, W)`` differentiable silhouettes when ``cfg.soft_mask_tau > 0``."""
    presence: torch.Tensor | None = None
    """``(B, N)`` each slot's presence probability (``cfg.presence``), else ``None``."""
    slot_steps: torch.Tensor | None = None
    """``(B, N)`` the 0-based encoder step that found each slot; ``None``: slot k is step k. Differs
    when slots were selected among more encoder steps (``prismonet.model.select``)."""
    keep_logit: torch.Tensor | None = None
    """``(B, N)`` the last refinement pass's keep logits (``cfg.refiner_keep``), else ``None``."""
    render: ObjectRender | None = None
    """The last render of all slots together (its hits), when there was one: a recolouring needs no second ray cast."""
    dropped: torch.Tensor | None = None
    """``(B, N)`` the slots the keep output dropped in the refinement passes (inactive now; their latents are the
    refiner's last for them), else ``None``. What a rescue (``cfg.refiner_rescue_px``) weighs."""

    def encoder_steps(self) -> torch.Tensor:
        """``(B, N)`` the 0-based encoder step of each slot."""
        B, N = self.obj_depth.shape[:2]
        return self.slot_steps if self.slot_steps is not None else torch.arange(N, device=self.obj_depth.device).expand(B, N)


class PriSMONet(nn.Module):
    """The PriSMONet scene model. The shape prior is frozen and kept outside the module tree
    (it is not in ``state_dict`` and is not trained)."""

    def __init__(self, cfg: ModelConfig = ModelConfig(), prior: ShapePrior | None = None) -> None:
        super().__init__()
        self.cfg = cfg
        if prior is None:
            prior = load_prior(None if cfg.prior == "shipped" else cfg.prior)
        self.__dict__["prior"] = prior.frozen()
        self.sh_dim = prior.decoder.cfg.latent_dim
        self.out_dim = self.sh_dim + cfg.tex_dim + 3 + 2 + 1 + (3 if cfg.full_rotation else 0) + (1 if cfg.presence else 0)
        self.encoder = ConvEncoder(cfg.in_channels, cfg.channels, cfg.fc, cfg.image_size, self.out_dim)
        if cfg.presence:  # the last output row: a presence logit that starts at "present" (p = 0.95)
            head = self.encoder.head[-1]
            with torch.no_grad():
                head.weight[-1].zero_()
                head.bias[-1] = PRESENCE_INIT_LOGIT
        self.bg_encoder = ConvEncoder(3, cfg.bg_channels, (64,), cfg.image_size, 3)
        self.texture = TextureField(cfg.tex_dim, cfg.texture_width, cfg.texture_depth)
        if cfg.refine_passes:
            self.refiner = SlotRefiner(self.sh_dim, cfg.tex_dim, cfg.image_size, cfg.refiner_channels, cfg.refiner_fc,
                                       cfg.refiner_coords, cfg.refiner_shape, cfg.refiner_keep,
                                       prior.latents.shape[0] if cfg.refiner_shape_codes else 0)
        if cfg.color_step:
            self.color_step = ColorStep(IN_CHANNELS + (COORD_CHANNELS if cfg.refiner_coords else 0),
                                        self.sh_dim + cfg.tex_dim + 6, cfg.tex_dim, cfg.image_size,
                                        cfg.color_step_channels, cfg.color_step_fc)
        self.register_buffer("pos_offset", torch.tensor(cfg.position_offset), persistent=False)
        self.register_buffer("pos_scale", torch.tensor(cfg.position_scale), persistent=False)

    def _apply(self, fn, recurse=True):
        """``.to(device)``, ``.cuda()`` and the like move the frozen prior with the module (it is outside the module
        tree); its dtype stays its own."""
        super()._apply(fn, recurse)
        self.__dict__["prior"] = self.prior.to(self.pos_offset.device)
        return self

    # -- pieces -------------------------------------------------------------------------
    def sdf_fn(self, z: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
        """Phi for the renderer: ``z (R, D)``, ``x (R, S, 3)`` -> ``(R, S)``."""
        return self.prior.decoder(z[:, None, :], x)

    def color_fn(self, z: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
        return self.texture(z, x)

    def shape_codes(self) -> torch.Tensor | None:
        """The prior's training codes ``(S, D_sh)`` when the refiner chooses among them (``cfg.refiner_shape_codes``),
        else ``None``."""
        return self.prior.latents if self.cfg.refiner_shape_codes else None

    def render_settings(self) -> RenderSettings:
        return RenderSettings(samples=self.cfg.render_samples, refine_steps=self.cfg.render_refine_steps,
                              far_depth=self.cfg.far_depth, soft_mask_tau=self.cfg.soft_mask_tau, box=self.prior.bounds)

    def anchor_rule(self) -> AnchorRule:
        return AnchorRule(color_tol=self.cfg.anchor_color_tol, min_area=self.cfg.anchor_min_area,
                          shade_min=self.cfg.anchor_shade_min, shade_tol=self.cfg.anchor_shade_tol,
                          gray_tol=self.cfg.anchor_gray_tol)

    def decode_latent(self, raw: torch.Tensor, K: torch.Tensor | None = None, T_world_cam: torch.Tensor | None = None,
                      ground_z: torch.Tensor | None = None, anchor_uv: torch.Tensor | None = None) -> SceneParams:
        """Split a raw encoder output ``(B, out_dim)`` into one slot's ``SceneParams`` (K = 1). A model with
        ``pose_frame = "camera"`` needs the cameras and ground heights (``prismonet.model.pose_frame``).

        ``anchor_uv (B, 2)`` (an anchored model, ``cfg.anchor``): the position outputs are the centre's pixel
        relative to that pixel, ``anchor + (S / 2) (a, b)``, and its height above the ground, as in the
        camera frame; the yaw stays in the model's ``pose_frame``."""
        d_sh, d_tex = self.sh_dim, self.cfg.tex_dim
        z_sh, z_tex, pos, cs, s = torch.split(raw[:, : d_sh + d_tex + 6], [d_sh, d_tex, 3, 2, 1], dim=1)
        lo, hi = self.cfg.scale_range
        axis = raw[:, d_sh + d_tex + 6 : d_sh + d_tex + 9][:, None] if self.cfg.full_rotation else None
        # (cos, sin) raw outputs start near 0: bias towards (1, 0) so the normalisation is well-posed
        cs = cs + torch.tensor([1.0, 0.0], dtype=cs.dtype, device=cs.device)
        if axis is not None:
            axis = axis + torch.tensor([0.0, 0.0, 1.0], dtype=axis.dtype, device=axis.device)
        if self.cfg.pose_frame == "camera" or anchor_uv is not None:  # the centre's pixel and its height
            if K is None or T_world_cam is None or ground_z is None:
                raise ValueError("a camera-frame or anchored model decodes poses with the cameras and ground heights")
            ab = pos[:, :2]
            if anchor_uv is not None:
                ab = ab + (anchor_uv - K[:, :2, 2]) / (self.cfg.image_size / 2.0)
            height = self.pos_offset[2] + self.pos_scale[2] * pos[:, 2]
            position = centre_from_pixel(ab, height, K, T_world_cam, ground_z, self.cfg.image_size, 2 * self.cfg.far_depth)
        else:
            position = self.pos_offset + self.pos_scale * pos
        if self.cfg.pose_frame == "camera":
            heading = camera_heading(T_world_cam)
            cs = rotate_about_z(cs, heading)
            axis = None if axis is None else rotate_about_z(axis[:, 0], heading)[:, None]
        return SceneParams(
            z_sh=z_sh[:, None], z_tex=z_tex[:, None],
            position=position[:, None],
            cos_sin=cs[:, None], scale=(lo + (hi - lo) * torch.sigmoid(s))[:, None, 0], axis=axis,
        )

    def presence_of(self, raw: torch.Tensor) -> torch.Tensor | None:
        """``(B,)`` the presence probability in a raw encoder output, or ``None`` without ``cfg.presence``."""
        return torch.sigmoid(raw[:, -1]) if self.cfg.presence else None

    def encoder_input(self, image: torch.Tensor, partial_image: torch.Tensor, partial_mask: torch.Tensor,
                      region: torch.Tensor | None = None) -> torch.Tensor:
        """The encoder's input channels; an anchored model also sees its anchor's region ``(B, H, W)`` bool."""
        parts = {"I": [image], "I+dI": [image, image - partial_image], "I+M": [image, partial_mask],
                 "I+dI+M": [image, image - partial_image, partial_mask]}[self.cfg.inputs]
        if region is not None:
            parts = [*parts, region[:, None].to(image.dtype)]
        return torch.cat(parts, dim=1)

    def sdf_world(self, params: SceneParams, x_world: torch.Tensor) -> torch.Tensor:
        """Signed distance in world units of each slot's shape at world points.

        ``x_world``: ``(B, K, P, 3)`` -> ``(B, K, P)``; ``s * Phi(z_sh, T_obj_world x)``.
        """
        B, K = params.scale.shape
        T_obj_world = invert_similarity(params.T_world_obj())  # (B, K, 4, 4)
        x_obj = transform_points(T_obj_world.reshape(B * K, 4, 4), x_world.reshape(B * K, -1, 3))
        f = self.prior.decoder(params.z_sh.reshape(B * K, 1, -1), x_obj)
        return (f * params.scale.reshape(B * K, 1)).reshape(B, K, -1)

    # -- the model ----------------------------------------------------------------------
    def forward(self, image: torch.Tensor, K: torch.Tensor, T_world_cam: torch.Tensor, ground_z: torch.Tensor,
                num_slots: int | None = None, stop: BoundStop | None = None, refine: bool = True,
                recolor: bool = True) -> ModelOutput:
        """Decompose images ``(B, 3, H, W)`` (cameras ``K (B, 3, 3)``, ``T_world_cam (B, 4, 4)``,
        ground heights ``(B,)``) into ``num_slots`` objects (default ``cfg.num_slots``).

        ``stop`` (``prismonet.model.stopping``): a scene stops when the slots so far explain it, or
        when a step's slot explains nothing more (that slot is dropped); its remaining slots are
        inactive (``params.active``) and cast no ray, and the loop ends when every scene has
        stopped. ``None``: all steps run.

        With ``cfg.refine_passes`` the refiner then corrects every slot that many times (``refine``
        ``False``: the encoder's slots, unrefined). With ``cfg.color_step``, at inference, the colour step then moves
        every slot's texture latent (``recolor`` ``False``, or ``refine`` ``False``: it does not).

        An anchored model (``cfg.anchor``, ``prismonet.model.unexplained``) points each step at the deepest pixel
        of the largest part of the image that the slots so far leave unexplained in colour, and sees that part;
        a part that the step's slot fails to explain is not proposed again; a scene with no part left stops
        there, in training as at inference.

        With ``cfg.presence``: in training every slot is rendered and the composite is
        ``presence_composite``; otherwise a slot whose presence is below 0.5 is dropped (inactive), and
        with ``stop`` a scene stops at its first absent slot instead of by ``stop``'s pixel rule."""
        B, C, H, W = image.shape
        if C != 3 or (H, W) != (self.cfg.image_size, self.cfg.image_size):
            raise ValueError(f"image: expected shape (B, 3, {self.cfg.image_size}, {self.cfg.image_size}), got {tuple(image.shape)}")
        N = self.cfg.num_slots if num_slots is None else num_slots
        if N <= 0:
            raise ValueError(f"num_slots must be positive, got {N}")
        bg_color = torch.sigmoid(self.bg_encoder(image))
        bg_depth = plane_depth(K, T_world_cam, H, W, ground_z, self.cfg.far_depth)
        cur_image = bg_color[:, :, None, None].expand(B, 3, H, W)
        dev = image.device
        cur_depth = torch.full((B, 1, H, W), float("inf"), dtype=image.dtype, device=dev)
        cur_mask = torch.zeros(B, 1, H, W, dtype=image.dtype, device=dev)
        slots, depths, masks, colors, softs, presences = [], [], [], [], [], []
        settings = self.render_settings()
        soft_presence = self.cfg.presence and self.training  # compose by presence; drop no slot
        gate = self.cfg.presence and not self.training  # drop absent slots, stop at them with ``stop``
        pixel_stop = stop is not None and not gate
        live = before = None
        if stop is not None or gate or self.cfg.anchor:
            live = torch.ones(B, dtype=torch.bool, device=dev)
        if pixel_stop:
            before = stop.count(cur_image, torch.minimum(cur_depth, bg_depth))
        rule = self.anchor_rule() if self.cfg.anchor else None
        failed = torch.zeros(B, H, W, dtype=torch.bool, device=dev) if self.cfg.anchor else None  # components proposed in vain
        for _ in range(N):
            if pixel_stop:
                live = live & ~stop.explained(before)
            anchors = None
            if self.cfg.anchor:
                anchors = find_anchors(image, cur_image.detach(), rule, failed)
                live = live & anchors.found
            if live is not None and not live.any():
                break
            pi, pm = (cur_image.detach(), cur_mask.detach()) if self.cfg.detach_partials else (cur_image, cur_mask)
            raw = self.encoder(self.encoder_input(image, pi, pm, None if anchors is None else anchors.region))
            params = self.decode_latent(raw, K, T_world_cam, ground_z, None if anchors is None else anchors.uv)
            p = self.presence_of(raw)
            if gate:  # an absent slot is inactive (it casts no ray); with ``stop`` its scene stops there
                present = live & (p >= 0.5)
                live = present if stop is not None else live
                params.active = present[:, None].clone()
            else:
                params.active = None if live is None else live[:, None].clone()
            obj = render_objects(self.sdf_fn, self.color_fn, params, K, T_world_cam, H, W, settings)
            d, m, c = obj.depth, obj.mask, obj.color[:, 0]  # (B, 1, H, W) x2, (B, 3, H, W)
            win = m & (d < cur_depth)
            m_seen = m  # what the next encoder step sees of this slot
            if soft_presence:  # the partial composition holds the slots more present than not
                keep = (p >= 0.5)[:, None, None, None]
                win, m_seen = win & keep, m & keep
            if pixel_stop:  # drop the slot where it explains nothing more, and stop there
                after = stop.count(torch.where(win, c, cur_image), torch.minimum(torch.where(win, d, cur_depth), bg_depth))
                live = live & stop.gained(before, after)
                before = torch.where(live[:, None], after, before)
                m, win = m & live[:, None, None, None], win & live[:, None, None, None]
                m_seen = m
                params.active = live[:, None].clone()
            presences.append(p)
            cur_image = torch.where(win, c, cur_image)
            cur_depth = torch.where(win, d, cur_depth)
            cur_mask = torch.maximum(cur_mask, m_seen.to(image.dtype))
            if anchors is not None:
                failed |= rule.failed(anchors, image, cur_image.detach())
            slots.append(params)
            depths.append(d[:, 0])
            masks.append(m[:, 0])
            colors.append(c)
            softs.append(obj.soft_mask)
        for _ in range(N - len(slots)):  # slots never decoded: inactive, empty renders
            slots.append(self._empty_slot(image, K, T_world_cam, ground_z))
            depths.append(torch.full((B, H, W), self.cfg.far_depth, dtype=image.dtype, device=dev))
            masks.append(torch.zeros(B, H, W, dtype=torch.bool, device=dev))
            colors.append(torch.zeros(B, 3, H, W, dtype=image.dtype, device=dev))
            softs.append(None if self.cfg.soft_mask_tau <= 0 else torch.zeros(B, 1, H, W, dtype=image.dtype, device=dev))
            if self.cfg.presence:
                presences.append(torch.zeros(B, dtype=image.dtype, device=dev))
        params = _cat_slots(slots)
        obj_depth, obj_mask, obj_color = torch.stack(depths, 1), torch.stack(masks, 1), torch.stack(colors, 1)
        soft = torch.cat(softs, 1) if softs[0] is not None else None
        presence = torch.stack(presences, 1) if self.cfg.presence else None
        if soft_presence:
            layer = presence
            if self.cfg.presence_straight_through:  # forward: present or not; backward: the layered gradient
                layer = (presence >= 0.5).to(presence.dtype) + presence - presence.detach()
            comp = presence_composite(obj_depth, obj_mask, obj_color, layer, bg_color, bg_depth)
            seen = layer if self.cfg.presence_in_mask_loss else layer.detach()
            soft = None if soft is None else soft * seen[:, :, None, None]  # L_mask sees present slots
        else:
            comp = composite(obj_depth, obj_mask, obj_color, bg_color, bg_depth)
        out = ModelOutput(SceneLatents(params, bg_color), comp, obj_depth, obj_mask, obj_color, bg_depth, soft, presence)
        if not refine:
            return out
        out = self.refine_slots(out, image, K, T_world_cam, ground_z)
        if self.cfg.reanchor_steps and not self.training:
            out = self.reanchor(out, image, K, T_world_cam, ground_z)
        if self.cfg.refiner_rescue_px and not self.training:
            out = self.rescue(out, image, K, T_world_cam)
        if self.cfg.color_step and recolor and not self.training:
            out = self.recolor(out, image, K, T_world_cam)
        return out

    def refine_slots(self, out: ModelOutput, image: torch.Tensor, K: torch.Tensor, T_world_cam: torch.Tensor,
                     ground_z: torch.Tensor) -> ModelOutput:
        """The model's ``cfg.refine_passes`` refinement passes (``prismonet.model.refiner``; none: ``out`` as
        it is): each corrects every active slot of ``out`` from its render against ``image``, then renders all
        again."""
        for i in range(self.cfg.refine_passes):
            out = self.refine_pass(out, image, K, T_world_cam, i)
        return out

    def refine_pass(self, out: ModelOutput, image: torch.Tensor, K: torch.Tensor, T_world_cam: torch.Tensor,
                    index: int = 0) -> ModelOutput:
        """Refinement pass ``index`` (from 0) of ``refine_slots`` on ``out``, with that pass's keep bar: what the
        passes before it hand on is what a later pass sees (``refiner_fit.second_pass_cache``)."""
        return self._refine_pass(out, image, K, T_world_cam, hold=self._holds_cells(index),
                                 keep_above=self._keep_bar(index, self.cfg.refiner_keep_logit))

    def _holds_cells(self, pass_index: int) -> bool:
        """Whether refinement pass ``pass_index`` (from 0) keeps each slot's shape in its prior code's cell
        (``cfg.refiner_hold_cells_from``)."""
        k = self.cfg.refiner_hold_cells_from
        return k is not None and pass_index >= k and not self.training

    def _keep_bar(self, pass_index: int, bar: float | None) -> float | None:
        """The keep bar of refinement pass ``pass_index`` (from 0): ``bar``, or ``None`` (no slot dropped) after the
        first ``cfg.refiner_keep_passes`` passes."""
        n = self.cfg.refiner_keep_passes
        return bar if n is None or pass_index < n else None

    def _refine_pass(self, out: ModelOutput, image: torch.Tensor, K: torch.Tensor, T_world_cam: torch.Tensor,
                     only: torch.Tensor | None = None, keep_above: float | None = 0.0,
                     hold: bool = False) -> ModelOutput:
        """One refinement pass over the active slots of ``out``, or over the slots ``only (B, N)`` bool alone (the
        others keep their latents and their activity), then a render of every active slot. A slot whose keep logit is
        not above ``keep_above`` is dropped (``apply_correction``); with ``hold`` a shape step that leaves the slot's
        prior code cell is not taken (``hold_cells``)."""
        H, W = image.shape[-2:]
        params = out.latents.params
        delta = self.on_slots(self.refiner, image, out.composite.image, out.composite.instance, out.obj_mask, params, K,
                               T_world_cam, params.active if only is None else only)
        subject = params if only is None else replace(params, active=only)
        new = apply_correction(subject, delta, self.pos_scale, self.cfg.scale_range, self.cfg.refiner_keep, keep_above,
                               self.cfg.refiner_turn, self.shape_codes())
        if hold:
            new = replace(new, z_sh=hold_cells(params.z_sh, new.z_sh, self.prior.latents))
        if self.cfg.refiner_snap_shape and not self.training:
            new = snap_shapes(new, self.prior.latents)
        if only is not None:
            before = params.active if params.active is not None else torch.ones_like(only)
            new.active = (before & ~only) | new.active  # the subjects' activity after the pass, the others' as before
        keep_logit = split_keep(delta, self.cfg.refiner_keep)[1]
        dropped = out.dropped
        if keep_logit is not None and new.active is not None:
            was = subject.active if subject.active is not None else torch.ones_like(new.active)
            lost = was & ~new.active
            dropped = lost if dropped is None else (dropped | lost) & ~new.active
        obj = self._render_changed(out, new, only, K, T_world_cam, H, W)
        comp = composite(obj.depth, obj.mask, obj.color, out.latents.bg_color, out.bg_depth)
        return ModelOutput(SceneLatents(new, out.latents.bg_color), comp, obj.depth, obj.mask, obj.color, out.bg_depth,
                           obj.soft_mask, out.presence, out.slot_steps,
                           None if keep_logit is None else keep_logit.reshape(new.scale.shape), obj, dropped)

    def _render_changed(self, out: ModelOutput, params: SceneParams, changed: torch.Tensor | None, K: torch.Tensor,
                        T_world_cam: torch.Tensor, H: int, W: int) -> ObjectRender:
        """The per-object render of ``params``, where only the slots ``changed (B, N)`` bool may differ from those
        ``out`` was rendered with (latents or activity): those are rendered again (an inactive one as empty) and every
        other slot's render is ``out``'s. Each slot is rendered on its own, so this is the render of every slot at the
        cost of the changed ones; with ``changed`` ``None``, or ``out`` without its hits, every slot is rendered."""
        settings = self.render_settings()
        if changed is None or out.render is None or (out.obj_soft_mask is not None) != (settings.soft_mask_tau > 0):
            return render_objects(self.sdf_fn, self.color_fn, params, K, T_world_cam, H, W, settings)
        active = params.active if params.active is not None else torch.ones_like(changed)
        obj = render_objects(self.sdf_fn, self.color_fn, replace(params, active=changed & active), K, T_world_cam, H, W,
                             settings)
        soft = obj.soft_mask
        if soft is not None:
            soft = torch.where(changed[:, :, None, None], soft, out.obj_soft_mask)
        r = out.render
        old = (~changed).reshape(-1)[r.hit_slot]
        hits = [torch.cat([h[old], h_new]) for h, h_new in ((r.hit_slot, obj.hit_slot), (r.hit_pix, obj.hit_pix),
                                                             (r.hit_x_obj, obj.hit_x_obj))]
        return ObjectRender(*_merged(changed, obj, out), *hits, soft_mask=soft)

    @torch.no_grad()
    def rescue(self, out: ModelOutput, image: torch.Tensor, K: torch.Tensor, T_world_cam: torch.Tensor) -> ModelOutput:
        """``out`` with the slots the keep output dropped taken back where one would show at least
        ``cfg.refiner_rescue_px`` pixels of ``image`` that the kept slots leave unexplained in colour, half of all it
        would show at least (``prismonet.model.rescue``). Only the dropped slots are rendered again."""
        if out.dropped is None or not bool(out.dropped.any()):
            return out
        p = out.latents.params
        H, W = image.shape[-2:]
        cand = out.dropped
        obj = render_objects(self.sdf_fn, self.color_fn, replace(p, active=cand), K, T_world_cam, H, W, self.render_settings())
        depth, mask, color = _merged(cand, obj, out)
        kept = rescue_keep(StopRule(min_gain=self.cfg.refiner_rescue_px), depth, mask, color, out.latents.bg_color,
                           out.bg_depth, image, None, p.active, cand)
        if torch.equal(kept, p.active):
            return out
        mask = mask & kept[:, :, None, None]
        comp = composite(depth, mask, color, out.latents.bg_color, out.bg_depth)
        render = None
        if out.render is not None:  # the kept slots' hits and those of the slots taken back: a recolouring casts no ray
            back = (kept & cand).reshape(-1)[obj.hit_slot]
            r = out.render
            render = ObjectRender(depth, mask, color, torch.cat([r.hit_slot, obj.hit_slot[back]]),
                                  torch.cat([r.hit_pix, obj.hit_pix[back]]), torch.cat([r.hit_x_obj, obj.hit_x_obj[back]]))
        return ModelOutput(SceneLatents(replace(p, active=kept), out.latents.bg_color), comp, depth, mask, color,
                           out.bg_depth, None, out.presence, out.slot_steps, out.keep_logit, render, cand & ~kept)

    @torch.no_grad()
    def reanchor(self, out: ModelOutput, image: torch.Tensor, K: torch.Tensor, T_world_cam: torch.Tensor,
                 ground_z: torch.Tensor) -> ModelOutput:
        """``cfg.reanchor_steps`` more encoder steps after refinement (see ``ModelConfig.reanchor_steps``), anchored
        where the model is: each step's slot goes into its scene's first empty slot (unanchored: the first its keep
        output dropped); a scene with none (or, anchored, nothing left unexplained) takes no step. Then the refiner's
        passes on the new slots alone."""
        out, added = self.reanchor_slots(out, image, K, T_world_cam, ground_z)
        if not added.any():
            return out
        for i in range(self.cfg.refine_passes):
            out = self._refine_pass(out, image, K, T_world_cam, only=added & out.latents.params.active,
                                    keep_above=self._keep_bar(i, self.cfg.reanchor_keep_logit),
                                    hold=self._holds_cells(i))
        return out

    @torch.no_grad()
    def reanchor_slots(self, out: ModelOutput, image: torch.Tensor, K: torch.Tensor, T_world_cam: torch.Tensor,
                       ground_z: torch.Tensor) -> tuple[ModelOutput, torch.Tensor]:
        """``reanchor``'s anchored steps without the refiner's passes: ``out`` with the new slots in place and rendered
        (``out`` itself when no scene takes a step), and ``(B, N)`` bool, the slots added. What the refiner's passes on
        the new slots see (``refiner_fit.reanchor_cache``)."""
        params = replace(out.latents.params)
        B, N = params.scale.shape
        H, W = image.shape[-2:]
        dev = image.device
        active = params.active.clone() if params.active is not None else torch.ones(B, N, dtype=torch.bool, device=dev)
        shown = out.obj_mask & active[:, :, None, None]
        cur_image = out.composite.image
        cur_depth = torch.where(shown, out.obj_depth, torch.full_like(out.obj_depth, float("inf"))).amin(1, keepdim=True)
        cur_mask = shown.any(1, keepdim=True).to(image.dtype)
        anchored = self.cfg.anchor
        rule, failed = (self.anchor_rule(), torch.zeros(B, H, W, dtype=torch.bool, device=dev)) if anchored else (None, None)
        # where a step may go: any empty slot of an anchored model (the anchors say whether anything is left); an
        # unanchored model's slots the keep output dropped, not those the encoder left empty (a stop rule's)
        room = ~active if anchored or out.dropped is None else out.dropped & ~active
        added = torch.zeros(B, N, dtype=torch.bool, device=dev)
        rows = torch.arange(B, device=dev)
        for _ in range(self.cfg.reanchor_steps):
            anchors = find_anchors(image, cur_image, rule, failed) if anchored else None
            live = room.any(1) if anchors is None else anchors.found & room.any(1)
            if not live.any():
                break
            region, uv = (None, None) if anchors is None else (anchors.region, anchors.uv)
            raw = self.encoder(self.encoder_input(image, cur_image, cur_mask, region))
            slot = self.decode_latent(raw, K, T_world_cam, ground_z, uv)
            slot.active = live[:, None].clone()
            obj = render_objects(self.sdf_fn, self.color_fn, slot, K, T_world_cam, H, W, self.render_settings())
            d, m, c = obj.depth, obj.mask, obj.color[:, 0]
            win = m & (d < cur_depth)
            cur_image = torch.where(win, c, cur_image)
            cur_depth = torch.where(win, d, cur_depth)
            cur_mask = torch.maximum(cur_mask, m.to(image.dtype))
            if anchors is not None:
                failed |= rule.failed(anchors, image, cur_image)
            k = room.to(torch.int8).argmax(1)  # each scene's first slot with room
            b, k = rows[live], k[live]
            for name in ("z_sh", "z_tex", "position", "cos_sin", "scale"):
                field = getattr(params, name).clone()
                field[b, k] = getattr(slot, name)[b, 0]
                setattr(params, name, field)
            active[b, k] = True
            room[b, k] = False
            added[b, k] = True
        if not added.any():
            return out, added
        params.active = active
        obj = self._render_changed(out, params, added, K, T_world_cam, H, W)
        comp = composite(obj.depth, obj.mask, obj.color, out.latents.bg_color, out.bg_depth)
        dropped = None if out.dropped is None else out.dropped & ~active
        return ModelOutput(SceneLatents(params, out.latents.bg_color), comp, obj.depth, obj.mask, obj.color, out.bg_depth,
                           obj.soft_mask, out.presence, out.slot_steps, out.keep_logit, obj, dropped), added

    def recolor(self, out: ModelOutput, image: torch.Tensor, K: torch.Tensor, T_world_cam: torch.Tensor) -> ModelOutput:
        """``out`` with every active slot's texture latent moved by the colour step (``cfg.color_step``,
        ``prismonet.model.color_step``) and recoloured at the same hits: depth, masks and instances are unchanged. Uses
        ``out.render`` (the last render's hits) when it has one, else casts the rays once more."""
        p = out.latents.params
        B, N = p.scale.shape
        H, W = image.shape[-2:]
        obj = out.render
        if obj is None:
            obj = render_objects(self.sdf_fn, None, p, K, T_world_cam, H, W, self.render_settings())
        new, comp = p, out.composite
        for _ in range(self.cfg.color_step_passes):  # each pass sees the image the one before it made
            step = self.on_slots(self.color_step, image, comp.image, comp.instance, out.obj_mask, new, K, T_world_cam, p.active)
            new = replace(new, z_tex=new.z_tex + step.reshape(B, N, -1))
            color = shade_objects(self.color_fn, new, obj)
            comp = composite(obj.depth, obj.mask, color, out.latents.bg_color, out.bg_depth)
        return ModelOutput(SceneLatents(new, out.latents.bg_color), comp, obj.depth, obj.mask, color, out.bg_depth,
                           obj.soft_mask, out.presence, out.slot_steps, out.keep_logit, obj, out.dropped)

    def on_slots(self, net: nn.Module, image: torch.Tensor, comp_image: torch.Tensor, instance: torch.Tensor,
                  obj_mask: torch.Tensor, params: SceneParams, K: torch.Tensor, T_world_cam: torch.Tensor,
                  active: torch.Tensor | None) -> torch.Tensor:
        """A slot network's (the refiner's or the colour step's) raw output ``(B*N, out)`` for every slot: its inputs are
        built and it runs on the ``active (B, N)`` slots only (an inactive slot's row is zero: ``apply_correction`` leaves it as it is, and
        a zero keep logit keeps it inactive), so a scene pays for the slots it uses."""
        rows = active_rows(active)
        views, latents = self.refiner_inputs(image, comp_image, instance, obj_mask, params, K, T_world_cam, rows)
        return net(views, latents) if rows is None else on_rows(net, views, latents, rows, params.scale.numel())

    def refiner_inputs(self, image: torch.Tensor, comp_image: torch.Tensor, instance: torch.Tensor, obj_mask: torch.Tensor,
                       params: SceneParams, K: torch.Tensor, T_world_cam: torch.Tensor,
                       rows: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """The refiner's views and latents of every slot (or of slot ``rows``), as its config asks
        (``refiner.refiner_inputs``)."""
        return refiner_inputs(image, comp_image, instance, obj_mask, params, self.pos_offset, self.pos_scale, K,
                              T_world_cam, self.cfg.refiner_coords, self.cfg.refiner_glimpse, rows)

    def _empty_slot(self, image: torch.Tensor, K: torch.Tensor, T_world_cam: torch.Tensor, ground_z: torch.Tensor) -> SceneParams:
        """One inactive slot per scene: the decoding of a zero encoder output, marked inactive."""
        params = self.decode_latent(torch.zeros(image.shape[0], self.out_dim, dtype=image.dtype, device=image.device), K,
                                    T_world_cam, ground_z)
        params.active = torch.zeros(image.shape[0], 1, dtype=torch.bool, device=image.device)
        return params


def _merged(changed: torch.Tensor, obj: ObjectRender, out: ModelOutput) -> tuple[torch.Tensor, ...]:
    """Per-object depth, mask and colour: ``obj``'s at the slots ``changed (B, N)`` bool, ``out``'s at the others."""
    c = changed[:, :, None, None]
    return (torch.where(c, obj.depth, out.obj_depth), torch.where(c, obj.mask, out.obj_mask),
            torch.where(c[:, :, None], obj.color, out.obj_color))


def _cat_slots(slots: list[SceneParams]) -> SceneParams:
    """Concatenate one-slot ``SceneParams`` along the slot axis; ``active`` is kept when any slot
    has it (``None`` elsewhere means active)."""
    cat = lambda name: None if getattr(slots[0], name) is None else torch.cat([getattr(p, name) for p in slots], 1)
    active = None
    if any(p.active is not None for p in slots):
        active = torch.cat([p.active if p.active is not None else torch.ones_like(p.scale, dtype=torch.bool) for p in slots], 1)
    return SceneParams(cat("z_sh"), cat("z_tex"), cat("position"), cat("cos_sin"), cat("scale"), cat("axis"), active)
