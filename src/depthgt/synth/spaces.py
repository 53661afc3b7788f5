"""The ``varied`` synthetic family: larger and harder indoor spaces than the furnished rooms.

Built to exercise what the furnished rooms of :func:`depthgt.synth.scene.generate_layout`
rarely show (issue 8): rooms from 3 to 9 m and corridors, so that far walls lie at
5-8 m and floors and ceilings are seen at grazing angles; partition walls and
pillars that make corners; ceiling beams and hanging lamps; thin structures 1-3 cm
wide (coat stands, floor-lamp poles, metal table and chair legs, shelf uprights,
railings); clutter on the floor and on desks; dark and glossy surfaces where a
depth sensor drops out (glossy floors, screens, whiteboards, black cabinets).

:func:`generate_space_layout` returns a :class:`~depthgt.synth.scene.Layout`, ray cast
by the same exact caster as the rooms; the camera path is
:func:`depthgt.synth.camera.make_walk_path`. Deterministic for a given generator state.
"""

from __future__ import annotations

import numpy as np

from depthgt.synth.scene import Layout, Material, Primitive, _add_box, _add_cyl, _add_sphere, _clutter, _local
from depthgt.synth.textures import make_texture

__all__ = ["SPACE_KINDS", "generate_space_layout"]

SPACE_KINDS = ("open_room", "corridor", "office")

# texture kinds and materials (texture index, period m, infrared return, gloss)
_TEXTURES = [
    "wood",
    "wood",
    "tiles",
    "carpet",
    "plaster",
    "plaster",
    "poster",
    "poster",
    "books",
    "metal",
    "fabric",
    "fabric",
    "dark",
    "plaster",
    "tiles",
    "dark",
    "plaster",
]
_MATS = {
    "wood": (0, 1.2, 1.0, 0.0),
    "wood2": (1, 1.0, 1.0, 0.0),
    "tiles": (2, 1.6, 1.0, 0.0),
    "carpet": (3, 2.0, 1.0, 0.0),
    "wall": (4, 2.0, 1.0, 0.0),
    "wall2": (5, 2.0, 1.0, 0.0),
    "poster": (6, 0.8, 1.0, 0.0),
    "poster2": (7, 0.6, 1.0, 0.0),
    "books": (8, 0.7, 1.0, 0.0),
    "metal": (9, 0.8, 0.9, 0.2),
    "fabric": (10, 0.5, 1.0, 0.0),
    "fabric2": (11, 0.4, 1.0, 0.0),
    "dark": (12, 0.8, 0.4, 0.0),
    "ceiling": (13, 2.5, 1.0, 0.0),
    # polished stone / lacquered floor: a glossy floor drops out at a distance and under the camera
    "glossy_floor": (14, 1.8, 0.8, 0.6),
    # screens, black lacquer: dark and glossy
    "screen": (15, 0.8, 0.5, 0.8),
    # whiteboard: bright but glossy
    "whiteboard": (16, 3.0, 1.0, 0.5),
}


def _materials(rng: np.random.Generator, texture_size: int):
    textures = [(make_texture(k, rng, texture_size) * 255 + 0.5).astype(np.uint8) for k in _TEXTURES]
    names = list(_MATS)
    materials = [Material(_MATS[n][0], _MATS[n][1], _MATS[n][2], _MATS[n][3]) for n in names]
    return textures, materials, {n: i for i, n in enumerate(names)}


def _room_size(rng: np.random.Generator, kind: str) -> np.ndarray:
    if kind == "corridor":
        return np.array([rng.uniform(6.5, 9.0), rng.uniform(1.8, 2.6), rng.uniform(2.4, 3.0)])
    if kind == "office":
        return np.array([rng.uniform(5.5, 9.0), rng.uniform(4.0, 6.5), rng.uniform(2.6, 3.2)])
    lx = rng.uniform(3.0, 9.0)
    return np.array([lx, rng.uniform(3.0, max(3.2, min(lx, 7.0))), rng.uniform(2.5, 3.2)])


def _free(fp, avoid, margin=0.05):
    """Whether the footprint (x0, y0, x1, y1) misses every footprint in ``avoid``."""
    return all(
        fp[2] + margin < a[0] or fp[0] - margin > a[2] or fp[3] + margin < a[1] or fp[1] - margin > a[3] for a in avoid
    )


def _place(rng, size, half_xy, avoid, margin_wall=0.05, tries=30):
    """A free spot (x, y) for a footprint of half sizes ``half_xy`` (axis aligned), or None."""
    hx, hy = half_xy
    for _ in range(tries):
        if size[0] < 2 * (hx + margin_wall) or size[1] < 2 * (hy + margin_wall):
            return None
        x = rng.uniform(hx + margin_wall, size[0] - hx - margin_wall)
        y = rng.uniform(hy + margin_wall, size[1] - hy - margin_wall)
        fp = (x - hx, y - hy, x + hx, y + hy)
        if _free(fp, avoid):
            avoid.append(fp)
            return x, y
    return None


def _thin_table(prims, rng, cx, cy, yaw, mats):
    """A desk on four thin metal legs (1-3 cm), with a laptop/books and a mug."""
    lx, ly = rng.uniform(0.5, 0.8), rng.uniform(0.3, 0.45)
    h = rng.uniform(0.7, 0.76)
    top = rng.uniform(0.012, 0.02)
    _add_box(prims, (cx, cy, h - top), (lx, ly, top), mats[rng.choice(["wood", "wood2", "whiteboard"])], yaw, rng)
    r = rng.uniform(0.005, 0.015)
    for sx in (-1, 1):
        for sy in (-1, 1):
            x, y = _local(cx, cy, yaw, sx * (lx - 0.05), sy * (ly - 0.05))
            _add_cyl(prims, x, y, 0.0, h - 2 * top, r, mats["metal"], rng)
    for _ in range(int(rng.integers(1, 4))):
        x, y = _local(cx, cy, yaw, rng.uniform(-lx + 0.15, lx - 0.15), rng.uniform(-ly + 0.12, ly - 0.12))
        hz = rng.uniform(0.005, 0.03)
        _add_box(
            prims,
            (x, y, h + hz),
            (rng.uniform(0.08, 0.17), rng.uniform(0.06, 0.12), hz),
            mats[rng.choice(["poster", "books", "screen", "dark"])],
            yaw + rng.uniform(-0.5, 0.5),
            rng,
        )
    if rng.uniform() < 0.6:  # a monitor on a thin stand
        x, y = _local(cx, cy, yaw, rng.uniform(-0.3, 0.3) * lx, -ly + 0.12)
        hs = rng.uniform(0.12, 0.2)
        _add_box(prims, (x, y, h + hs / 2), (0.012, 0.012, hs / 2), mats["metal"], yaw, rng)
        _add_box(prims, (x, y, h + hs + 0.17), (rng.uniform(0.22, 0.32), 0.015, 0.17), mats["screen"], yaw, rng)
    x, y = _local(cx, cy, yaw, rng.uniform(-lx + 0.1, lx - 0.1), rng.uniform(-ly + 0.1, ly - 0.1))
    _add_cyl(prims, x, y, h, h + rng.uniform(0.08, 0.12), rng.uniform(0.03, 0.045), mats["fabric"], rng)
    return lx, ly, h


def _thin_chair(prims, rng, cx, cy, yaw, mats):
    """A chair on thin legs (1-3 cm) with a solid or slatted back."""
    s = rng.uniform(0.19, 0.23)
    h = rng.uniform(0.43, 0.48)
    mat = mats[rng.choice(["metal", "dark", "wood", "screen"], p=[0.4, 0.25, 0.2, 0.15])]
    _add_box(prims, (cx, cy, h), (s, s, 0.018), mats[rng.choice(["fabric", "fabric2", "wood"])], yaw, rng)
    leg = rng.uniform(0.005, 0.013)
    round_legs = rng.uniform() < 0.5
    for sx in (-1, 1):
        for sy in (-1, 1):
            x, y = _local(cx, cy, yaw, sx * (s - 0.025), sy * (s - 0.025))
            if round_legs:
                _add_cyl(prims, x, y, 0.0, h - 0.018, leg, mat, rng)
            else:
                _add_box(prims, (x, y, (h - 0.018) / 2), (leg, leg, (h - 0.018) / 2), mat, yaw, rng)
    back_h = rng.uniform(0.35, 0.5)
    for sy in (-1, 1):
        x, y = _local(cx, cy, yaw, -(s - 0.025), sy * (s - 0.025))
        _add_box(prims, (x, y, h + back_h / 2), (leg, leg, back_h / 2), mat, yaw, rng)
    x, y = _local(cx, cy, yaw, -(s - 0.025), 0.0)
    if rng.uniform() < 0.5:
        _add_box(prims, (x, y, h + back_h * 0.7), (0.012, s - 0.02, back_h * 0.25), mat, yaw, rng)
    else:
        for k in range(int(rng.integers(2, 4))):
            _add_box(prims, (x, y, h + back_h * (k + 1) / 4.2), (0.01, s - 0.02, 0.02), mat, yaw, rng)


def _coat_stand(prims, rng, x, y, mats):
    """A pole (2-3 cm) on a base with a few thin hooks."""
    hp = rng.uniform(1.6, 1.85)
    r = rng.uniform(0.01, 0.015)
    mat = mats[rng.choice(["metal", "wood", "dark"])]
    _add_cyl(prims, x, y, 0.0, 0.025, rng.uniform(0.15, 0.2), mat, rng)
    _add_cyl(prims, x, y, 0.025, hp, r, mat, rng)
    for k in range(int(rng.integers(3, 6))):
        a = rng.uniform(0, 2 * np.pi)
        hx, hy = _local(x, y, a, 0.08, 0.0)
        _add_box(prims, (hx, hy, hp - 0.08 - 0.05 * (k % 2)), (0.08, 0.006, 0.006), mat, a, rng)
    if rng.uniform() < 0.5:  # a coat
        a = rng.uniform(0, 2 * np.pi)
        hx, hy = _local(x, y, a, 0.17, 0.0)
        _add_box(prims, (hx, hy, hp - 0.5), (0.05, 0.2, 0.4), mats["fabric2"], a, rng)


def _floor_lamp(prims, rng, x, y, mats):
    hl = rng.uniform(1.4, 1.8)
    _add_cyl(prims, x, y, 0.0, 0.03, rng.uniform(0.12, 0.16), mats["metal"], rng)
    _add_cyl(prims, x, y, 0.03, hl, rng.uniform(0.006, 0.012), mats["metal"], rng)
    _add_cyl(prims, x, y, hl, hl + 0.22, rng.uniform(0.14, 0.2), mats["fabric"], rng)


def _shelf(prims, rng, x, y, yaw, mats):
    """An open shelf on four thin uprights (2-3 cm) with boards and books/boxes."""
    lx, ly = rng.uniform(0.4, 0.7), rng.uniform(0.15, 0.2)
    hs = rng.uniform(1.2, 2.0)
    up = rng.uniform(0.01, 0.015)
    mat = mats[rng.choice(["metal", "dark", "wood"])]
    for sx in (-1, 1):
        for sy in (-1, 1):
            ux, uy = _local(x, y, yaw, sx * (lx - up), sy * (ly - up))
            _add_box(prims, (ux, uy, hs / 2), (up, up, hs / 2), mat, yaw, rng)
    n = int(rng.integers(3, 6))
    for k in range(n):
        z = 0.1 + k * (hs - 0.15) / (n - 1)
        _add_box(prims, (x, y, z), (lx, ly, 0.01), mats["wood"], yaw, rng)
        if k < n - 1 and rng.uniform() < 0.75:
            bl = lx * rng.uniform(0.3, 0.9)
            bh = rng.uniform(0.08, 0.14)
            bx, by = _local(x, y, yaw, rng.uniform(-(lx - bl), lx - bl + 1e-6), 0.0)
            _add_box(
                prims,
                (bx, by, z + 0.01 + bh),
                (bl, ly * 0.8, bh),
                mats[rng.choice(["books", "poster2", "dark"])],
                yaw,
                rng,
            )


def _railing(prims, rng, size, mats):
    """A low railing of thin balusters along part of a long wall (corridors, halls)."""
    y = rng.uniform(0.25, 0.45) if rng.uniform() < 0.5 else size[1] - rng.uniform(0.25, 0.45)
    x0 = rng.uniform(0.5, size[0] * 0.4)
    x1 = min(size[0] - 0.5, x0 + rng.uniform(1.5, 3.5))
    h = rng.uniform(0.9, 1.05)
    _add_box(prims, ((x0 + x1) / 2, y, h), ((x1 - x0) / 2, 0.02, 0.02), mats["wood"], 0.0, rng)
    r = rng.uniform(0.006, 0.012)
    for x in np.arange(x0, x1 + 1e-6, rng.uniform(0.12, 0.25)):
        _add_cyl(prims, float(x), y, 0.0, h - 0.02, r, mats["metal"], rng)
    return (x0, y - 0.05, x1, y + 0.05)


def _ceiling(prims, rng, size, mats, kind):
    """Beams or ducts across the ceiling and hanging lamps on thin cables."""
    lz = size[2]
    if rng.uniform() < 0.6:
        n = int(rng.integers(1, 4))
        along_x = kind == "corridor" or rng.uniform() < 0.5
        for k in range(n):
            depth = rng.uniform(0.1, 0.3)
            if along_x:  # a beam across the room (spanning y) at some x
                x = size[0] * (k + 1) / (n + 1) + rng.uniform(-0.3, 0.3)
                _add_box(
                    prims,
                    (x, size[1] / 2, lz - depth / 2),
                    (rng.uniform(0.08, 0.2), size[1] / 2 - 0.001, depth / 2),
                    mats["ceiling"],
                    0.0,
                    rng,
                )
            else:
                y = size[1] * (k + 1) / (n + 1) + rng.uniform(-0.3, 0.3)
                _add_box(
                    prims,
                    (size[0] / 2, y, lz - depth / 2),
                    (size[0] / 2 - 0.001, rng.uniform(0.08, 0.2), depth / 2),
                    mats["ceiling"],
                    0.0,
                    rng,
                )
    for _ in range(int(rng.integers(2, 6))):
        x, y = rng.uniform(0.5, size[0] - 0.5), rng.uniform(0.4, size[1] - 0.4)
        drop = rng.uniform(0.3, 0.8)
        _add_cyl(prims, x, y, lz - drop, lz, rng.uniform(0.003, 0.006), mats["dark"], rng)  # cable (sub-pixel)
        if rng.uniform() < 0.5:
            _add_box(
                prims,
                (x, y, lz - drop - 0.03),
                (rng.uniform(0.3, 0.6), rng.uniform(0.08, 0.15), 0.03),
                mats[rng.choice(["metal", "ceiling"])],
                rng.uniform(0, np.pi),
                rng,
            )
        else:
            _add_cyl(prims, x, y, lz - drop - 0.2, lz - drop, rng.uniform(0.12, 0.22), mats["fabric"], rng)


def _wall_items(prims, rng, size, mats, n):
    """Posters, whiteboards, screens, doors flat on the walls."""
    for _ in range(n):
        wall = int(rng.integers(0, 4))
        kind = rng.choice(["poster", "poster2", "whiteboard", "screen", "door"], p=[0.3, 0.2, 0.2, 0.15, 0.15])
        if kind == "door":
            w, hh, z, t = 0.45, 1.02, 1.02, 0.02
        else:
            w, hh = rng.uniform(0.25, 0.9), rng.uniform(0.25, 0.6)
            z, t = rng.uniform(1.2, 1.8), 0.008 if kind != "screen" else 0.03
        mat = mats["wood2"] if kind == "door" else mats[kind]
        if wall in (0, 1):
            if size[1] < 2 * w + 0.3:
                continue
            y = rng.uniform(w + 0.1, size[1] - w - 0.1)
            _add_box(prims, (t if wall == 0 else size[0] - t, y, z), (t, w, hh), mat, 0.0, rng)
        else:
            if size[0] < 2 * w + 0.3:
                continue
            x = rng.uniform(w + 0.1, size[0] - w - 0.1)
            _add_box(prims, (x, t if wall == 2 else size[1] - t, z), (w, t, hh), mat, 0.0, rng)


def generate_space_layout(rng: np.random.Generator, texture_size: int = 512) -> Layout:
    """A random space of the ``varied`` family (see the module docstring).

    Kinds (:data:`SPACE_KINDS`, drawn uniformly): ``open_room`` (3-9 m x 3-7 m, a few
    tables and chairs, clutter), ``corridor`` (6.5-9 m x 1.8-2.6 m, railing, coat
    stands, lamps along it), ``office`` (5.5-9 m x 4-6.5 m, rows of desks on thin
    legs, partition walls, pillars, shelves). All get ceiling beams or lamps, wall
    items and some dark and glossy surfaces. ``Layout.focus`` is the room's centre
    at 1 m (the walk path does not circle it).

    Long because it is one sequence of draws from ``rng``, kind by kind and object after
    object; split, the order that every space depends on would be spread over functions.
    """
    kind = SPACE_KINDS[int(rng.integers(0, len(SPACE_KINDS)))]
    size = _room_size(rng, kind)
    textures, materials, mats = _materials(rng, texture_size)
    floor = mats[rng.choice(["tiles", "carpet", "wood2", "glossy_floor", "dark"], p=[0.25, 0.2, 0.2, 0.25, 0.1])]
    wall_a, wall_b = (mats["wall"], mats["wall2"]) if rng.uniform() < 0.5 else (mats["wall2"], mats["wall"])
    face_materials = [wall_a, wall_a, wall_b, wall_b, floor, mats["ceiling"]]
    prims: list[Primitive] = []
    avoid: list[tuple[float, float, float, float]] = []

    if kind == "corridor":
        if rng.uniform() < 0.6:
            avoid.append(_railing(prims, rng, size, mats))
        for _ in range(int(rng.integers(1, 3))):
            spot = _place(rng, size, (0.2, 0.2), avoid)
            if spot is not None:
                _coat_stand(prims, rng, *spot, mats)
        for _ in range(int(rng.integers(1, 3))):
            spot = _place(rng, size, (0.18, 0.18), avoid)
            if spot is not None:
                _floor_lamp(prims, rng, *spot, mats)
        for _ in range(int(rng.integers(1, 3))):  # a cabinet or shelf against a long wall
            wall_y = 0.2 if rng.uniform() < 0.5 else size[1] - 0.2
            x = rng.uniform(0.6, size[0] - 0.6)
            fp = (x - 0.45, wall_y - 0.2, x + 0.45, wall_y + 0.2)
            if _free(fp, avoid):
                avoid.append(fp)
                if rng.uniform() < 0.5:
                    _shelf(prims, rng, x, wall_y, 0.0, mats)
                else:
                    hb = rng.uniform(0.6, 1.1)
                    _add_box(
                        prims,
                        (x, wall_y, hb / 2),
                        (0.4, 0.18, hb / 2),
                        mats[rng.choice(["dark", "wood", "screen"])],
                        0.0,
                        rng,
                    )
                    _clutter(prims, rng, x, wall_y, 0.0, hb, 0.3, 0.12, mats)
        n_tables = int(rng.integers(0, 2))
        n_pillars = 0
    else:
        n_tables = int(rng.integers(1, 3)) if kind == "open_room" else int(rng.integers(2, 5))
        n_pillars = int(rng.integers(0, 3)) if kind == "office" else int(rng.integers(0, 2))
        if kind == "office" and rng.uniform() < 0.7:  # a partition wall from one long wall: corners in view
            x = rng.uniform(0.35, 0.65) * size[0]
            length = rng.uniform(0.35, 0.6) * size[1]
            y0 = 0.0 if rng.uniform() < 0.5 else size[1] - length
            _add_box(
                prims,
                (x, y0 + length / 2, size[2] / 2),
                (0.05, length / 2, size[2] / 2 - 0.001),
                mats[rng.choice(["wall", "wall2", "wood2"])],
                0.0,
                rng,
            )
            avoid.append((x - 0.15, y0, x + 0.15, y0 + length))
    for _ in range(n_pillars):
        spot = _place(rng, size, (0.25, 0.25), avoid, margin_wall=0.8)
        if spot is not None:
            half = rng.uniform(0.12, 0.25)
            if rng.uniform() < 0.5:
                _add_box(
                    prims, (spot[0], spot[1], size[2] / 2), (half, half, size[2] / 2 - 0.001), mats["wall"], 0.0, rng
                )
            else:
                _add_cyl(prims, spot[0], spot[1], 0.0, size[2] - 0.001, half, mats[rng.choice(["wall", "metal"])], rng)
    for _ in range(n_tables):
        yaw = rng.choice([0.0, np.pi / 2]) + rng.uniform(-0.2, 0.2)
        spot = _place(rng, size, (0.9, 0.9), avoid)
        if spot is None:
            continue
        lx, ly, _ = _thin_table(prims, rng, spot[0], spot[1], yaw, mats)
        for sy in rng.permutation([-1, 1])[: int(rng.integers(1, 3))]:
            x, y = _local(spot[0], spot[1], yaw, rng.uniform(-0.3, 0.3) * lx, sy * (ly + 0.2))
            _thin_chair(prims, rng, x, y, yaw + np.arctan2(-sy, 0) + np.pi + rng.uniform(-0.4, 0.4), mats)
    if kind != "corridor":
        for _ in range(int(rng.integers(1, 3))):
            wall = int(rng.integers(0, 4))
            if wall < 2:
                fp_half, x, yaw = (0.2, 0.7), (0.22 if wall == 0 else size[0] - 0.22), np.pi / 2
                spot = _place(rng, (size[0], size[1]), fp_half, [], 0.0)
                if spot is None:
                    continue
                y = float(np.clip(spot[1], 0.8, size[1] - 0.8))
            else:
                fp_half, y, yaw = (0.7, 0.2), (0.22 if wall == 2 else size[1] - 0.22), 0.0
                spot = _place(rng, (size[0], size[1]), fp_half, [], 0.0)
                if spot is None:
                    continue
                x = float(np.clip(spot[0], 0.8, size[0] - 0.8))
            fp = (x - fp_half[0], y - fp_half[1], x + fp_half[0], y + fp_half[1])
            if _free(fp, avoid):
                avoid.append(fp)
                _shelf(prims, rng, x, y, yaw, mats)
        for maker in (_coat_stand, _floor_lamp):
            if rng.uniform() < 0.7:
                spot = _place(rng, size, (0.2, 0.2), avoid)
                if spot is not None:
                    maker(prims, rng, *spot, mats)
    # floor clutter: boxes, bins, a ball
    for _ in range(int(rng.integers(3, 8))):
        half = rng.uniform([0.08, 0.08, 0.05], [0.3, 0.25, 0.3])
        spot = _place(rng, size, (half[0] + 0.05, half[1] + 0.05), avoid)
        if spot is None:
            continue
        r = rng.uniform()
        if r < 0.5:
            _add_box(
                prims,
                (spot[0], spot[1], half[2]),
                half,
                mats[rng.choice(["wood2", "poster", "dark", "books"])],
                rng.uniform(0, np.pi),
                rng,
            )
        elif r < 0.8:
            _add_cyl(
                prims,
                spot[0],
                spot[1],
                0.0,
                2 * half[2],
                min(half[0], half[1]),
                mats[rng.choice(["metal", "fabric", "dark"])],
                rng,
            )
        else:
            _add_sphere(prims, (spot[0], spot[1], min(half[:2])), min(half[:2]), mats["fabric2"], rng)
    _ceiling(prims, rng, size, mats, kind)
    _wall_items(prims, rng, size, mats, int(rng.integers(3, 7)))
    light = np.array([size[0] * rng.uniform(0.3, 0.7), size[1] * rng.uniform(0.3, 0.7), size[2] - 0.1])
    return Layout(
        size,
        face_materials,
        prims,
        materials,
        textures,
        light,
        np.array([size[0] / 2, size[1] / 2, 1.0]),
        ambient=float(rng.uniform(0.3, 0.45)),
    )
