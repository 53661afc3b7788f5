"""Procedural indoor rooms made of analytic primitives, and their exact ray casting.

World frame: metres, z up, the room spans ``[0, Lx] x [0, Ly] x [0, Lz]`` (floor at
z = 0). Cameras follow OpenCV (x right, y down, looking down +z); poses are
camera-to-world (4, 4) float64.

A :class:`Layout` holds the room, ~30-60 primitives (yawed boxes, vertical capped
cylinders, spheres) and their materials. :func:`raycast` intersects one ray per pixel
with every primitive (a Python loop over primitives, each vectorised over the pixels
of its projected bounding box) and keeps the nearest hit: the depth is exact up to
float32 rounding. :func:`shade` colours the hits with texture albedo and lambertian +
ambient lighting.

Ray casting of analytic primitives is written here because no installed library
does it on the CPU (kornia/OpenCV have no ray tracer; a mesh rasteriser would lose
the analytic depth the tests compare against).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import cv2
import numpy as np

from depthgt.shapes import check_shape
from depthgt.synth.textures import make_texture

__all__ = [
    "Material",
    "Primitive",
    "Layout",
    "RayHits",
    "THIN_WIDTH_M",
    "generate_layout",
    "raycast",
    "raycast_depth",
    "albedo",
    "shade",
    "camera_rays",
    "thin_mask",
]

_NEAR_M = 0.05
THIN_WIDTH_M = 0.03  # poles, legs and rods at most this wide count as thin structures
_CORNER_SIGNS = np.array(np.meshgrid([-1, 1], [-1, 1], [-1, 1], indexing="ij"), np.float64).reshape(3, -1).T
# inward normals of the room faces, in hit-id order: x=0, x=Lx, y=0, y=Ly, floor, ceiling
_FACE_NORMALS = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], np.float32)


@dataclass(frozen=True)
class Material:
    """Surface appearance.

    Attributes:
        texture: index into ``Layout.textures``.
        period_m: metres of surface covered by one texture tile.
        ir_return: relative strength of the surface's infrared return in (0, 1]; low
            values (black, glossy) make the Kinect drop depth there (see noise.py).
        gloss: share of the infrared return reflected specularly, in [0, 1]: it comes
            back only near normal incidence (where it saturates the sensor), so a
            glossy surface returns little at oblique angles (see
            :func:`depthgt.synth.noise.infrared_return`). 0 = matte.
    """

    texture: int
    period_m: float
    ir_return: float = 1.0
    gloss: float = 0.0


@dataclass(frozen=True)
class Primitive:
    """One solid. ``kind`` is "box" (centre, half extents, yaw about z), "cylinder"
    (vertical axis through ``center[:2]``, radius, z from ``center[2] - half[2]`` to
    ``center[2] + half[2]``) or "sphere" (centre, radius)."""

    kind: str
    center: np.ndarray  # (3,) metres
    half: np.ndarray  # (3,) metres; cylinder: (r, r, half height); sphere: (r, r, r)
    material: int
    yaw: float = 0.0
    uv_offset: tuple[float, float] = (0.0, 0.0)

    @cached_property
    def corners(self) -> np.ndarray:
        """(8, 3) corners of a world bounding box of the primitive (computed once)."""
        if self.kind == "box":
            c, s = np.cos(self.yaw), np.sin(self.yaw)
            R = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
            return self.center + (_CORNER_SIGNS * self.half) @ R.T
        return self.center + _CORNER_SIGNS * self.half

    @cached_property
    def aabb(self) -> np.ndarray:
        """(6,) world axis-aligned bounds (xmin, ymin, zmin, xmax, ymax, zmax)."""
        return np.concatenate([self.corners.min(0), self.corners.max(0)])

    @property
    def thin(self) -> bool:
        """A pole, leg or rod: at most ``THIN_WIDTH_M`` wide across its longest axis
        and at least 4 times as long (a cylinder of radius <= 1.5 cm, a box whose two
        smaller extents are <= 3 cm)."""
        full = np.sort(2.0 * self.half)  # ascending full extents
        if self.kind == "sphere":
            return False
        return bool(full[1] <= THIN_WIDTH_M and full[2] >= 4.0 * full[1])


@dataclass
class Layout:
    """A room: size (Lx, Ly, Lz) in metres, its six faces' materials (order: wall
    x=0, wall x=Lx, wall y=0, wall y=Ly, floor, ceiling), the primitives, materials,
    textures and a point light.

    ``focus`` is a world point the camera path looks around (the table)."""

    size: np.ndarray
    face_materials: list[int]
    primitives: list[Primitive]
    materials: list[Material]
    textures: list[np.ndarray]  # (S, S, 3) uint8 tileable albedo
    light_pos: np.ndarray
    focus: np.ndarray
    ambient: float = 0.35

    @cached_property
    def corners(self) -> np.ndarray:
        """(P, 8, 3) bounding-box corners of all primitives (computed once)."""
        return np.stack([p.corners for p in self.primitives]) if self.primitives else np.zeros((0, 8, 3))

    @cached_property
    def aabbs(self) -> np.ndarray:
        """(P, 6) world bounds (xmin, ymin, zmin, xmax, ymax, zmax) of all primitives."""
        return np.stack([p.aabb for p in self.primitives]) if self.primitives else np.zeros((0, 6))


@dataclass
class RayHits:
    """Result of :func:`raycast` at (H, W).

    Attributes:
        depth_m: (H, W) float32 z-depth in metres (exact), 0 = no surface.
        prim: (H, W) int16 hit id: 0..5 room faces, 6 + k primitive k.
        points_world: (H, W, 3) float32 hit points.
        normals_world: (H, W, 3) float32 unit normals facing the camera side.
        uv: (H, W, 2) float32 texture coordinates in tiles.
        material: (H, W) int16 material index.
    """

    depth_m: np.ndarray
    prim: np.ndarray
    points_world: np.ndarray
    normals_world: np.ndarray
    uv: np.ndarray
    material: np.ndarray


def _rotz(yaw: float) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]], np.float64)


# ----------------------------------------------------------------------------- layout


def _add_box(prims, center, half, mat, yaw=0.0, rng=None):
    off = tuple(rng.uniform(0, 1, 2)) if rng is not None else (0.0, 0.0)
    prims.append(Primitive("box", np.asarray(center, np.float64), np.asarray(half, np.float64), mat, float(yaw), off))


def _add_cyl(prims, x, y, z0, z1, r, mat, rng=None):
    off = tuple(rng.uniform(0, 1, 2)) if rng is not None else (0.0, 0.0)
    prims.append(Primitive("cylinder", np.array([x, y, (z0 + z1) / 2]), np.array([r, r, (z1 - z0) / 2]), mat, 0.0, off))


def _add_sphere(prims, center, r, mat, rng=None):
    off = tuple(rng.uniform(0, 1, 2)) if rng is not None else (0.0, 0.0)
    prims.append(Primitive("sphere", np.asarray(center, np.float64), np.array([r, r, r]), mat, 0.0, off))


def _local(cx, cy, yaw, dx, dy):
    """World xy of the point (dx, dy) in a frame at (cx, cy) rotated by yaw."""
    c, s = np.cos(yaw), np.sin(yaw)
    return cx + c * dx - s * dy, cy + s * dx + c * dy


def _table(prims, rng, cx, cy, yaw, mats):
    lx, ly = rng.uniform(0.55, 0.85), rng.uniform(0.35, 0.5)
    h = rng.uniform(0.72, 0.78)
    top = 0.02 + rng.uniform(0, 0.02)
    _add_box(prims, (cx, cy, h - top), (lx, ly, top), mats["wood"], yaw, rng)
    round_legs = rng.uniform() < 0.5
    for sx in (-1, 1):
        for sy in (-1, 1):
            x, y = _local(cx, cy, yaw, sx * (lx - 0.07), sy * (ly - 0.07))
            if round_legs:
                _add_cyl(prims, x, y, 0.0, h - 2 * top, rng.uniform(0.02, 0.03), mats["metal"], rng)
            else:
                _add_box(prims, (x, y, (h - 2 * top) / 2), (0.03, 0.03, (h - 2 * top) / 2), mats["wood"], yaw, rng)
    # objects on the table: books / a laptop, a mug, a bowl
    for _ in range(int(rng.integers(1, 4))):
        bx, by = rng.uniform(-lx + 0.15, lx - 0.15), rng.uniform(-ly + 0.12, ly - 0.12)
        x, y = _local(cx, cy, yaw, bx, by)
        hz = rng.uniform(0.005, 0.025)
        _add_box(
            prims,
            (x, y, h + hz),
            (rng.uniform(0.1, 0.17), rng.uniform(0.08, 0.13), hz),
            mats[rng.choice(["poster", "books", "dark"])],
            yaw + rng.uniform(-0.5, 0.5),
            rng,
        )
    x, y = _local(cx, cy, yaw, rng.uniform(-lx + 0.1, lx - 0.1), rng.uniform(-ly + 0.1, ly - 0.1))
    _add_cyl(prims, x, y, h, h + rng.uniform(0.08, 0.2), rng.uniform(0.035, 0.06), mats["fabric"], rng)
    x, y = _local(cx, cy, yaw, rng.uniform(-lx + 0.15, lx - 0.15), rng.uniform(-ly + 0.15, ly - 0.15))
    r = rng.uniform(0.06, 0.1)
    _add_sphere(prims, (x, y, h + 0.7 * r), r, mats["fabric2"], rng)
    return lx, ly, h


def _clutter(prims, rng, cx, cy, yaw, z, half_depth, half_length, mats):
    """2-4 small objects (jars, boxes) standing at height ``z`` on a surface centred
    at (cx, cy) with half sizes ``half_depth`` x ``half_length`` rotated by yaw."""
    for _ in range(int(rng.integers(2, 5))):
        x, y = _local(cx, cy, yaw, rng.uniform(-half_depth, half_depth), rng.uniform(-half_length, half_length))
        if rng.uniform() < 0.5:
            r, hz = rng.uniform(0.03, 0.07), rng.uniform(0.05, 0.15)
            _add_cyl(prims, x, y, z, z + 2 * hz, r, mats[rng.choice(["metal", "fabric", "fabric2"])], rng)
        else:
            half = rng.uniform([0.03, 0.03, 0.04], [0.1, 0.1, 0.15])
            _add_box(
                prims,
                (x, y, z + half[2]),
                half,
                mats[rng.choice(["poster", "poster2", "books", "wood2"])],
                yaw + rng.uniform(-0.8, 0.8),
                rng,
            )


def _chair(prims, rng, cx, cy, yaw, mats):
    """A chair at (cx, cy) whose seat front faces direction ``yaw``: four thin legs,
    a seat, two back posts and horizontal slats (gaps to see through)."""
    s = rng.uniform(0.2, 0.24)
    h = rng.uniform(0.43, 0.48)
    mat = mats[rng.choice(["wood", "wood2", "metal", "dark"], p=[0.35, 0.3, 0.25, 0.1])]
    _add_box(prims, (cx, cy, h), (s, s, 0.02), mat, yaw, rng)
    leg = rng.uniform(0.015, 0.025)
    for sx in (-1, 1):
        for sy in (-1, 1):
            x, y = _local(cx, cy, yaw, sx * (s - 0.03), sy * (s - 0.03))
            _add_box(prims, (x, y, (h - 0.02) / 2), (leg, leg, (h - 0.02) / 2), mat, yaw, rng)
    back_h = rng.uniform(0.4, 0.5)
    for sy in (-1, 1):
        x, y = _local(cx, cy, yaw, -(s - 0.03), sy * (s - 0.03))
        _add_box(prims, (x, y, h + back_h / 2), (leg, leg, back_h / 2), mat, yaw, rng)
    n_slats = int(rng.integers(2, 4))
    for k in range(n_slats):
        z = h + back_h * (k + 1) / (n_slats + 0.5)
        x, y = _local(cx, cy, yaw, -(s - 0.03), 0.0)
        _add_box(prims, (x, y, z), (0.012, s - 0.03, 0.03), mat, yaw, rng)


def _against_wall(rng, size, wall, depth, length, avoid):
    """Centre (x, y) and yaw of a piece of furniture of half ``depth`` x ``length``
    standing against wall ``wall`` (0: x=0, 1: x=Lx, 2: y=0, 3: y=Ly), avoiding the
    footprints in ``avoid``; None when it does not fit."""
    Lx, Ly = size[0], size[1]
    for _ in range(20):
        if wall in (0, 1):
            y = rng.uniform(length + 0.05, Ly - length - 0.05) if Ly > 2 * length + 0.1 else None
            if y is None:
                return None
            x = depth + 0.01 if wall == 0 else Lx - depth - 0.01
            fp = (x - depth, y - length, x + depth, y + length)
            yaw = 0.0 if wall == 0 else np.pi
        else:
            x = rng.uniform(length + 0.05, Lx - length - 0.05) if Lx > 2 * length + 0.1 else None
            if x is None:
                return None
            y = depth + 0.01 if wall == 2 else Ly - depth - 0.01
            fp = (x - length, y - depth, x + length, y + depth)
            yaw = np.pi / 2 if wall == 2 else -np.pi / 2
        if all(fp[2] < a[0] or fp[0] > a[2] or fp[3] < a[1] or fp[1] > a[3] for a in avoid):
            avoid.append(fp)
            return x, y, yaw
    return None


def generate_layout(rng: np.random.Generator, texture_size: int = 512) -> Layout:
    """A random furnished room, deterministic for a given generator state.

    Contents: floor (tiles, parquet or carpet), plastered walls and ceiling, a table
    with legs and objects on it, sometimes a rug, 2-3 chairs with slatted backs, a
    kitchen run of cabinets with a dark counter top and jars and boxes on it, a shelf
    unit with books, a floor lamp (thin pole), a sideboard with objects and sometimes
    a television, posters and a door on the walls.

    Long because it is one sequence of draws from ``rng``, object after object; split,
    the order that every room depends on (the default dataset's rooms) would be spread
    over functions.
    """
    size = np.array([rng.uniform(3.8, 5.0), rng.uniform(3.5, 4.6), rng.uniform(2.5, 2.8)])
    kinds = [
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
    ]
    textures = [(make_texture(k, rng, texture_size) * 255 + 0.5).astype(np.uint8) for k in kinds]
    materials = [
        Material(0, 1.2),
        Material(1, 1.0),
        Material(2, rng.uniform(1.2, 2.2)),
        Material(3, 2.0),
        Material(4, 2.0),
        Material(5, 2.0),
        Material(6, 0.8),
        Material(7, 0.6),
        Material(8, 0.7),
        Material(9, 0.8, 0.9),
        Material(10, 0.5),
        Material(11, 0.4),
        Material(12, 0.8, ir_return=0.4),
        Material(13, 2.5),
    ]
    mats = {
        "wood": 0,
        "wood2": 1,
        "tiles": 2,
        "carpet": 3,
        "wall": 4,
        "wall2": 5,
        "poster": 6,
        "poster2": 7,
        "books": 8,
        "metal": 9,
        "fabric": 10,
        "fabric2": 11,
        "dark": 12,
        "ceiling": 13,
    }
    floor = mats[rng.choice(["tiles", "carpet", "wood2"])]
    wall_a, wall_b = (mats["wall"], mats["wall2"]) if rng.uniform() < 0.5 else (mats["wall2"], mats["wall"])
    face_materials = [wall_a, wall_a, wall_b, wall_b, floor, mats["ceiling"]]

    prims: list[Primitive] = []
    cx, cy = size[0] * rng.uniform(0.42, 0.58), size[1] * rng.uniform(0.42, 0.58)
    yaw = rng.uniform(0, np.pi)
    lx, ly, h_table = _table(prims, rng, cx, cy, yaw, mats)
    if rng.uniform() < 0.5:  # a thin rug under the table
        rug = mats["carpet"] if floor != mats["carpet"] else mats["fabric"]
        _add_box(prims, (cx, cy, 0.004), (lx + rng.uniform(0.3, 0.6), ly + rng.uniform(0.4, 0.7), 0.004), rug, yaw, rng)
    # chairs on the long sides, facing the table
    sides = rng.permutation([(0, 1), (0, -1), (1, 0), (-1, 0)])[: int(rng.integers(2, 4))]
    for sx, sy in sides:
        dx = sx * (lx + 0.15) + (rng.uniform(-0.3, 0.3) if sx == 0 else 0)
        dy = sy * (ly + 0.15) + (rng.uniform(-0.2, 0.2) * lx if sy == 0 else 0)
        x, y = _local(cx, cy, yaw, dx, dy)
        face = yaw + np.arctan2(-sy, -sx) + rng.uniform(-0.3, 0.3)
        _chair(prims, rng, x, y, face + np.pi, mats)
    avoid = [(cx - 1.2, cy - 1.2, cx + 1.2, cy + 1.2)]
    walls = list(rng.permutation(4))
    # kitchen run: cabinets + dark counter top + wall cabinet with posters above
    spot = _against_wall(rng, size, walls[0], 0.3, rng.uniform(0.8, 1.3), avoid)
    if spot is not None:
        x, y, wyaw = spot
        ln = avoid[-1]
        length = max(ln[2] - ln[0], ln[3] - ln[1]) / 2
        hc = rng.uniform(0.85, 0.92)
        _add_box(prims, (x, y, hc / 2), (0.3, length, hc / 2 - 0.02), mats["wood2"], wyaw, rng)
        _add_box(prims, (x, y, hc), (0.31, length + 0.01, 0.02), mats["dark"], wyaw, rng)
        _clutter(prims, rng, x, y, wyaw, hc + 0.02, 0.22, length - 0.1, mats)
        if rng.uniform() < 0.7:
            xw, yw = _local(x, y, wyaw, -0.12, 0.0)
            _add_box(prims, (xw, yw, 1.85), (0.17, length * 0.8, 0.3), mats["wood"], wyaw, rng)
    # shelf unit: two sides, boards, rows of books
    spot = _against_wall(rng, size, walls[1], 0.17, rng.uniform(0.4, 0.6), avoid)
    if spot is not None:
        x, y, wyaw = spot
        ln = avoid[-1]
        length = max(ln[2] - ln[0], ln[3] - ln[1]) / 2
        hs = rng.uniform(1.4, 2.0)
        for s in (-1, 1):
            xs, ys = _local(x, y, wyaw, 0.0, s * (length - 0.01))
            _add_box(prims, (xs, ys, hs / 2), (0.17, 0.01, hs / 2), mats["wood"], wyaw, rng)
        n_boards = int(rng.integers(3, 6))
        for k in range(n_boards):
            z = 0.05 + k * (hs - 0.1) / (n_boards - 1)
            _add_box(prims, (x, y, z), (0.17, length - 0.02, 0.012), mats["wood"], wyaw, rng)
            if k < n_boards - 1 and rng.uniform() < 0.8:
                bh = rng.uniform(0.1, 0.14)
                bl = (length - 0.03) * rng.uniform(0.4, 0.95)
                xb, yb = _local(x, y, wyaw, -0.02, rng.uniform(-(length - 0.03 - bl), length - 0.03 - bl + 1e-6))
                _add_box(prims, (xb, yb, z + 0.012 + bh), (0.12, bl, bh), mats["books"], wyaw, rng)
    # floor lamp: base, thin pole, shade
    spot = _against_wall(rng, size, walls[2], 0.25, 0.2, avoid)
    if spot is not None:
        x, y, wyaw = spot
        x, y = _local(x, y, wyaw, 0.05, 0.0)
        hl = rng.uniform(1.4, 1.7)
        _add_cyl(prims, x, y, 0.0, 0.03, 0.14, mats["metal"], rng)
        _add_cyl(prims, x, y, 0.03, hl, rng.uniform(0.01, 0.015), mats["metal"], rng)
        _add_cyl(prims, x, y, hl, hl + 0.25, rng.uniform(0.15, 0.2), mats["fabric"], rng)
    # a cabinet / sideboard
    spot = _against_wall(rng, size, walls[3], 0.22, rng.uniform(0.4, 0.7), avoid)
    if spot is not None:
        x, y, wyaw = spot
        ln = avoid[-1]
        length = max(ln[2] - ln[0], ln[3] - ln[1]) / 2
        hb = rng.uniform(0.6, 1.1)
        _add_box(prims, (x, y, hb / 2), (0.22, length, hb / 2), mats[rng.choice(["wood", "wood2"])], wyaw, rng)
        _clutter(prims, rng, x, y, wyaw, hb, 0.15, length - 0.1, mats)
        if rng.uniform() < 0.6:  # a television: dark, low infrared return
            xt, yt = _local(x, y, wyaw, 0.0, rng.uniform(-0.3, 0.3) * length)
            _add_box(prims, (xt, yt, hb + 0.32), (0.03, rng.uniform(0.3, 0.45), 0.22), mats["dark"], wyaw, rng)
    # posters and a door, flat on the walls
    for _k in range(int(rng.integers(3, 6))):
        wall = int(rng.integers(0, 4))
        w, hh = rng.uniform(0.2, 0.5), rng.uniform(0.25, 0.45)
        z = rng.uniform(1.3, 1.9)
        if wall in (0, 1):
            y = rng.uniform(w + 0.1, size[1] - w - 0.1)
            x = 0.008 if wall == 0 else size[0] - 0.008
            _add_box(prims, (x, y, z), (0.008, w, hh), mats[rng.choice(["poster", "poster2"])], 0.0, rng)
        else:
            x = rng.uniform(w + 0.1, size[0] - w - 0.1)
            y = 0.008 if wall == 2 else size[1] - 0.008
            _add_box(prims, (x, y, z), (w, 0.008, hh), mats[rng.choice(["poster", "poster2"])], 0.0, rng)
    wall = int(rng.integers(0, 4))
    if wall in (0, 1):
        y = rng.uniform(0.6, size[1] - 0.6)
        _add_box(prims, (0.02 if wall == 0 else size[0] - 0.02, y, 1.02), (0.02, 0.45, 1.02), mats["wood2"], 0.0, rng)
    else:
        x = rng.uniform(0.6, size[0] - 0.6)
        _add_box(prims, (x, 0.02 if wall == 2 else size[1] - 0.02, 1.02), (0.45, 0.02, 1.02), mats["wood2"], 0.0, rng)

    light = np.array([size[0] * rng.uniform(0.3, 0.7), size[1] * rng.uniform(0.3, 0.7), size[2] - 0.05])
    return Layout(
        size,
        face_materials,
        prims,
        materials,
        textures,
        light,
        np.array([cx, cy, h_table]),
        ambient=float(rng.uniform(0.3, 0.4)),
    )


# ---------------------------------------------------------------------------- casting


def camera_rays(K: np.ndarray, hw: tuple[int, int], R_world_cam: np.ndarray) -> np.ndarray:
    """World directions of the pixel rays, scaled so that their camera z is 1.

    With this scaling the ray parameter t of a hit is its z-depth. Stored as three
    planes so that every per-axis operation runs on contiguous memory.

    Returns:
        (3, H, W) float32 (x, y, z components).
    """
    h, w = hw
    Kinv = np.linalg.inv(K)
    u = np.arange(w, dtype=np.float64)[None, :]
    v = np.arange(h, dtype=np.float64)[:, None]
    x_n = Kinv[0, 0] * u + Kinv[0, 1] * v + Kinv[0, 2]
    y_n = np.broadcast_to(Kinv[1, 1] * v + Kinv[1, 2], (h, w))
    x_n = np.broadcast_to(x_n, (h, w))
    R = R_world_cam
    return np.stack([R[k, 0] * x_n + R[k, 1] * y_n + R[k, 2] for k in range(3)]).astype(np.float32)


def _screen_boxes(corners_world: np.ndarray, T_cam_world: np.ndarray, K: np.ndarray, hw: tuple[int, int]) -> np.ndarray:
    """Pixel rectangles holding the projections of bounding boxes.

    Args:
        corners_world: (P, 8, 3) corners of the primitives' bounding boxes.

    Returns:
        (P, 4) int rows (v0, v1, u0, u1); empty rectangles (v0 >= v1) for boxes
        behind the camera or outside the image, the whole image for boxes that
        straddle the camera plane.
    """
    h, w = hw
    c = corners_world @ T_cam_world[:3, :3].T + T_cam_world[:3, 3]
    z = c[..., 2]
    zs = np.maximum(z, _NEAR_M)
    u = K[0, 0] * c[..., 0] / zs + K[0, 1] * c[..., 1] / zs + K[0, 2]
    v = K[1, 1] * c[..., 1] / zs + K[1, 2]
    boxes = np.stack([np.floor(v.min(1)) - 1, np.ceil(v.max(1)) + 2, np.floor(u.min(1)) - 1, np.ceil(u.max(1)) + 2], 1)
    straddle = (z < _NEAR_M).any(1)
    boxes[straddle] = [0, h, 0, w]
    boxes[:, :2] = boxes[:, :2].clip(0, h)
    boxes[:, 2:] = boxes[:, 2:].clip(0, w)
    boxes[(z < _NEAR_M).all(1)] = 0
    return boxes.astype(np.int64)


def _safe(d):
    return np.where(np.abs(d) < 1e-9, np.float32(1e-9), d)


def _t_cylinder(o, d, prim):
    ox, oy = np.float32(o[0] - prim.center[0]), np.float32(o[1] - prim.center[1])
    r = np.float32(prim.half[0])
    z0, z1 = prim.center[2] - prim.half[2], prim.center[2] + prim.half[2]
    dx, dy, dz = d[0], d[1], d[2]
    a = _safe(dx * dx + dy * dy)
    b = 2 * (ox * dx + oy * dy)
    c = ox * ox + oy * oy - r * r
    disc = b * b - 4 * a * c
    t_side = (-b - np.sqrt(np.maximum(disc, 0))) / (2 * a)
    z_side = np.float32(o[2]) + t_side * dz
    t = np.where((disc >= 0) & (t_side > _NEAR_M) & (z_side >= z0) & (z_side <= z1), t_side, np.inf)
    dzs = _safe(dz)
    for zc in (z0, z1):
        tc = (np.float32(zc - o[2])) / dzs
        inside = (ox + tc * dx) ** 2 + (oy + tc * dy) ** 2 <= r * r
        t = np.where(inside & (tc > _NEAR_M), np.minimum(t, tc), t)
    return t


def _t_sphere(o, d, prim):
    oc = (o - prim.center).astype(np.float32)
    r = np.float32(prim.half[0])
    a = d[0] * d[0] + d[1] * d[1] + d[2] * d[2]
    b = 2 * (d[0] * oc[0] + d[1] * oc[1] + d[2] * oc[2])
    c = np.float32(oc @ oc) - r * r
    disc = b * b - 4 * a * c
    t = (-b - np.sqrt(np.maximum(disc, 0))) / (2 * a)
    return np.where((disc >= 0) & (t > _NEAR_M), t, np.inf)


# boxes, most primitives of a room, are intersected in one batch (_box_pairs)
_T_FUNCS = {"cylinder": _t_cylinder, "sphere": _t_sphere}


def _attributes_box(p, prim):
    R = _rotz(prim.yaw).astype(np.float32)
    p_l = (p - prim.center.astype(np.float32)) @ R
    half = prim.half.astype(np.float32)
    axis = (np.abs(p_l) / half).argmax(-1)
    sign = np.sign(np.take_along_axis(p_l, axis[:, None], 1))
    n_l = np.eye(3, dtype=np.float32)[axis] * sign
    # texture axes: the two other local axes, the longer one first (wood grain along it)
    order = np.argsort(-prim.half, kind="stable")
    pairs = np.array([[k for k in order if k != ax] for ax in range(3)])
    uv = np.take_along_axis(p_l, pairs[axis], 1)
    return n_l @ R.T, uv


def _attributes_cylinder(p, prim):
    q = p - prim.center.astype(np.float32)
    z0, z1 = -prim.half[2], prim.half[2]
    n = np.zeros_like(q)
    cap = (np.abs(q[:, 2] - z1) < 1e-4) | (np.abs(q[:, 2] - z0) < 1e-4)
    n[:, :2] = q[:, :2] / np.float32(prim.half[0])
    n[cap] = 0
    n[cap, 2] = np.sign(q[cap, 2])
    ang = np.arctan2(q[:, 1], q[:, 0]) * np.float32(prim.half[0])
    uv = np.where(cap[:, None], q[:, :2], np.stack([ang, q[:, 2]], -1))
    return n / np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-6), uv.astype(np.float32)


def _attributes_sphere(p, prim):
    q = p - prim.center.astype(np.float32)
    n = q / np.float32(prim.half[0])
    uv = np.stack([np.arctan2(q[:, 1], q[:, 0]) * np.float32(prim.half[0]), q[:, 2]], -1)
    return n, uv.astype(np.float32)


_ATTR_FUNCS = {"box": _attributes_box, "cylinder": _attributes_cylinder, "sphere": _attributes_sphere}


def _nearest_hits(
    layout: Layout, T_world_cam: np.ndarray, K: np.ndarray, hw: tuple[int, int]
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The nearest surface along every pixel ray: ``(o, d, depth, prim_id)`` with the
    camera centre ``o`` (3,), the rays ``d`` (3, H, W) of :func:`camera_rays`, the
    z-depth (H, W) float32 and what was hit (H, W) int16 (0-5: the room's faces, 6 + k:
    primitive k). Arguments as :func:`raycast`."""
    T_world_cam = np.asarray(T_world_cam, np.float64)
    check_shape(T_world_cam, "4 4", "T_world_cam")
    K = np.asarray(K, np.float64)
    check_shape(K, "3 3", "K")
    h, w = hw
    o = T_world_cam[:3, 3]
    if not ((o > 0) & (o < layout.size)).all():
        raise ValueError(f"camera centre {o.round(3).tolist()} is outside the room {layout.size.round(3).tolist()}")
    d = camera_rays(K, hw, T_world_cam[:3, :3])
    T_cam_world = np.linalg.inv(T_world_cam)

    # the room seen from inside: the nearest exit of the ray through the six faces
    depth = np.full((h, w), np.inf, np.float32)
    prim_id = np.zeros((h, w), np.int16)
    for axis in range(3):
        inv = 1.0 / _safe(d[axis])
        pos = d[axis] > 0
        t_face = np.where(pos, np.float32(layout.size[axis] - o[axis]) * inv, np.float32(-o[axis]) * inv)
        closer = t_face < depth
        depth[closer] = t_face[closer]
        prim_id[closer] = (2 * axis + pos[closer]).astype(np.int16)  # 0: x=0, 1: x=Lx, 2: y=0, ...

    boxes = _screen_boxes(layout.corners, T_cam_world, K, hw) if layout.primitives else np.zeros((0, 4), np.int64)
    seen = [k for k in range(len(layout.primitives)) if boxes[k, 0] < boxes[k, 1] and boxes[k, 2] < boxes[k, 3]]
    area = (boxes[:, 1] - boxes[:, 0]) * (boxes[:, 3] - boxes[:, 2])
    # primitives in order, in chunks of at most _MAX_PAIRS (pixel, primitive) pairs
    chunk: list[int] = []
    pairs = 0
    for k in seen:
        chunk.append(k)
        pairs += int(area[k])
        if pairs >= _MAX_PAIRS or k == seen[-1]:
            _nearest_of(layout, o, d, boxes, chunk, depth, prim_id)
            chunk, pairs = [], 0
    return o, d, depth, prim_id


# (pixel, primitive) pairs intersected at once: bounds the memory of a large image
_MAX_PAIRS = 1 << 19


def _window_pixels(boxes: np.ndarray, ks: list[int], width: int) -> tuple[np.ndarray, np.ndarray]:
    """Flat pixel indices of the screen rectangles of primitives ``ks`` (row-major in
    each) and the position in ``ks`` each belongs to."""
    v0, v1, u0, u1 = (boxes[ks, i] for i in range(4))
    wid = u1 - u0
    area = (v1 - v0) * wid
    owner = np.repeat(np.arange(len(ks)), area)
    r = np.arange(int(area.sum())) - np.repeat(np.cumsum(area) - area, area)
    return (v0[owner] + r // wid[owner]) * width + u0[owner] + r % wid[owner], owner


def _box_pairs(o: np.ndarray, d_flat: np.ndarray, prims: list[Primitive], pix: np.ndarray, owner: np.ndarray):
    """Ray parameters of the boxes ``prims`` at pixels ``pix`` (``owner``: which box):
    the slab test in each box's frame (yaw about z), over all boxes at once. Hand-written
    because numpy has no batched ray-box test, and one call per box cost more in Python
    than in arithmetic on small images (the camera-path checks cast 80-pixel-wide views).
    Bit for bit the per-box loop it replaced (tests/test_synth.py keeps that loop as the
    oracle): the same float32/float64 operations in the same order."""
    # cos and sin one by one, as the loop did: numpy's vector loops may round them differently
    c = np.array([np.float32(np.cos(prim.yaw)) for prim in prims], np.float32)
    s = np.array([np.float32(np.sin(prim.yaw)) for prim in prims], np.float32)
    q = o - np.stack([prim.center for prim in prims])  # (B, 3) float64, as o - prim.center
    half = np.stack([prim.half for prim in prims])
    # float32 x float64 promotes to float64, as the loop's numpy scalars did
    o_l = (c * q[:, 0] + s * q[:, 1], -s * q[:, 0] + c * q[:, 1], q[:, 2])
    lo = [(-half[:, k] - o_l[k]).astype(np.float32) for k in range(3)]
    hi = [(half[:, k] - o_l[k]).astype(np.float32) for k in range(3)]
    cp, sp = c[owner], s[owner]
    dx, dy = d_flat[0, pix], d_flat[1, pix]
    d_l = (cp * dx + sp * dy, -sp * dx + cp * dy, d_flat[2, pix])
    t_in, t_out = None, None
    for k in range(3):
        inv = 1.0 / _safe(d_l[k])
        ta, tb = lo[k][owner] * inv, hi[k][owner] * inv
        near, far = np.minimum(ta, tb), np.maximum(ta, tb)
        t_in = near if t_in is None else np.maximum(t_in, near)
        t_out = far if t_out is None else np.minimum(t_out, far)
    return np.where((t_out >= t_in) & (t_in > _NEAR_M), t_in, np.inf)


def _nearest_of(
    layout: Layout,
    o: np.ndarray,
    d: np.ndarray,
    boxes: np.ndarray,
    ks: list[int],
    depth: np.ndarray,
    prim_id: np.ndarray,
) -> None:
    """Update ``depth`` and ``prim_id`` in place with primitives ``ks`` (ascending) as if
    each were tested in turn and kept where strictly nearer: per pixel the nearest hit,
    the lowest primitive index among equal ones, and what is already there on a tie."""
    h, w = depth.shape
    d_flat = d.reshape(3, -1)
    pix_all, k_all, t_all = [], [], []
    box_ks = [k for k in ks if layout.primitives[k].kind == "box"]
    if box_ks:
        pix, owner = _window_pixels(boxes, box_ks, w)
        pix_all.append(pix)
        k_all.append(np.asarray(box_ks)[owner])
        t_all.append(_box_pairs(o, d_flat, [layout.primitives[k] for k in box_ks], pix, owner))
    for k in ks:
        prim = layout.primitives[k]
        if prim.kind == "box":
            continue
        v0, v1, u0, u1 = boxes[k]
        pix = (np.arange(v0, v1)[:, None] * w + np.arange(u0, u1)).ravel()
        pix_all.append(pix)
        k_all.append(np.full(len(pix), k))
        t_all.append(_T_FUNCS[prim.kind](o, d[:, v0:v1, u0:u1], prim).ravel())
    pix, kk, t = np.concatenate(pix_all), np.concatenate(k_all), np.concatenate(t_all)
    flat_depth, flat_id = depth.reshape(-1), prim_id.reshape(-1)
    nearer = t < flat_depth[pix]
    pix, kk, t = pix[nearer], kk[nearer], t[nearer]
    t_min = np.full(h * w, np.inf, np.float32)
    np.minimum.at(t_min, pix, t)
    first = t == t_min[pix]
    k_min = np.full(h * w, len(layout.primitives), np.int64)
    np.minimum.at(k_min, pix[first], kk[first])
    hit = k_min < len(layout.primitives)
    flat_depth[hit] = t_min[hit]
    flat_id[hit] = (6 + k_min[hit]).astype(np.int16)


def raycast_depth(layout: Layout, T_world_cam: np.ndarray, K: np.ndarray, hw: tuple[int, int]) -> np.ndarray:
    """The exact z-depth (H, W) float32 of every pixel, equal to :func:`raycast`'s
    ``depth_m`` without the surface attributes (what the camera-path checks need)."""
    return _nearest_hits(layout, T_world_cam, K, hw)[2]


def raycast(layout: Layout, T_world_cam: np.ndarray, K: np.ndarray, hw: tuple[int, int]) -> RayHits:
    """Exact depth and surface attributes of every pixel.

    Args:
        layout: the room.
        T_world_cam: (4, 4) float64 camera-to-world pose (OpenCV camera axes).
        K: (3, 3) intrinsics at ``hw``.
        hw: image size (H, W).

    Returns:
        :class:`RayHits` (all pixels hit something inside the closed room).
    """
    o, d, depth, prim_id = _nearest_hits(layout, T_world_cam, K, hw)
    h, w = hw
    points = (o.astype(np.float32) + depth[..., None] * np.moveaxis(d, 0, -1)).astype(np.float32)
    normals = np.zeros((h, w, 3), np.float32)
    uv = np.zeros((h, w, 2), np.float32)
    material = np.zeros((h, w), np.int16)
    flat_id = prim_id.ravel()
    order = np.argsort(flat_id, kind="stable")  # groups pixels by what they hit
    ids, starts = np.unique(flat_id[order], return_index=True)
    bounds = list(starts[1:]) + [len(order)]
    pts_flat, n_flat, uv_flat, m_flat = (
        points.reshape(-1, 3),
        normals.reshape(-1, 3),
        uv.reshape(-1, 2),
        material.ravel(),
    )
    for pid, s, e in zip(ids, starts, bounds):
        idx = order[s:e]
        p = pts_flat[idx]
        if pid < 6:
            axis = pid // 2
            n_flat[idx] = _FACE_NORMALS[pid]
            others = [a for a in (0, 1, 2) if a != axis]
            uv_flat[idx] = p[:, others]
            m_flat[idx] = layout.face_materials[pid]
            off = (0.0, 0.0)
            mat = layout.materials[layout.face_materials[pid]]
        else:
            prim = layout.primitives[pid - 6]
            n, q = _ATTR_FUNCS[prim.kind](p, prim)
            n_flat[idx] = n
            uv_flat[idx] = q
            m_flat[idx] = prim.material
            off = prim.uv_offset
            mat = layout.materials[prim.material]
        uv_flat[idx] = uv_flat[idx] / np.float32(mat.period_m) + np.asarray(off, np.float32)
    return RayHits(depth.astype(np.float32), prim_id, points, normals, uv, material)


def _sample_bilinear(tex: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Bilinear, wrap-around lookup of a tileable (S, S, 3) uint8 texture at (N, 2)
    texture coordinates in tiles; returns (N, 3) float32 in [0, 1].

    The N lookups are laid out as an image of 1024-wide rows for cv2.remap (which
    takes image-shaped maps), so only the pixels of this texture are sampled.
    """
    s = tex.shape[0]
    n = len(uv)
    cols = 1024
    rows = -(-n // cols)
    maps = np.zeros((2, rows * cols), np.float32)
    maps[0, :n] = (uv[:, 0] % 1.0) * s - 0.5
    maps[1, :n] = (uv[:, 1] % 1.0) * s - 0.5
    out = cv2.remap(
        tex, maps[0].reshape(rows, cols), maps[1].reshape(rows, cols), cv2.INTER_LINEAR, borderMode=cv2.BORDER_WRAP
    )
    return out.reshape(-1, 3)[:n].astype(np.float32) * np.float32(1.0 / 255.0)


def albedo(layout: Layout, hits: RayHits) -> np.ndarray:
    """Texture albedo of every pixel.

    Returns:
        (H, W, 3) float32 RGB in [0, 1].
    """
    h, w = hits.depth_m.shape
    out = np.zeros((h * w, 3), np.float32)
    mat_flat = hits.material.ravel()
    uv_flat = hits.uv.reshape(-1, 2)
    order = np.argsort(mat_flat, kind="stable")
    ids, starts = np.unique(mat_flat[order], return_index=True)
    for m, s, e in zip(ids, starts, list(starts[1:]) + [len(order)]):
        idx = order[s:e]
        out[idx] = _sample_bilinear(layout.textures[layout.materials[int(m)].texture], uv_flat[idx])
    return out.reshape(h, w, 3)


def shade(layout: Layout, hits: RayHits, albedo_rgb: np.ndarray | None = None) -> np.ndarray:
    """Colour of every pixel: texture albedo x (ambient + lambertian point light with
    a soft distance falloff).

    Args:
        albedo_rgb: (H, W, 3) albedo from :func:`albedo` (computed when None).

    Returns:
        (H, W, 3) float32 RGB in [0, 1].
    """
    if albedo_rgb is None:
        albedo_rgb = albedo(layout, hits)
    to_light = layout.light_pos.astype(np.float32) - hits.points_world
    dist = np.sqrt((to_light * to_light).sum(-1))
    cos = (hits.normals_world * to_light).sum(-1) / np.maximum(dist, 1e-6)
    falloff = 1.0 / (1.0 + (dist / 3.0) ** 2)
    light = layout.ambient + 1.1 * np.clip(cos, 0, 1) * falloff
    return np.clip(albedo_rgb * light[..., None], 0, 1)


def thin_mask(layout: Layout, hits: RayHits) -> np.ndarray:
    """(H, W) bool: pixels whose surface is a thin primitive (:attr:`Primitive.thin`)."""
    thin = np.zeros(6 + len(layout.primitives), bool)
    thin[6:] = [p.thin for p in layout.primitives]
    return thin[hits.prim]
