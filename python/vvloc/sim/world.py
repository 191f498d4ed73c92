"""Procedural worlds built from boxes, quads and cylinders: an outdoor parking lot and an
underground garage of several near-identical floors.

World frame: x east, y north, z up, metres. Every random choice comes from the world's seed;
the per-session variation (cars that came or left) from the session's own seed.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from vvloc._checks import positive_int

# Material ids, mirrored in the fragment shader (render.py).
ASPHALT, PAINT, CAR, GLASS, CONCRETE, FACADE, FOLIAGE, SIGN, EMISSIVE, MARKER, BARK = range(11)

FLOOR_HEIGHT = 3.2  # garage storey pitch, m
CEILING = 2.8  # garage clear height, m


class MeshBuilder:
    """Collects triangles as interleaved float32 vertices (pos 3, normal 3, colour 3, material)."""

    def __init__(self) -> None:
        self._verts: list[np.ndarray] = []
        self._idx: list[np.ndarray] = []
        self._n = 0
        # point lights: x, y, z, range m, colour, floor
        self.lights: list[tuple[float, float, float, float, tuple[float, float, float], int]] = []

    def _add(
        self, pos: np.ndarray, nrm: np.ndarray, color: tuple[float, ...], mat: int, tris: np.ndarray
    ) -> None:
        v = np.empty((len(pos), 10), dtype=np.float32)
        v[:, 0:3] = pos
        v[:, 3:6] = nrm
        v[:, 6:9] = color
        v[:, 9] = mat
        self._verts.append(v)
        self._idx.append(tris.astype(np.uint32).reshape(-1) + self._n)
        self._n += len(pos)

    def quad(self, corners: np.ndarray, color: tuple[float, ...], mat: int) -> None:
        """A planar quad from 4 corners (4, 3) in order around its outline."""
        c = np.asarray(corners, dtype=np.float64)
        n = np.cross(c[1] - c[0], c[2] - c[0])
        n /= np.linalg.norm(n)
        self._add(c, np.tile(n, (4, 1)), color, mat, np.array([0, 1, 2, 0, 2, 3]))

    def ground_rect(
        self,
        cx: float,
        cy: float,
        lx: float,
        ly: float,
        yaw: float,
        z: float,
        color: tuple[float, ...],
        mat: int,
    ) -> None:
        """A horizontal rectangle (e.g. a painted line) centred at (cx, cy), lengths along its
        own axes, rotated by ``yaw``, at height ``z``."""
        c, s = math.cos(yaw), math.sin(yaw)
        pts = []
        for ax, ay in ((-1, -1), (1, -1), (1, 1), (-1, 1)):
            dx, dy = ax * lx / 2, ay * ly / 2
            pts.append((cx + c * dx - s * dy, cy + s * dx + c * dy, z))
        self.quad(np.array(pts), color, mat)

    def box(
        self,
        center: tuple[float, float, float],
        size: tuple[float, float, float],
        color: tuple[float, ...],
        mat: int,
        yaw: float = 0.0,
        bottom: bool = False,
    ) -> None:
        """An axis-aligned (then yawed) box; ``center`` is the centre of its *base* face."""
        cx, cy, z0 = center
        lx, ly, lz = size
        c, s = math.cos(yaw), math.sin(yaw)
        R = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])
        faces = [((1, 0, 0), 0), ((-1, 0, 0), 0), ((0, 1, 0), 1), ((0, -1, 0), 1), ((0, 0, 1), 2)]
        if bottom:
            faces.append(((0, 0, -1), 2))
        half = np.array([lx / 2, ly / 2, lz / 2])
        ctr = np.array([0.0, 0.0, lz / 2])
        pos_all, nrm_all, tri_all = [], [], []
        for k, (face, _) in enumerate(faces):
            n = np.array(face, dtype=np.float64)
            # two tangent axes of the face
            a = np.roll(n, 1)
            b = np.cross(n, a)
            corners = [
                ctr + half * (n + sa * a + sb * b)
                for sa, sb in ((-1, -1), (1, -1), (1, 1), (-1, 1))
            ]
            pos_all.append(np.array(corners) @ R.T + (cx, cy, z0))
            nrm_all.append(np.tile(R @ n, (4, 1)))
            tri_all.append(np.array([0, 1, 2, 0, 2, 3]) + 4 * k)
        self._add(
            np.concatenate(pos_all), np.concatenate(nrm_all), color, mat, np.concatenate(tri_all)
        )

    def cylinder(
        self,
        center: tuple[float, float, float],
        radius: float,
        height: float,
        color: tuple[float, ...],
        mat: int,
        sides: int = 8,
        top: bool = True,
    ) -> None:
        """A vertical prism of ``sides`` faces; ``center`` is the centre of its base."""
        cx, cy, z0 = center
        ang = np.linspace(0, 2 * np.pi, sides, endpoint=False)
        pos, nrm, tris = [], [], []
        for k in range(sides):
            a0, a1 = ang[k], ang[(k + 1) % sides]
            am = (a0 + a1) / 2 if k + 1 < sides else (a0 + a1 + 2 * np.pi) / 2
            p = [
                (cx + radius * math.cos(a), cy + radius * math.sin(a), z)
                for a, z in ((a0, z0), (a1, z0), (a1, z0 + height), (a0, z0 + height))
            ]
            pos.extend(p)
            nrm.extend([(math.cos(am), math.sin(am), 0.0)] * 4)
            tris.append(np.array([0, 1, 2, 0, 2, 3]) + 4 * k)
        if top:
            base = len(pos)
            pos.append((cx, cy, z0 + height))
            nrm.append((0.0, 0.0, 1.0))
            for k in range(sides):
                pos.append(
                    (cx + radius * math.cos(ang[k]), cy + radius * math.sin(ang[k]), z0 + height)
                )
                nrm.append((0.0, 0.0, 1.0))
                tris.append(np.array([base, base + 1 + k, base + 1 + (k + 1) % sides]))
        self._add(np.array(pos), np.array(nrm), color, mat, np.concatenate(tris))

    def digit(
        self,
        d: int,
        origin: tuple[float, float, float],
        along: tuple[float, float],
        normal: tuple[float, float],
        size: float,
        color: tuple[float, ...],
    ) -> None:
        """A seven-segment digit painted on a vertical wall: ``origin`` is its bottom-left corner,
        ``along`` the unit wall direction (x), ``normal`` the wall's outward normal.

        The digit reads upright to a viewer facing the wall when ``along`` points to that
        viewer's right, (−normal_y, normal_x). Known (2026-12-05): the world builders pass the
        opposite direction (the parking lot's wall signs, the garage's level signs and its
        pillar numbers), so every painted digit reads mirrored (a 2 as a 5). The signs still
        differ between floors as they should; kept because every rendered dataset and the
        committed model were made with them, and a fix changes each image that shows a sign
        (for the next retraining, ``models/synth-small/HISTORY.md``, "Held for the next
        retraining")."""
        segs = {
            0: "abcdef",
            1: "bc",
            2: "abged",
            3: "abgcd",
            4: "fgbc",
            5: "afgcd",
            6: "afgedc",
            7: "abc",
            8: "abcdefg",
            9: "abcdfg",
        }[d % 10]
        w, h, t = 0.6 * size, size, 0.14 * size
        # segment rectangles (u0, v0, u1, v1) in the digit's plane
        rects = {
            "a": (0, h - t, w, h),
            "g": (0, h / 2 - t / 2, w, h / 2 + t / 2),
            "d": (0, 0, w, t),
            "f": (0, h / 2, t, h),
            "b": (w - t, h / 2, w, h),
            "e": (0, 0, t, h / 2),
            "c": (w - t, 0, w, h / 2),
        }
        o = np.array(origin, dtype=np.float64) + 0.02 * np.array([normal[0], normal[1], 0.0])
        ux = np.array([along[0], along[1], 0.0])
        uz = np.array([0.0, 0.0, 1.0])
        for sname in segs:
            u0, v0, u1, v1 = rects[sname]
            pts = [
                o + u0 * ux + v0 * uz,
                o + u1 * ux + v0 * uz,
                o + u1 * ux + v1 * uz,
                o + u0 * ux + v1 * uz,
            ]
            self.quad(np.array(pts), color, SIGN)

    def arrays(self) -> tuple[np.ndarray, np.ndarray]:
        """(N, 10) float32 vertices and (K,) uint32 triangle indices."""
        if not self._verts:
            return np.zeros((0, 10), np.float32), np.zeros(0, np.uint32)
        return np.concatenate(self._verts), np.concatenate(self._idx)


@dataclass
class Bay:
    """A parking bay: centre (x, y), the direction a car parks in (yaw), storey, z."""

    x: float
    y: float
    yaw: float
    floor: int = 0
    z: float = 0.0


@dataclass
class World:
    """A static scene plus what varies per session (parked cars).

    Attributes:
        kind: "parking" or "garage".
        static: (vertices, indices) of everything that never changes, laid out as
            :meth:`mesh` returns them.
        bays: parking bays; ``occupancy`` (B,) bool and ``car_colors`` (B, 3) of the base world.
        lights: (L, 4) float32 light positions (x, y, z) and range (m); ``light_colors`` (L, 3);
            ``light_floors`` (L,) the storey each light is on.
        routes: per floor, a closed loop of waypoints (K, 2) along the aisle centres.
        floor_z: (F,) float height of each floor's driving surface, metres (world z, up; 0 and
            below: the lower storeys).
        level_signs: (S, 4) float64 centres (x, y, z) and storey of the garage's wall level-sign
            panels (1.4 × 1.3 m, the storey's digit 0.9 m tall on it); (0, 4) elsewhere.
    """

    kind: str
    seed: int
    static: tuple[np.ndarray, np.ndarray]
    bays: list[Bay]
    occupancy: np.ndarray
    car_colors: np.ndarray
    lights: np.ndarray
    light_colors: np.ndarray
    light_floors: np.ndarray
    routes: list[np.ndarray]
    floor_z: np.ndarray
    extra: dict[str, float] = field(default_factory=dict)
    level_signs: np.ndarray = field(default_factory=lambda: np.zeros((0, 4)))

    def cars(
        self, change_fraction: float = 0.0, session_seed: int = 0
    ) -> tuple[np.ndarray, np.ndarray]:
        """The parked cars of a session: occupancy (B,) bool and colours (B, 3) of ``bays``, with
        ``change_fraction`` of the bays toggled (cars that left or arrived, new colours), drawn
        from ``session_seed``."""
        _check_share(change_fraction, "change_fraction")
        occ = self.occupancy.copy()
        colors = self.car_colors.copy()
        if change_fraction > 0:
            rng = np.random.default_rng([self.seed, session_seed, 7])
            flip = rng.random(len(occ)) < change_fraction
            occ ^= flip
            colors[flip] = rng.choice(CAR_PALETTE, size=int(flip.sum()))
        return occ, colors

    def mesh(
        self, change_fraction: float = 0.0, session_seed: int = 0
    ) -> tuple[np.ndarray, np.ndarray]:
        """The full mesh with the parked cars of :meth:`cars` (same arguments): vertices (N, 10)
        float32 (world position x, y, z in metres, unit normal, linear RGB colour, material id
        as a float; :class:`MeshBuilder`) and triangle indices (K,) uint32, three per
        triangle."""
        occ, colors = self.cars(change_fraction, session_seed)
        mb = MeshBuilder()
        rng = np.random.default_rng([self.seed, 11])
        jitter = rng.uniform(-1, 1, size=(len(self.bays), 3))
        for b, on, col, j in zip(self.bays, occ, colors, jitter, strict=True):
            if on:
                add_car(
                    mb, b.x + 0.15 * j[0], b.y + 0.15 * j[1], b.z, b.yaw + 0.05 * j[2], tuple(col)
                )
        v, i = mb.arrays()
        sv, si = self.static
        return np.concatenate([sv, v]), np.concatenate([si, i + len(sv)])


CAR_PALETTE = np.array(
    [
        (0.75, 0.75, 0.78),
        (0.1, 0.1, 0.12),
        (0.9, 0.9, 0.92),
        (0.55, 0.05, 0.05),
        (0.1, 0.2, 0.5),
        (0.35, 0.36, 0.4),
        (0.15, 0.35, 0.2),
        (0.8, 0.55, 0.1),
        (0.45, 0.3, 0.2),
        (0.2, 0.5, 0.7),
    ],
    dtype=np.float32,
)


def add_car(
    mb: MeshBuilder, x: float, y: float, z: float, yaw: float, color: tuple[float, ...]
) -> None:
    """A parked car (body, glass cabin, roof, wheels) centred at (x, y), nose along ``yaw``."""
    c, s = math.cos(yaw), math.sin(yaw)

    def at(dx: float, dy: float) -> tuple[float, float]:
        return x + c * dx - s * dy, y + s * dx + c * dy

    mb.box((*at(0, 0), z + 0.3), (4.3, 1.8, 0.75), color, CAR, yaw)
    mb.box((*at(-0.2, 0), z + 1.05), (2.3, 1.6, 0.45), (0.15, 0.18, 0.22), GLASS, yaw)
    mb.box((*at(-0.2, 0), z + 1.5), (2.1, 1.5, 0.06), color, CAR, yaw)
    for dx in (-1.35, 1.35):
        for dy in (-0.8, 0.8):
            mb.box((*at(dx, dy), z), (0.65, 0.25, 0.6), (0.05, 0.05, 0.05), CONCRETE, yaw)
    mb.box((*at(2.16, 0.6), z + 0.75), (0.02, 0.3, 0.12), (0.95, 0.95, 0.85), EMISSIVE, yaw)
    mb.box((*at(2.16, -0.6), z + 0.75), (0.02, 0.3, 0.12), (0.95, 0.95, 0.85), EMISSIVE, yaw)


WHITE = (0.92, 0.92, 0.88)
YELLOW = (0.9, 0.75, 0.15)


def _bay_rows(
    mb: MeshBuilder,
    x0: float,
    n_bays: int,
    y_aisle: float,
    aisle_w: float,
    z: float,
    floor: int,
    bays: list[Bay],
    bay_w: float = 2.6,
    depth: float = 5.0,
) -> None:
    """Bays on both sides of an aisle running along x at ``y_aisle``, with their painted lines."""
    for side in (-1, 1):
        y_edge = y_aisle + side * aisle_w / 2
        yc = y_edge + side * depth / 2
        for k in range(n_bays + 1):
            xl = x0 + k * bay_w
            mb.ground_rect(xl, yc, 0.12, depth, 0.0, z + 0.01, WHITE, PAINT)
        mb.ground_rect(
            x0 + n_bays * bay_w / 2,
            y_edge + side * depth,
            n_bays * bay_w,
            0.12,
            0.0,
            z + 0.01,
            WHITE,
            PAINT,
        )
        for k in range(n_bays):
            # nose into the bay: away from the aisle
            bays.append(Bay(x0 + (k + 0.5) * bay_w, yc, math.pi / 2 * side, floor, z))
    # dashed centre line
    length = n_bays * bay_w
    for k in range(int(length // 4)):
        mb.ground_rect(x0 + 4 * k + 1.5, y_aisle, 2.0, 0.12, 0.0, z + 0.01, YELLOW, PAINT)


def _zebra(mb: MeshBuilder, x: float, y: float, width: float, z: float) -> None:
    for k in range(int(width // 1.0)):
        mb.ground_rect(x, y - width / 2 + 0.5 + k, 2.5, 0.5, 0.0, z + 0.01, WHITE, PAINT)


def _check_share(value: float, name: str) -> None:
    """``ValueError`` naming ``name`` unless ``value`` is a number in [0, 1] (a share of bays)."""
    if isinstance(value, bool) or not isinstance(value, (int, float, np.number)):
        raise ValueError(f"{name}: expected a share in [0, 1], got {value!r}")
    if not 0.0 <= value <= 1.0:  # NaN fails too
        raise ValueError(f"{name}: expected a share in [0, 1], got {value!r}")


def parking_world(
    seed: int = 0, *, n_aisles: int = 3, n_bays: int = 20, occupancy: float = 0.65
) -> World:
    """An outdoor parking lot: ``n_aisles`` aisles running east-west with bays on both sides,
    lamp posts on the medians, a perimeter road, walls with signs, trees, buildings with window
    grids around it."""
    if n_aisles < 1 or n_bays < 4:
        raise ValueError(f"n_aisles >= 1 and n_bays >= 4 expected, got {n_aisles}, {n_bays}")
    _check_share(occupancy, "occupancy")
    rng = np.random.default_rng([seed, 1])
    mb = MeshBuilder()
    bays: list[Bay] = []
    bay_w, depth, aisle_w, median = 2.6, 5.0, 7.0, 1.2
    pitch = aisle_w + 2 * depth + median
    length = n_bays * bay_w
    y_aisles = [depth + aisle_w / 2 + k * pitch for k in range(n_aisles)]
    y_top = y_aisles[-1] + aisle_w / 2 + depth
    x_min, x_max, y_min, y_max = -26.0, length + 26.0, -20.0, y_top + 18.0
    # ground
    mb.quad(
        np.array(
            [
                (x_min - 60, y_min - 60, 0),
                (x_max + 60, y_min - 60, 0),
                (x_max + 60, y_max + 60, 0),
                (x_min - 60, y_max + 60, 0),
            ]
        ),
        (0.36, 0.36, 0.37),
        ASPHALT,
    )
    for k, ya in enumerate(y_aisles):
        _bay_rows(mb, 0.0, n_bays, ya, aisle_w, 0.0, 0, bays)
        _zebra(mb, -2.0, ya, aisle_w, 0.0)
        _zebra(mb, length + 2.0, ya, aisle_w, 0.0)
        if k + 1 < n_aisles:
            ym = ya + aisle_w / 2 + depth + median / 2
            mb.box((length / 2, ym, 0.0), (length, median, 0.15), (0.55, 0.55, 0.5), CONCRETE)
            for xl in np.arange(3.0, length, 13.0):
                _lamp(mb, xl, ym, 0.0)
    # perimeter road edge lines and stop lines
    mb.ground_rect(length / 2, -8.0, length + 30, 0.15, 0.0, 0.01, WHITE, PAINT)
    # lamp posts along the perimeter
    for xl in np.arange(-12.0, length + 14.0, 16.0):
        _lamp(mb, float(xl), -13.0, 0.0)
    # walls with signs
    wall_h = 2.2
    for x0, y0, x1, y1 in (
        (x_min, y_min, x_max, y_min),
        (x_max, y_min, x_max, y_max),
        (x_max, y_max, x_min, y_max),
        (x_min, y_max, x_min, y_min),
    ):
        lx, ly = x1 - x0, y1 - y0
        L = math.hypot(lx, ly)
        yaw = math.atan2(ly, lx)
        mb.box(
            ((x0 + x1) / 2, (y0 + y1) / 2, 0.0),
            (L, 0.3, wall_h),
            tuple(rng.uniform(0.45, 0.7, 3)),
            CONCRETE,
            yaw,
        )
        ux, uy = lx / L, ly / L
        nx, ny = -uy, ux  # inward normal (walls run counter-clockwise)
        for t in np.arange(6.0, L - 4.0, float(rng.uniform(9, 14))):
            col = tuple(CAR_PALETTE[rng.integers(len(CAR_PALETTE))] * 0.6 + 0.3)
            px, py = x0 + ux * t + nx * 0.17, y0 + uy * t + ny * 0.17
            w = float(rng.uniform(1.2, 2.5))
            mb.quad(
                np.array(
                    [
                        (px, py, 0.8),
                        (px + ux * w, py + uy * w, 0.8),
                        (px + ux * w, py + uy * w, 1.9),
                        (px, py, 1.9),
                    ]
                ),
                col,
                SIGN,
            )
            mb.digit(
                int(rng.integers(10)),
                (px + ux * 0.2 + nx * 0.01, py + uy * 0.2 + ny * 0.01, 0.95),
                (ux, uy),
                (nx, ny),
                0.8,
                (0.05, 0.05, 0.05),
            )
    # trees inside the south and west margins
    for k in range(int(rng.integers(14, 20))):
        if k % 2:
            tx, ty = float(rng.uniform(x_min + 3, x_max - 3)), float(rng.uniform(y_min + 2, -15.5))
        else:
            tx, ty = float(rng.uniform(x_min + 2, -16.0)), float(rng.uniform(y_min + 3, y_max - 3))
        _tree(mb, tx, ty, rng)
    # buildings beyond the walls
    for side in range(4):
        pos = x_min - 10.0
        span = (x_max - x_min) if side in (0, 2) else (y_max - y_min)
        pos = 0.0
        while pos < span:
            w = float(rng.uniform(12, 28))
            h = float(rng.uniform(8, 26))
            d = float(rng.uniform(10, 18))
            col = tuple(rng.uniform(0.45, 0.8, 3) * np.array([1.0, 0.95, 0.9]))
            c = pos + w / 2
            if side == 0:
                center, size = (x_min + c, y_min - 6 - d / 2, 0.0), (w, d, h)
            elif side == 1:
                center, size = (x_max + 6 + d / 2, y_min + c, 0.0), (d, w, h)
            elif side == 2:
                center, size = (x_min + c, y_max + 6 + d / 2, 0.0), (w, d, h)
            else:
                center, size = (x_min - 6 - d / 2, y_min + c, 0.0), (d, w, h)
            mb.box(center, size, col, FACADE)
            pos += w + float(rng.uniform(2, 8))
    static = mb.arrays()
    occ = rng.random(len(bays)) < occupancy
    colors = CAR_PALETTE[rng.integers(len(CAR_PALETTE), size=len(bays))]
    # closed loop: serpentine through the aisles, back along the perimeter road
    xw, xe = -6.0, length + 6.0
    pts = []
    for k, ya in enumerate(y_aisles):
        a, b = (xw, xe) if k % 2 == 0 else (xe, xw)
        pts += [(a, ya), (b, ya)]
    x_last = pts[-1][0]
    x_far = xe + 7.0 if x_last == xe else xw - 7.0
    pts[-1] = (x_far, y_aisles[-1])
    pts += [(x_far, -8.0 + 2.0), (xw - 7.0 if x_far > 0 else xe + 7.0, -6.0)]
    pts += [(pts[-1][0], y_aisles[0])]
    route = np.array(pts, dtype=np.float64)
    lights, lcols, lfloors = _collect_lights(mb)
    return World(
        "parking", seed, static, bays, occ, colors, lights, lcols, lfloors, [route], np.zeros(1)
    )


_LIGHTS: list[tuple[float, float, float, float, tuple[float, float, float]]] = []


def _lamp(mb: MeshBuilder, x: float, y: float, z: float) -> None:
    mb.cylinder((x, y, z), 0.1, 6.0, (0.4, 0.42, 0.45), CONCRETE, sides=6)
    mb.box((x, y, z + 6.0), (0.9, 0.35, 0.12), (0.3, 0.3, 0.32), CONCRETE)
    mb.box((x, y, z + 5.94), (0.7, 0.25, 0.06), (1.0, 0.85, 0.6), EMISSIVE, bottom=True)
    mb.lights.append((x, y, z + 5.9, 9.0, (1.0, 0.8, 0.55), 0))


def _ceiling_light(mb: MeshBuilder, x: float, y: float, z_ceiling: float, floor: int) -> None:
    mb.box((x, y, z_ceiling - 0.08), (1.2, 0.25, 0.08), (0.95, 0.97, 1.0), EMISSIVE, bottom=True)
    mb.lights.append((x, y, z_ceiling - 0.2, 4.0, (0.85, 0.9, 1.0), floor))


def _collect_lights(mb: MeshBuilder) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    ls = mb.lights
    pos = np.array([(x, y, z, r) for x, y, z, r, _, _ in ls], dtype=np.float32).reshape(-1, 4)
    col = np.array([c for *_, c, _ in ls], dtype=np.float32).reshape(-1, 3)
    floors = np.array([f for *_, f in ls], dtype=np.int64)
    return pos, col, floors


def _tree(mb: MeshBuilder, x: float, y: float, rng: np.random.Generator) -> None:
    h = float(rng.uniform(2.0, 3.5))
    mb.cylinder((x, y, 0.0), 0.2, h, (0.35, 0.25, 0.15), BARK, sides=6)
    r = float(rng.uniform(1.5, 2.6))
    g = (0.15 + 0.1 * float(rng.random()), 0.35 + 0.15 * float(rng.random()), 0.12)
    mb.cylinder((x, y, h - 0.3), r, float(rng.uniform(1.8, 3.0)), g, FOLIAGE, sides=8)
    mb.cylinder((x, y, h + 1.8), r * 0.6, 1.2, g, FOLIAGE, sides=8)


#: Level colours of ``floor_marking="pillars"`` (floor f paints its pillars FLOOR_COLOURS[f % 6]).
FLOOR_COLOURS = (
    (0.85, 0.72, 0.1),  # yellow
    (0.15, 0.35, 0.85),  # blue
    (0.2, 0.65, 0.25),  # green
    (0.8, 0.2, 0.15),  # red
    (0.6, 0.25, 0.7),  # purple
    (0.9, 0.5, 0.1),  # orange
)
FLOOR_MARKINGS = ("walls", "pillars")


def garage_world(
    seed: int = 0,
    *,
    floors: int = 2,
    n_bays: int = 18,
    occupancy: float = 0.6,
    floor_marking: str = "walls",
) -> World:
    """An underground garage of ``floors`` storeys of the same layout (pillars, bays, ceiling
    lights, walls); the level signs (digits) and a quarter of the parked cars differ between
    floors (the cross-floor look-alikes).

    ``floor_marking`` says how a floor shows its level: ``"walls"`` (default), only four level
    signs on the south and north walls (visible from few places; every pillar has the same
    yellow band), or ``"pillars"``, as many real garages do it, additionally a level colour on
    every pillar (a 1.2 m band of :data:`FLOOR_COLOURS`) with the level number above it on the
    faces towards the aisles. Geometry, cars and lights are the same for both.
    Floor f's driving surface is at z = −3.2·f."""
    floors = positive_int(floors, "floors")
    n_bays = positive_int(n_bays, "n_bays", 3)  # the level signs need the room
    _check_share(occupancy, "occupancy")
    if floor_marking not in FLOOR_MARKINGS:
        raise ValueError(f"floor_marking: expected one of {FLOOR_MARKINGS}, got {floor_marking!r}")
    rng = np.random.default_rng([seed, 2])
    mb = MeshBuilder()
    bays: list[Bay] = []
    bay_w, depth, aisle_w = 2.6, 5.0, 6.5
    length = n_bays * bay_w
    y_aisles = [depth + aisle_w / 2, depth + aisle_w / 2 + aisle_w + 2 * depth]
    y_top = y_aisles[-1] + aisle_w / 2 + depth
    x_min, x_max, y_min, y_max = -9.0, length + 9.0, -0.5, y_top + 0.5
    # one layout of pillars, wall signs and wall colours shared by every floor (the look-alikes)
    wall_col = tuple(rng.uniform(0.55, 0.7, 3))
    sign_pos = [(float(rng.uniform(3, length - 3))) for _ in range(4)]
    floor_z = np.array([-FLOOR_HEIGHT * f for f in range(floors)])
    signs: list[tuple[float, float, float, int]] = []
    for f, z in enumerate(floor_z):
        # floor slab (top surface) and ceiling (underside of the slab above)
        mb.quad(
            np.array([(x_min, y_min, z), (x_max, y_min, z), (x_max, y_max, z), (x_min, y_max, z)]),
            (0.5, 0.5, 0.48),
            ASPHALT,
        )
        zc = z + CEILING
        mb.quad(
            np.array(
                [(x_min, y_max, zc), (x_max, y_max, zc), (x_max, y_min, zc), (x_min, y_min, zc)]
            ),
            (0.6, 0.6, 0.58),
            CONCRETE,
        )
        for ya in y_aisles:
            _bay_rows(mb, 0.0, n_bays, ya, aisle_w, float(z), f, bays)
            for xl in np.arange(1.0, length, 6.0):
                _ceiling_light(mb, float(xl), ya, zc, f)
        for xl in (-4.5, length + 4.5):
            for yl in np.arange(2.0, y_top, 6.0):
                _ceiling_light(mb, xl, float(yl), zc, f)
        # pillars every 3 bays on the bay-row boundaries
        for ya in y_aisles:
            for side in (-1, 1):
                yp = ya + side * (aisle_w / 2 + depth - 0.3)
                for k in range(0, n_bays + 1, 3):
                    xp = k * bay_w
                    mb.box((xp, yp, float(z)), (0.6, 0.6, CEILING), (0.7, 0.7, 0.68), CONCRETE)
                    if floor_marking == "walls":
                        mb.box((xp, yp, float(z) + 0.9), (0.62, 0.62, 0.4), YELLOW, PAINT)
                        continue
                    colour = FLOOR_COLOURS[f % len(FLOOR_COLOURS)]
                    mb.box((xp, yp, float(z) + 0.5), (0.62, 0.62, 1.2), colour, PAINT)
                    ny = -float(side)  # the face towards the aisle
                    ux = ny  # the wall signs' convention for the digit's direction
                    mb.digit(
                        f + 1,
                        (xp - 0.12 * ux, yp + 0.32 * ny, float(z) + 1.8),
                        (ux, 0.0),
                        (0.0, ny),
                        0.4,
                        (0.95, 0.95, 0.95),
                    )
        # perimeter walls
        for x0, y0, x1, y1 in (
            (x_min, y_min, x_max, y_min),
            (x_max, y_min, x_max, y_max),
            (x_max, y_max, x_min, y_max),
            (x_min, y_max, x_min, y_min),
        ):
            lx, ly = x1 - x0, y1 - y0
            L = math.hypot(lx, ly)
            mb.box(
                ((x0 + x1) / 2, (y0 + y1) / 2, float(z)),
                (L, 0.3, CEILING),
                wall_col,
                CONCRETE,
                math.atan2(ly, lx),
            )
        # level signs: a panel with the storey number on the south and north walls
        for k, xs in enumerate(sign_pos):
            wall_y, ny = (y_min + 0.16, 1.0) if k % 2 == 0 else (y_max - 0.16, -1.0)
            ux = 1.0 if ny > 0 else -1.0
            pts = np.array(
                [
                    (xs, wall_y, z + 0.9),
                    (xs + 1.4 * ux, wall_y, z + 0.9),
                    (xs + 1.4 * ux, wall_y, z + 2.2),
                    (xs, wall_y, z + 2.2),
                ]
            )
            mb.quad(pts, (0.1, 0.35, 0.7), SIGN)
            signs.append((xs + 0.7 * ux, wall_y, z + 1.55, f))
            mb.digit(
                f + 1,
                (xs + 0.4 * ux, wall_y + 0.01 * ny, z + 1.1),
                (ux, 0.0),
                (0.0, ny),
                0.9,
                (0.95, 0.95, 0.95),
            )
    static = mb.arrays()
    # floors look alike: every floor starts from floor 0's cars, a quarter of the bays differ
    per_floor = len(bays) // floors
    occ0 = rng.random(per_floor) < occupancy
    col0 = CAR_PALETTE[rng.integers(len(CAR_PALETTE), size=per_floor)]
    occ_f, col_f = [occ0], [col0]
    for _ in range(1, floors):
        flip = rng.random(per_floor) < 0.25
        col = col0.copy()
        col[flip] = CAR_PALETTE[rng.integers(len(CAR_PALETTE), size=int(flip.sum()))]
        occ_f.append(occ0 ^ flip)
        col_f.append(col)
    occ, colors = np.concatenate(occ_f), np.concatenate(col_f)
    xw, xe = -4.5, length + 4.5
    loop = np.array([(xw, y_aisles[0]), (xe, y_aisles[0]), (xe, y_aisles[1]), (xw, y_aisles[1])])
    lights, lcols, lfloors = _collect_lights(mb)
    return World(
        "garage",
        seed,
        static,
        bays,
        occ,
        colors,
        lights,
        lcols,
        lfloors,
        [loop] * floors,
        floor_z,
        level_signs=np.array(signs, dtype=np.float64).reshape(-1, 4),
    )
