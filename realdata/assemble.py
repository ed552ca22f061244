"""One 3-D scene from a photo read in tiles.

Each tile of an uncalibrated photo is decoded as a photo of its own, seen by the model's camera (``realdata.tiles``):
its objects sit in that tile's own world. The photo as a whole is taken to be seen by the same camera over a square
*view* of the photo (the square around the tiled region). A tile is a zoomed part of that view, and an object found
in it is moved into the view's world so that it looks the same from there:

- its centre's pixel in the tile goes, through the photo, to a pixel of the view;
- it lies on the view's ray through that pixel, at the depth ``d`` where the object, scaled by
  ``zoom (d / d_tile)`` (``zoom`` = the tile's side over the view's, so that it covers as many photo pixels as in
  the tile), keeps its height above the ground in proportion:
  ``o_z + d r_z = ground_z + h_tile zoom d / d_tile`` (``o`` the camera centre, ``r`` the ray with unit camera depth);
- its yaw, shape and texture latents are kept (the two cameras share their heading).

A tile that is the view itself maps every object onto itself. This assumes what the tiles already assume (one
camera, objects resting on one plane). It places objects where the photo shows them and sizes them consistently;
it does not recover the photo's true camera.
"""

from __future__ import annotations

import torch


def view_box(region: tuple[int, int, int, int]) -> tuple[int, int, int, int]:
    """The square ``(x0, y0, side, side)`` centred on a region ``(x0, y0, w, h)``, its side the region's longer side."""
    x, y, w, h = (int(v) for v in region)
    side = max(w, h)
    return x + (w - side) // 2, y + (h - side) // 2, side, side


def tile_to_view(position: torch.Tensor, scale: torch.Tensor, camera, ground_z: float,
                 tile: tuple[int, int, int, int], view: tuple[int, int, int, int]) -> tuple[torch.Tensor, torch.Tensor]:
    """Positions ``(K, 3)`` and scales ``(K,)`` of objects found in ``tile`` (photo pixels ``x0, y0, side, side``),
    seen there by ``camera`` (the model's camera at its input size), moved into the world of the same camera seen over
    ``view``: ``(position, scale)`` there."""
    pos, s = position.double(), scale.double()
    K, T = camera.K.double(), camera.T_world_cam.double()
    R, o = T[:3, :3], T[:3, 3]
    S = float(camera.width)
    pc = (pos - o) @ R  # camera coordinates (R^T (p - o))
    d_tile = pc[:, 2]
    uv = (pc @ K.T)[:, :2] / d_tile[:, None]
    tx, ty, ts, _ = tile
    vx, vy, vs, _ = view
    photo = torch.stack([tx + (uv[:, 0] + 0.5) * ts / S, ty + (uv[:, 1] + 0.5) * ts / S], 1) - 0.5
    uv_v = torch.stack([(photo[:, 0] - vx + 0.5) * S / vs, (photo[:, 1] - vy + 0.5) * S / vs], 1) - 0.5
    ray_cam = torch.cat([uv_v, torch.ones_like(uv_v[:, :1])], 1) @ torch.linalg.inv(K).T  # camera depth 1
    r = ray_cam @ R.T
    zoom = ts / vs
    h = pos[:, 2] - ground_z
    d = (ground_z - o[2]) / (r[:, 2] - h * zoom / d_tile)
    new_pos = o + d[:, None] * r
    return new_pos.to(position.dtype), (s * zoom * d / d_tile).to(scale.dtype)


def assemble_scene(tile_scenes: dict, tiles: list[tuple[int, int, int, int]], picks: list[tuple[int, int]],
                   view: tuple[int, int, int, int]):
    """A ``LatentScene`` of the objects ``picks`` (at least one; ``(tile index, object index in that tile's scene)``),
    moved from their tiles into ``view``'s world; ``tile_scenes``: ``{tile index: LatentScene}`` for those tiles. It is
    seen by the tiles' camera over the view, with the mean of those tiles' background colours."""
    from dataclasses import replace

    if not picks:
        raise ValueError("assemble_scene: no objects to assemble")
    parts = []
    for t, k in picks:
        sc = tile_scenes[t].select([k])
        pos, scale = tile_to_view(sc.position, sc.scale, sc.camera, sc.ground_z, tiles[t], view)
        parts.append(replace(sc, position=pos, scale=scale))
    cat = lambda name: torch.cat([getattr(p, name) for p in parts])
    return replace(parts[0], z_sh=cat("z_sh"), z_tex=cat("z_tex"), position=cat("position"), cos_sin=cat("cos_sin"), scale=cat("scale"),
                   bg_color=torch.stack([tile_scenes[t].bg_color for t in sorted({t for t, _ in picks})]).mean(0))
