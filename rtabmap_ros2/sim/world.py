"""A 2D floor plan of a lab building with textured walls, for the simulated multi-session runs.

The building imitates the one of Labbé & Michaud 2014 §III (about 76 m x 54 m): two corridor
loops (100 m each) around two blocks of offices, a lab and a lobby as open areas, a north wing
leading to an atrium with pillars, rooms with 1 m doors. Free space is drawn as rectangles on a
0.1 m grid; walls are the boundaries between free and occupied cells, merged into line segments
and split into pieces of at most :data:`MAX_SEGMENT_LENGTH_M`. Walls are vertical, zero-thickness
and :data:`WALL_HEIGHT_M` high (2.5D world).

Each wall segment is oriented with the free space on its *right* (``p0 -> p1`` runs left to
right for someone facing the wall), and carries a texture kind:

* ``POSTER``: a distinct crop/transform of a real photograph shipped with scikit-image (no
  download) hung on painted wall -- distinctive features;
* ``REPEATED``: one of a few posters hung in several far-apart places -- perceptual aliasing;
* ``PLAIN``: uniform paint with slight noise -- few features (bad signatures).

Everything random (texture assignment, crops, colours) depends only on the seed. The layout and
the waypoint graph the robot drives on (:attr:`World.nodes`, :attr:`World.edges`) are fixed.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from functools import lru_cache

import cv2
import numpy as np
from scipy import ndimage

logger = logging.getLogger(__name__)

GRID_RESOLUTION_M = 0.1
GRID_ORIGIN_XY = (-16.0, -10.0)
GRID_SIZE_XY_M = (78.0, 56.0)
WALL_HEIGHT_M = 2.5
MAX_SEGMENT_LENGTH_M = 3.5
MIN_POSTER_WALL_M = 1.2  # shorter walls (door jambs, pillars) stay plain

POSTER = 0
REPEATED = 1
PLAIN = 2
KIND_NAMES = {POSTER: "poster", REPEATED: "repeated", PLAIN: "plain"}

# Texture assignment probabilities of the walls long enough for a poster.
P_POSTER = 0.62
P_REPEATED = 0.12
N_REPEATED_POSTERS = 4

# Poster atlas: every poster resampled to this size (texels), plus mip levels for distant walls.
ATLAS_SHAPE = (256, 384)
ATLAS_LEVELS = 3
POSTER_BOTTOM_RANGE_M = (0.15, 0.45)
POSTER_TOP_RANGE_M = (1.7, 2.3)
POSTER_WIDTH_FRACTION = (0.65, 0.92)
POSTER_CROP_SCALE = (0.6, 1.0)  # crop side as a fraction of the photo (smaller = zoomed, blurrier)
BASEBOARD_HEIGHT_M = 0.08

# Tiled paint noise / floor / ceiling textures: texel size (m) and contrast.
PAINT_NOISE_TEXELS = 128
PAINT_TEXEL_M = 0.01
PAINT_NOISE_SIGMA = 0.012
FLOOR_TEXELS = 256
FLOOR_TEXEL_M = 0.012
FLOOR_CONTRAST = 0.06
FLOOR_BLUR_TEXELS = 1.5
CEILING_NOISE_SIGMA = 0.01

# Photographs of skimage.data that ship with the wheel (no pooch download needed).
PHOTO_NAMES = (
    "astronaut", "coffee", "chelsea", "rocket", "coins", "camera", "page", "brick", "grass",
    "gravel", "immunohistochemistry", "hubble_deep_field", "motorcycle_left", "retina",
    "colorwheel", "clock", "text", "cell", "moon", "logo",
)

# Free space: (x0, y0, x1, y1) metres. Corridors are 2.2 m wide on centre lines y=0, y=20,
# x=0, x=30, x=60; rooms sit 0.2 m (a wall) away from corridors and open through doors.
CORRIDORS = {
    "corridor_south": (-1.1, -1.1, 61.1, 1.1),
    "corridor_north": (-1.1, 18.9, 61.1, 21.1),
    "corridor_west": (-1.1, -1.1, 1.1, 21.1),
    "corridor_mid": (28.9, -1.1, 31.1, 21.1),
    "corridor_east": (58.9, -1.1, 61.1, 21.1),
    "corridor_wing": (43.9, 21.1, 46.1, 33.0),
}
ROOMS = {
    "room_1": (1.3, 1.3, 9.0, 8.5),
    "room_2": (9.2, 1.3, 18.0, 8.5),
    "room_3": (18.2, 11.5, 28.7, 18.7),
    "room_4": (1.3, 11.5, 12.0, 18.7),
    "room_5": (51.0, 1.3, 58.7, 9.0),
    "room_6": (8.0, -9.0, 18.0, -1.3),
    "room_7": (36.0, -9.0, 46.0, -1.3),
    "room_8": (4.0, 21.3, 14.0, 29.0),
    "room_9": (20.0, 21.3, 30.0, 29.0),
}
OPEN_AREAS = {
    "lobby": (-15.0, 4.0, -1.4, 16.0),
    "lab": (31.3, 4.0, 50.0, 16.0),
    "atrium": (36.0, 33.0, 56.0, 45.0),
}
DOORS = {
    "door_1": (4.5, 1.1, 5.5, 1.3),
    "door_2": (13.5, 1.1, 14.5, 1.3),
    "door_3": (22.5, 18.7, 23.5, 18.9),
    "door_4w": (1.1, 14.5, 1.3, 15.5),
    "door_4n": (7.5, 18.7, 8.5, 18.9),
    "door_5": (58.7, 4.5, 58.9, 5.5),
    "door_6": (12.5, -1.3, 13.5, -1.1),
    "door_7": (40.5, -1.3, 41.5, -1.1),
    "door_8": (8.5, 21.1, 9.5, 21.3),
    "door_9": (24.5, 21.1, 25.5, 21.3),
    "lobby_opening": (-1.4, 8.0, -1.1, 12.0),
    "lab_west": (31.1, 9.5, 31.3, 10.5),
    "lab_north": (39.5, 16.0, 40.5, 18.9),
}
PILLAR_SIZE_M = 0.6
PILLARS_XY = ((40, 37), (46, 37), (52, 37), (40, 41), (46, 41), (52, 41))

# Waypoint graph (centre lines, door passages, room centres), metres.
NODES = {
    # corridor intersections
    "SW": (0, 0), "SM": (30, 0), "SE": (60, 0), "NW": (0, 20), "NM": (30, 20), "NE": (60, 20),
    "N45": (45, 20),
    # doors: corridor side -> inside -> room centre
    "c1": (5, 0), "i1": (5, 2.6), "r1": (5, 5.5),
    "c2": (14, 0), "i2": (14, 2.6), "r2": (13.6, 5.5),
    "c3": (23, 20), "i3": (23, 17.4), "r3": (23.4, 14.5),
    "c4w": (0, 15), "i4w": (2.6, 15), "r4": (7.2, 15), "i4n": (8, 17.4), "c4n": (8, 20),
    "c5": (60, 5), "i5": (57.4, 5), "r5": (54.8, 5),
    "c6": (13, 0), "i6": (13, -2.6), "r6": (13, -5.5),
    "c7": (41, 0), "i7": (41, -2.6), "r7": (41, -5.5),
    "c8": (9, 20), "i8": (9, 22.6), "r8": (9, 25.5),
    "c9": (25, 20), "i9": (25, 22.6), "r9": (25, 25.5),
    # lobby
    "cL": (0, 10), "iL": (-2.8, 10), "L_c": (-8, 10), "L_s": (-8, 6.3), "L_w": (-12.5, 10),
    "L_n": (-8, 13.7),
    # lab
    "cA": (30, 10), "iA": (32.8, 10), "A_c": (40, 10), "A_n": (40, 14.0), "cAn": (40, 20),
    "A_e": (47, 10), "A_s": (40, 6.2),
    # north wing and atrium (pillar rows at y=37/41, columns x=40/46/52)
    "W1": (45, 27), "W2": (45, 32.0), "T_s": (45, 35), "T_sw": (38, 35), "T_se": (54.2, 35),
    "T_w": (38, 39), "T_e": (54.2, 39), "T_nw": (38, 43), "T_ne": (54.2, 43), "T_m": (43, 39),
    "T_m2": (49, 39),
}
# Corridor centre lines: the nodes on each line are chained in order.
_LINES = (("y", 0.0), ("y", 20.0), ("x", 0.0), ("x", 30.0), ("x", 60.0))
_EXTRA_EDGES = (
    ("c1", "i1"), ("i1", "r1"), ("c2", "i2"), ("i2", "r2"), ("c3", "i3"), ("i3", "r3"),
    ("c4w", "i4w"), ("i4w", "r4"), ("r4", "i4n"), ("i4n", "c4n"),
    ("c5", "i5"), ("i5", "r5"), ("c6", "i6"), ("i6", "r6"), ("c7", "i7"), ("i7", "r7"),
    ("c8", "i8"), ("i8", "r8"), ("c9", "i9"), ("i9", "r9"),
    ("cL", "iL"), ("iL", "L_c"), ("L_c", "L_s"), ("L_c", "L_w"), ("L_c", "L_n"), ("L_s", "L_w"),
    ("L_w", "L_n"),
    ("cA", "iA"), ("iA", "A_c"), ("A_c", "A_n"), ("A_n", "cAn"), ("A_c", "A_e"), ("A_c", "A_s"),
    ("A_s", "A_e"), ("A_e", "A_n"),
    ("N45", "W1"), ("W1", "W2"), ("W2", "T_s"), ("T_s", "T_sw"), ("T_s", "T_se"),
    ("T_sw", "T_w"), ("T_w", "T_nw"), ("T_se", "T_e"), ("T_e", "T_ne"), ("T_nw", "T_ne"),
    ("T_w", "T_m"), ("T_m", "T_m2"), ("T_m2", "T_e"),
)


@dataclass
class World:
    """The building: wall segments with textures, plus the robot's waypoint graph.

    Attributes:
        p0, p1: (N,2) float64 wall segment end points (m, world frame), free space on the right.
        kind: (N,) int8 texture kind (POSTER, REPEATED, PLAIN).
        texture_id: (N,) int32 poster atlas index, -1 for plain walls.
        poster_rect: (N,4) float64 poster extent on the wall (u0, u1, v0, v1) in metres along the
            segment from ``p0`` and in height above the floor; NaN for plain walls.
        paint_rgb: (N,3) float32 paint colour (0..255).
        atlas: list of ATLAS_LEVELS arrays (K, H_l, W_l, 3) uint8, the posters' mip levels.
        paint_noise: (T,T) float32 tiled multiplicative paint noise (texel PAINT_TEXEL_M).
        floor_tex, ceiling_tex: (T,T,3) float32 tiled textures (0..255).
        free: (rows, cols) bool occupancy of the 0.1 m grid (row = y, col = x), True = free.
        nodes: name -> (x, y) waypoints; edges: list of (name, name).
        seed: the seed the textures were drawn with.
    """

    p0: np.ndarray
    p1: np.ndarray
    kind: np.ndarray
    texture_id: np.ndarray
    poster_rect: np.ndarray
    paint_rgb: np.ndarray
    atlas: list[np.ndarray]
    paint_noise: np.ndarray
    floor_tex: np.ndarray
    ceiling_tex: np.ndarray
    free: np.ndarray
    nodes: dict[str, tuple[float, float]] = field(default_factory=dict)
    edges: list[tuple[str, str]] = field(default_factory=list)
    seed: int = 0

    @property
    def n_walls(self) -> int:
        return len(self.p0)

    @property
    def lengths(self) -> np.ndarray:
        """(N,) wall segment lengths (m)."""
        return np.linalg.norm(self.p1 - self.p0, axis=1)

    def distance_to_walls(self, points_xy: np.ndarray) -> np.ndarray:
        """(M,) distance (m) of world points (M,2) to the nearest wall segment."""
        p = np.asarray(points_xy, dtype=np.float64)[:, None, :]
        e = (self.p1 - self.p0)[None]
        t = np.clip(((p - self.p0[None]) * e).sum(-1) / (e * e).sum(-1), 0.0, 1.0)
        closest = self.p0[None] + t[..., None] * e
        return np.linalg.norm(p - closest, axis=-1).min(axis=1)

    def is_free(self, points_xy: np.ndarray) -> np.ndarray:
        """(M,) True where world points (M,2) fall in free space."""
        ij = _to_cells(np.asarray(points_xy, dtype=np.float64))
        inside = (ij[:, 0] >= 0) & (ij[:, 0] < self.free.shape[0]) & (ij[:, 1] >= 0) & (ij[:, 1] < self.free.shape[1])
        out = np.zeros(len(ij), dtype=bool)
        out[inside] = self.free[ij[inside, 0], ij[inside, 1]]
        return out


def _to_cells(points_xy: np.ndarray) -> np.ndarray:
    """(M,2) int grid cells (row, col) of world points (M,2)."""
    col = np.floor((points_xy[:, 0] - GRID_ORIGIN_XY[0]) / GRID_RESOLUTION_M).astype(int)
    row = np.floor((points_xy[:, 1] - GRID_ORIGIN_XY[1]) / GRID_RESOLUTION_M).astype(int)
    return np.stack([row, col], axis=1)


def free_space_grid() -> np.ndarray:
    """The building's free space as a (rows, cols) bool grid (row = y, col = x, 0.1 m cells)."""
    cols = int(round(GRID_SIZE_XY_M[0] / GRID_RESOLUTION_M))
    rows = int(round(GRID_SIZE_XY_M[1] / GRID_RESOLUTION_M))
    free = np.zeros((rows, cols), dtype=bool)

    def cells(x0: float, y0: float, x1: float, y1: float) -> tuple[slice, slice]:
        c0, c1 = (int(round((v - GRID_ORIGIN_XY[0]) / GRID_RESOLUTION_M)) for v in (x0, x1))
        r0, r1 = (int(round((v - GRID_ORIGIN_XY[1]) / GRID_RESOLUTION_M)) for v in (y0, y1))
        return slice(r0, r1), slice(c0, c1)

    for rect in (*CORRIDORS.values(), *ROOMS.values(), *OPEN_AREAS.values(), *DOORS.values()):
        free[cells(*rect)] = True
    half = PILLAR_SIZE_M / 2
    for x, y in PILLARS_XY:
        free[cells(x - half, y - half, x + half, y + half)] = False
    return free


def _runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """Runs [start, end) of True in a 1D bool array."""
    d = np.diff(np.concatenate([[0], mask.astype(np.int8), [0]]))
    return list(zip(np.flatnonzero(d == 1), np.flatnonzero(d == -1)))


def extract_walls(free: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Boundary segments of the free space, free on the right of ``p0 -> p1``: (N,2), (N,2) m."""
    res = GRID_RESOLUTION_M
    ox, oy = GRID_ORIGIN_XY
    p0, p1 = [], []
    padded = np.pad(free, 1)  # outside the grid is occupied
    # Vertical edges at x = ox + (c-1)*res between padded columns c-1 and c.
    for c in range(1, padded.shape[1]):
        west, east = padded[:, c - 1], padded[:, c]
        x = ox + (c - 1) * res
        for r0, r1 in _runs(west & ~east):  # free on the west: run south
            p0.append((x, oy + (r1 - 1) * res)); p1.append((x, oy + (r0 - 1) * res))
        for r0, r1 in _runs(east & ~west):  # free on the east: run north
            p0.append((x, oy + (r0 - 1) * res)); p1.append((x, oy + (r1 - 1) * res))
    # Horizontal edges at y = oy + (r-1)*res between padded rows r-1 (south) and r (north).
    for r in range(1, padded.shape[0]):
        south, north = padded[r - 1], padded[r]
        y = oy + (r - 1) * res
        for c0, c1 in _runs(south & ~north):  # free on the south: run east
            p0.append((ox + (c0 - 1) * res, y)); p1.append((ox + (c1 - 1) * res, y))
        for c0, c1 in _runs(north & ~south):  # free on the north: run west
            p0.append((ox + (c1 - 1) * res, y)); p1.append((ox + (c0 - 1) * res, y))
    return np.round(np.asarray(p0, dtype=np.float64), 6), np.round(np.asarray(p1, dtype=np.float64), 6)


def split_walls(p0: np.ndarray, p1: np.ndarray, max_length: float = MAX_SEGMENT_LENGTH_M) -> tuple[np.ndarray, np.ndarray]:
    """Split segments (N,2)->(N,2) longer than ``max_length`` (m) into equal pieces."""
    out0, out1 = [], []
    for a, b in zip(p0, p1):
        n = max(1, int(np.ceil(np.linalg.norm(b - a) / max_length - 1e-9)))
        t = np.linspace(0.0, 1.0, n + 1)[:, None]
        pts = a + t * (b - a)
        out0.extend(pts[:-1]); out1.extend(pts[1:])
    return np.asarray(out0), np.asarray(out1)


@lru_cache(maxsize=1)
def load_photos() -> tuple[np.ndarray, ...]:
    """The scikit-image photographs of :data:`PHOTO_NAMES` as HxWx3 uint8 RGB (offline only, cached)."""
    import skimage.data as data

    photos = []
    for name in PHOTO_NAMES:
        if name == "motorcycle_left":
            img = data.stereo_motorcycle()[0]
        else:
            img = getattr(data, name)()
        img = np.asarray(img)
        if img.ndim == 2:
            img = np.repeat(img[..., None], 3, axis=2)
        photos.append(np.ascontiguousarray(img[..., :3]).astype(np.uint8))
    return tuple(photos)


def _make_poster(photo: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """A distinct ATLAS_SHAPE crop of a photograph: random window, flip, colour gain, gamma."""
    h_out, w_out = ATLAS_SHAPE
    aspect = w_out / h_out
    h, w = photo.shape[:2]
    scale = rng.uniform(POSTER_CROP_SCALE[0], POSTER_CROP_SCALE[1])
    ch = max(16, int(min(h, w / aspect) * scale))
    cw = int(ch * aspect)
    y0 = int(rng.integers(0, h - ch + 1))
    x0 = int(rng.integers(0, w - cw + 1))
    crop = cv2.resize(photo[y0:y0 + ch, x0:x0 + cw], (w_out, h_out), interpolation=cv2.INTER_AREA)
    if rng.random() < 0.5:
        crop = crop[:, ::-1]
    # A colour cast and a gamma per poster, applied through one lookup table per channel.
    gain = rng.uniform(0.75, 1.2, size=3)
    gamma = rng.uniform(0.8, 1.25)
    levels = np.arange(256, dtype=np.float32)
    out = np.empty_like(crop)
    for c in range(3):
        lut = 255.0 * (np.clip(levels * gain[c], 0, 255) / 255.0) ** gamma
        out[..., c] = lut.astype(np.uint8)[crop[..., c]]
    return out


def _tiled_noise(rng: np.random.Generator, size: int, sigma: float, blur: float) -> np.ndarray:
    """(size,size) float32 smooth periodic noise with std ``sigma`` (tiles without seams)."""
    n = rng.standard_normal((size, size)).astype(np.float32)
    n = ndimage.gaussian_filter(n, blur, mode="wrap")
    return (n / max(float(n.std()), 1e-9) * sigma).astype(np.float32)


def build_world(seed: int = 0) -> World:
    """The building with its textures drawn from ``seed`` (deterministic; ~0.5 s)."""
    rng = np.random.default_rng([seed, 0x5EED])
    free = free_space_grid()
    p0, p1 = split_walls(*extract_walls(free))
    n = len(p0)
    lengths = np.linalg.norm(p1 - p0, axis=1)

    # Texture kinds: long walls get a unique poster, a repeated one or plain paint.
    draw = rng.random(n)
    kind = np.full(n, PLAIN, dtype=np.int8)
    long_enough = lengths >= MIN_POSTER_WALL_M
    kind[long_enough & (draw < P_POSTER)] = POSTER
    kind[long_enough & (draw >= P_POSTER) & (draw < P_POSTER + P_REPEATED)] = REPEATED

    photos = load_photos()
    n_unique = int((kind == POSTER).sum())
    order = rng.permutation(len(photos))
    posters = [_make_poster(photos[order[i % len(photos)]], rng) for i in range(N_REPEATED_POSTERS + n_unique)]
    texture_id = np.full(n, -1, dtype=np.int32)
    texture_id[kind == POSTER] = N_REPEATED_POSTERS + np.arange(n_unique)
    repeated = np.flatnonzero(kind == REPEATED)
    texture_id[repeated] = np.arange(len(repeated)) % N_REPEATED_POSTERS  # spread in wall order: far apart
    atlas = [np.stack(posters)]
    for _ in range(1, ATLAS_LEVELS):
        atlas.append(np.stack([cv2.pyrDown(img) for img in atlas[-1]]))

    poster_rect = np.full((n, 4), np.nan)
    has_poster = kind != PLAIN
    width = lengths * rng.uniform(*POSTER_WIDTH_FRACTION, size=n)
    u0 = (lengths - width) * rng.uniform(0.2, 0.8, size=n)
    poster_rect[has_poster] = np.stack([
        u0, u0 + width, rng.uniform(*POSTER_BOTTOM_RANGE_M, size=n), rng.uniform(*POSTER_TOP_RANGE_M, size=n)],
        axis=1)[has_poster]

    # Pastel paints: a few colours shared by many walls (plain walls look alike).
    palette = np.array([[222, 216, 200], [200, 210, 222], [228, 222, 186], [210, 222, 205],
                        [235, 235, 232], [222, 200, 196]], dtype=np.float32)
    paint_rgb = palette[rng.integers(0, len(palette), size=n)]

    paint_noise = _tiled_noise(rng, PAINT_NOISE_TEXELS, PAINT_NOISE_SIGMA, 1.5)
    gravel = photos[PHOTO_NAMES.index("gravel")][..., 0].astype(np.float32)
    gravel = cv2.resize(gravel, (FLOOR_TEXELS, FLOOR_TEXELS), interpolation=cv2.INTER_AREA)
    gravel = cv2.GaussianBlur(gravel, (0, 0), FLOOR_BLUR_TEXELS)
    gravel = (gravel - gravel.mean()) / max(float(gravel.std()), 1e-9)
    floor_tex = np.array([150, 140, 125], dtype=np.float32) * (1.0 + FLOOR_CONTRAST * np.clip(gravel, -2.5, 2.5))[..., None]
    ceiling = 1.0 + _tiled_noise(rng, FLOOR_TEXELS, CEILING_NOISE_SIGMA, 2.0)
    ceiling_tex = np.array([238, 238, 235], dtype=np.float32) * ceiling[..., None]

    edges = []
    for axis, value in _LINES:
        a, b = (1, 0) if axis == "y" else (0, 1)
        on_line = sorted((name for name, xy in NODES.items() if abs(xy[a] - value) < 1e-9), key=lambda k: NODES[k][b])
        edges.extend(zip(on_line[:-1], on_line[1:]))
    edges.extend(_EXTRA_EDGES)
    logger.debug("world: %d walls (%d poster, %d repeated, %d plain)", n, (kind == POSTER).sum(),
                 (kind == REPEATED).sum(), (kind == PLAIN).sum())
    return World(p0=p0, p1=p1, kind=kind, texture_id=texture_id, poster_rect=poster_rect,
                 paint_rgb=paint_rgb, atlas=atlas, paint_noise=paint_noise,
                 floor_tex=np.clip(floor_tex, 0, 255).astype(np.float32),
                 ceiling_tex=np.clip(ceiling_tex, 0, 255).astype(np.float32), free=free,
                 nodes={k: (float(v[0]), float(v[1])) for k, v in NODES.items()}, edges=edges, seed=seed)
