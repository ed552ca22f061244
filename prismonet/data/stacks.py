"""Stacks of mixed wooden blocks (``prismonet.shapes.blocks``): the block-tower setting with the blocks of a
real block photo (boxes of many proportions, hexagonal prisms, wedges) instead of equal cubes.

A scene holds ``min_objects .. num_objects`` blocks (uniform), dealt into ``1 .. max_towers`` stacks
(``prismonet.data.towers``' rule, dealt again where a stack would be taller than ``MAX_LEVELS`` or the stacks do not
fit apart; a stack of one block stands on the ground). Each block has its own shape,
scale and CLEVR colour. A block above another rests on the lower one's flat top (only boxes and hexagonal
prisms have one; a wedge can only crown a stack), its centre shifted by up to ``offset`` x the lower top's
half-extents, and turned freely. A stack is kept only when it balances: for every block, the centre of mass of
it and the blocks above (masses by volume) lies inside the top face it rests on, shrunk by ``margin`` towards
that face's centre. Stacks keep ``min_gap`` apart. With ``cfg.towers.platform_share``, that share of scenes is
built around a platform: a wide, low block (``platforms``) at ``cfg.towers.platform_scale``, carrying one or two short
stacks (1 to 4 blocks in all), as the slab of a real block photo carries a board, a
bar and a cube; the other blocks stand on the ground around it. With ``cfg.randomize``, each scene draws its camera, ground
colour and light as the Clevr generator's (``prismonet.data.clevr.sample_conditions``).
"""

from __future__ import annotations

import math

import numpy as np

from prismonet.data.clevr import ClevrConfig, ObjectSpec, SceneSpec, sample_conditions
from prismonet.data.errors import PlacementError
from prismonet.data.towers import MAX_TOWER_TRIES, deal
from prismonet.geometry.camera import Camera
from prismonet.shapes.blocks import top_face, volume
from prismonet.shapes.library import shape_library

MAX_LEVELS = 3
"""Blocks per stack at most (a deal with a taller stack is dealt again): a real toy-block scene, such as the shipped
``blox.jpg`` (a slab carrying a board and a bar), is rarely taller, and a taller stack leaves the camera's view."""


def _rot(yaw: float) -> np.ndarray:
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, -s], [s, c]])


def inside_convex(p: np.ndarray, poly: np.ndarray) -> bool:
    """Whether the point ``p`` (2,) lies in the convex polygon ``poly (n, 2)`` (counter-clockwise), edges included."""
    a, b = poly, np.roll(poly, -1, axis=0)
    cross = (b[:, 0] - a[:, 0]) * (p[1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (p[0] - a[:, 0])
    return bool((cross >= -1e-12).all())


def world_top(category: str, half_extents, scale: float, xy: np.ndarray, yaw: float) -> np.ndarray | None:
    """A block's flat top in world xy ``(n, 2)``, or ``None`` (a wedge)."""
    top = top_face(category, half_extents)
    return None if top is None else (scale * top) @ _rot(yaw).T + xy


def stack_balances(blocks: list[dict], margin: float) -> bool:
    """Whether a stack (bottom to top; each block a dict with ``category``, ``half_extents``, ``scale``, ``xy``,
    ``yaw``) balances: for each block above the first, the centre of mass of it and every block above lies
    inside the top of the block below, shrunk by ``margin`` towards that top's centre."""
    mass = np.array([volume(b["category"], b["half_extents"]) * b["scale"] ** 3 for b in blocks])
    xy = np.array([b["xy"] for b in blocks])
    for i in range(1, len(blocks)):
        below = blocks[i - 1]
        top = world_top(below["category"], below["half_extents"], below["scale"], np.asarray(below["xy"]), below["yaw"])
        if top is None:
            return False
        com = (mass[i:, None] * xy[i:]).sum(0) / mass[i:].sum()
        centre = top.mean(0)
        if not inside_convex(com, centre + (1.0 - margin) * (top - centre)):
            return False
    return True


def _one_stack(rng: np.random.Generator, cfg: ClevrConfig, height: int, base: dict | None = None,
               spread: float | None = None) -> list[dict]:
    """A balancing stack of ``height`` blocks with its base in the placement area, or, given ``base`` (a block with a
    flat top), resting on that block's top, shifted by up to ``spread`` x its half-extents (the stack and ``base``
    together balance)."""
    lib = shape_library(cfg.shapes, cfg.shape_split)
    flat = [s for s in lib.specs if top_face(s.category, s.half_extents) is not None]
    if height > 1 and not flat:
        raise PlacementError(f"{cfg.shapes}: no block with a flat top, so nothing can be stacked")
    t = cfg.towers
    for _ in range(MAX_TOWER_TRIES):
        blocks: list[dict] = []
        for level in range(height):
            pool = flat if level < height - 1 else lib.specs
            spec = pool[int(rng.integers(len(pool)))]
            scale = float(rng.uniform(*cfg.scale_range))
            yaw = float(rng.uniform(-math.pi, math.pi))
            below = blocks[-1] if blocks else base
            if below is None:
                xy = rng.uniform(-cfg.area_half, cfg.area_half, 2)
                z = scale * spec.half_extents[2]
            else:
                frac = t.offset if blocks else spread
                reach = below["scale"] * np.asarray(below["half_extents"][:2]) * frac
                xy = np.asarray(below["xy"]) + _rot(below["yaw"]) @ (rng.uniform(-1.0, 1.0, 2) * reach)
                z = below["z"] + below["scale"] * below["half_extents"][2] + scale * spec.half_extents[2]
            blocks.append({"spec": spec, "category": spec.category, "half_extents": spec.half_extents, "scale": scale,
                           "xy": xy, "yaw": yaw, "z": z})
        if stack_balances(([] if base is None else [base]) + blocks, t.margin):
            return blocks
    raise PlacementError(f"could not build a balancing stack of {height} blocks in {MAX_TOWER_TRIES} tries "
                         f"(offset {t.offset}, margin {t.margin}: lower the offset)")


PLATFORM_SPREAD = 0.6
"""How far a stack on a platform may stand from the platform's centre, in the platform's half-extents."""

PLATFORM_MAX_HEIGHT = 0.3
"""A platform is a block whose flat top is wide and low: half-height at most this share of its longest half-extent,
and a top at least half as deep as it is wide."""


def platforms(cfg: ClevrConfig) -> list:
    """The block set's shapes that may serve as a platform (``PLATFORM_MAX_HEIGHT``)."""
    lib = shape_library(cfg.shapes, cfg.shape_split)
    return [s for s in lib.specs if top_face(s.category, s.half_extents) is not None
            and s.half_extents[2] <= PLATFORM_MAX_HEIGHT * max(s.half_extents[:2])
            and min(s.half_extents[:2]) >= 0.5 * max(s.half_extents[:2])]


def _group_disc(blocks: list[dict]) -> tuple[np.ndarray, float]:
    """The disc on the ground (centre, radius) that holds a group of blocks' footprints, centred on the first."""
    centre = np.asarray(blocks[0]["xy"])
    return centre, max(float(np.linalg.norm(np.asarray(b["xy"]) - centre)) + b["scale"] * b["spec"].footprint_radius()
                       for b in blocks)


PLACE_TRIES = 20
"""Layouts tried for one deal of the blocks into stacks before it is dealt again."""


def _stacks_apart(rng: np.random.Generator, cfg: ClevrConfig, heights: list[int], discs: list,
                  base: dict | None = None) -> list[list[dict]] | None:
    """Stacks of the given heights, on the ground or on ``base``'s top, whose footprint discs keep ``cfg.min_gap`` apart
    from each other and from ``discs`` (extended with theirs), or ``None`` at the first one that does not."""
    stacks = []
    for h in heights:
        blocks = _one_stack(rng, cfg, h, base=base, spread=None if base is None else PLATFORM_SPREAD)
        centre, radius = _group_disc(blocks)
        if any(np.linalg.norm(centre - c) < radius + r + cfg.min_gap for c, r in discs):
            return None
        stacks.append(blocks)
        discs.append((centre, radius))
    return stacks


def _platform(rng: np.random.Generator, cfg: ClevrConfig, heights: list[int]) -> list[list[dict]] | None:
    """A platform on the ground carrying stacks of the given heights apart from each other (each balancing on it), or
    ``None`` after ``PLACE_TRIES`` layouts. The platform is the first stack returned, alone."""
    pool = platforms(cfg)
    if not pool:
        raise PlacementError(f"{cfg.shapes}: no wide, low block with a flat top to serve as a platform")
    for _ in range(PLACE_TRIES):
        spec = pool[int(rng.integers(len(pool)))]
        scale = float(rng.uniform(*cfg.towers.platform_scale))
        base = {"spec": spec, "category": spec.category, "half_extents": spec.half_extents, "scale": scale,
                "xy": rng.uniform(-cfg.area_half, cfg.area_half, 2), "yaw": float(rng.uniform(-math.pi, math.pi)),
                "z": scale * spec.half_extents[2]}
        on_top = _stacks_apart(rng, cfg, heights, [], base)
        if on_top is not None:
            return [[base], *on_top]
    return None


def _place(rng: np.random.Generator, cfg: ClevrConfig, heights: list[int], platform_heights: list[int] | None = None
           ) -> list[list[dict]] | None:
    """Stacks of the given heights whose footprints keep ``cfg.min_gap`` apart, or ``None`` after ``PLACE_TRIES``;
    with ``platform_heights``, first a platform carrying stacks of those heights (``_platform``), kept apart too."""
    for _ in range(PLACE_TRIES):
        group, discs = [], []
        if platform_heights is not None:
            group = _platform(rng, cfg, platform_heights)
            if group is None:
                continue
            discs.append(_group_disc([b for stack in group for b in stack]))
        ground = _stacks_apart(rng, cfg, heights, discs)
        if ground is not None:
            return group + ground
    return None


def sample_stacks(rng: np.random.Generator, cfg: ClevrConfig, camera: Camera | None = None) -> SceneSpec:
    """Sample one scene of stacked blocks (``cfg.towers`` set, ``cfg.shapes`` a block set). All randomness
    comes from ``rng``."""
    t = cfg.towers
    if t is None:
        raise ValueError("sample_stacks: cfg.towers is not set")
    light = ground = None
    if cfg.randomize is not None:
        camera, ground, light = sample_conditions(rng, cfg)
    if camera is None:
        raise ValueError("sample_stacks: give a camera, or set cfg.randomize")
    lo = cfg.num_objects if cfg.min_objects is None else cfg.min_objects
    n = int(rng.integers(max(lo, 1), cfg.num_objects + 1))
    # a platform scene: one block is the platform, 1..4 blocks stand on it in one or two stacks, the rest on the ground
    # (the draw is made only when platforms are asked for, so scenes without them stay what they were)
    on_platform = 0
    if t.platform_share > 0 and n >= 2 and rng.uniform() < t.platform_share:
        on_platform = int(rng.integers(1, min(n - 1, 4) + 1))
    for _ in range(MAX_TOWER_TRIES):  # a new deal each try: fewer, taller stacks fit where many do not
        platform_heights = None
        if on_platform:
            platform_heights = deal(rng, on_platform, int(rng.integers(1, min(2, on_platform) + 1)))
            if max(platform_heights) > MAX_LEVELS - 1:
                continue
        rest = n - on_platform - (1 if on_platform else 0)
        heights = deal(rng, rest, int(rng.integers(1, min(t.max_towers, rest) + 1))) if rest else []
        if heights and max(heights) > MAX_LEVELS:
            continue
        stacks = _place(rng, cfg, heights, platform_heights)
        if stacks is not None:
            break
    else:
        raise PlacementError(f"could not place {n} blocks in stacks of at most {MAX_LEVELS}, apart in "
                             f"[-{cfg.area_half}, {cfg.area_half}]^2 (a larger --area, or fewer blocks)")
    objects = []
    for blocks in stacks:
        for b in blocks:
            color = int(t.colors[int(rng.integers(len(t.colors)))])
            objects.append(ObjectSpec(b["spec"].shape_id, b["spec"].category_id, color, b["scale"],
                                      (float(b["xy"][0]), float(b["xy"][1]), float(b["z"])), b["yaw"],
                                      shapes=cfg.shapes, shape_split=cfg.shape_split))
    return SceneSpec(tuple(objects), camera, cfg.ground_z, cfg.ground_color if ground is None else ground, light=light)
