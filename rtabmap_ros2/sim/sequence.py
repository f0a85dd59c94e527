"""A long revisiting image sequence for the 2013 paper's experiments (appearance only).

A camera slides along an endless mural made of real photographs (scikit-image's data module,
shipped with the package: nothing is downloaded). The mural is procedural: tile ``k`` is a crop
of one photograph chosen, cropped, flipped and tinted from ``(seed, k)``, so any length can be
rendered without holding the mural in memory. Some tiles repeat another tile (perceptual
aliasing) and some are plain paint (bad signatures), as in a real building.

The route alternates *exploration* (new mural) and *revisits* of earlier stretches, with stops
(the camera stays still for a few frames, which raises weights by rehearsal, like the UdeS
experiment's waypoints). Each frame differs from the last by a small random tilt, scale,
vertical offset, brightness change and sensor noise, and revisits are seen with other values.

Ground truth (RTAB-Map's convention): image ``i`` closes a loop with image ``j`` when ``j``
belongs to an earlier segment of the route and their views overlap by more than
:data:`LOOP_OVERLAP` of the image width. :func:`write_sequence` writes ``1.jpg ... N.jpg`` and
``ground_truth.png`` (N x N, pixel (i, j) = 255 when image i+1 closes a loop with image j+1).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import cv2
import numpy as np

WIDTH, HEIGHT = 640, 480
TILE_WIDTH = 320
MARGIN = 48  # px of mural above and below the view, room for the vertical jitter
STEP_PX = 320  # camera advance per frame while moving (50 % overlap between frames, 1 Hz-like)
LOOP_OVERLAP = 0.25  # views sharing more than this part of the width show the same place (a merged location keeps an older view)
ALIASED_TILE_RATIO = 0.05
PLAIN_TILE_RATIO = 0.04
TILE_KEY_OFFSET = 1 << 20  # seeds must be non-negative; views near 0 reach tile -1
PHOTOS = ("astronaut", "coffee", "chelsea", "rocket", "hubble_deep_field", "immunohistochemistry",
          "retina", "camera", "coins", "clock", "horse", "moon", "page", "text", "grass", "gravel",
          "brick", "colorwheel", "logo")


@lru_cache(maxsize=None)
def _photo(name: str) -> np.ndarray:
    """An RGB uint8 photograph from skimage.data."""
    import skimage.data

    image = getattr(skimage.data, name)()
    if image.ndim == 2:
        image = np.repeat(image[:, :, None], 3, axis=2)
    return np.ascontiguousarray(image[:, :, :3]).astype(np.uint8)


def _available_photos() -> tuple[str, ...]:
    out = []
    for name in PHOTOS:
        try:
            _photo(name)
        except Exception:  # noqa: BLE001 - a photo needing a download is simply not used
            continue
        out.append(name)
    return tuple(out)


class Mural:
    """The endless wall of photographs; :meth:`view` renders a camera image."""

    def __init__(self, seed: int = 0) -> None:
        self.seed = seed
        self.photos = _available_photos()
        self._tiles: dict[int, np.ndarray] = {}

    def _tile_recipe(self, k: int) -> tuple[int, int]:
        """(source tile, kind) of tile k: kind 0 photo, 1 plain paint; aliasing copies a tile."""
        rng = np.random.default_rng([self.seed, k + TILE_KEY_OFFSET])
        u = rng.random()
        if k > 8 and u < ALIASED_TILE_RATIO:
            return int(rng.integers(0, k - 4)), 0
        if u > 1.0 - PLAIN_TILE_RATIO:
            return k, 1
        return k, 0

    def tile(self, k: int) -> np.ndarray:
        """Tile k: (HEIGHT + 2 MARGIN) x TILE_WIDTH x 3 uint8."""
        cached = self._tiles.get(k)
        if cached is not None:
            return cached
        source, kind = self._tile_recipe(k)
        h = HEIGHT + 2 * MARGIN
        # The background of an aliased tile repeats another tile's (same wallpaper elsewhere);
        # its notices are its own.
        rng = np.random.default_rng([self.seed, source + TILE_KEY_OFFSET, 7])
        if kind == 1:
            colour = rng.integers(120, 230, 3)
            tile = np.empty((h, TILE_WIDTH, 3), np.uint8)
            tile[:] = colour
            tile = np.clip(tile + rng.normal(0, 2, tile.shape), 0, 255).astype(np.uint8)
        else:
            photo = _photo(self.photos[int(rng.integers(len(self.photos)))])
            ph, pw = photo.shape[:2]
            # A random part of the photo, scaled so that detail stays at a camera-like scale.
            crop_h = int(ph * rng.uniform(0.45, 0.9))
            crop_w = min(max(8, int(crop_h * TILE_WIDTH / h)), pw)
            y0 = int(rng.integers(0, ph - crop_h + 1))
            x0 = int(rng.integers(0, pw - crop_w + 1))
            tile = cv2.resize(photo[y0:y0 + crop_h, x0:x0 + crop_w], (TILE_WIDTH, h),
                              interpolation=cv2.INTER_LINEAR)
            if rng.random() < 0.5:
                tile = tile[:, ::-1]
            tint = rng.uniform(0.75, 1.25, 3)
            tile = np.clip(tile * tint, 0, 255).astype(np.uint8)
            tile = _add_posters(np.ascontiguousarray(tile),
                                np.random.default_rng([self.seed, k + TILE_KEY_OFFSET, 11]))
        tile = np.ascontiguousarray(tile)
        if len(self._tiles) > 256:
            self._tiles.pop(next(iter(self._tiles)))
        self._tiles[k] = tile
        return tile

    def view(self, x: float, jitter: "ViewJitter") -> np.ndarray:
        """The HEIGHT x WIDTH x 3 RGB image seen with its left edge at mural position ``x`` (px)."""
        pad = 64
        left = int(np.floor(x)) - pad
        first, last = left // TILE_WIDTH, (left + WIDTH + 2 * pad) // TILE_WIDTH
        strip = np.concatenate([self.tile(k) for k in range(first, last + 1)], axis=1)
        ox = x - first * TILE_WIDTH
        cx, cy = ox + WIDTH / 2, MARGIN + jitter.dy + HEIGHT / 2
        M = cv2.getRotationMatrix2D((cx, cy), jitter.angle_deg, jitter.scale)
        M[0, 2] += WIDTH / 2 - cx
        M[1, 2] += HEIGHT / 2 - cy
        image = cv2.warpAffine(strip, M, (WIDTH, HEIGHT), flags=cv2.INTER_LINEAR,
                               borderMode=cv2.BORDER_REFLECT)
        rng = np.random.default_rng(jitter.noise_seed)
        noisy = image.astype(np.float32) * jitter.gain + rng.normal(0, 3.0, image.shape)
        return np.clip(noisy, 0, 255).astype(np.uint8)


_FONTS = (cv2.FONT_HERSHEY_SIMPLEX, cv2.FONT_HERSHEY_DUPLEX, cv2.FONT_HERSHEY_COMPLEX,
          cv2.FONT_HERSHEY_TRIPLEX, cv2.FONT_HERSHEY_PLAIN)
_LETTERS = np.array(list("ABCDEFGHJKLMNPQRSTUVWXYZ0123456789"))


def _add_posters(tile: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Paste 1-3 notices (random text and shapes) on a photo tile so no two tiles look alike.

    A crop of one of a few photographs repeats across a long mural; notices drawn from the
    tile's own seed make every place distinctive, as signs and posters do in a building.
    """
    h, w = tile.shape[:2]
    for _ in range(int(rng.integers(1, 4))):
        pw, ph = int(rng.integers(90, 200)), int(rng.integers(70, 160))
        x0, y0 = int(rng.integers(0, max(1, w - pw))), int(rng.integers(0, max(1, h - ph)))
        background = tuple(int(v) for v in rng.integers(150, 256, 3))
        cv2.rectangle(tile, (x0, y0), (x0 + pw, y0 + ph), background, -1)
        for line in range(int(rng.integers(2, 5))):
            text = "".join(rng.choice(_LETTERS, int(rng.integers(3, 8))))
            colour = tuple(int(v) for v in rng.integers(0, 110, 3))
            cv2.putText(tile, text, (x0 + 4, y0 + 22 + 30 * line), _FONTS[int(rng.integers(len(_FONTS)))],
                        float(rng.uniform(0.5, 0.9)), colour, int(rng.integers(1, 3)), cv2.LINE_AA)
        for _ in range(int(rng.integers(1, 4))):
            centre = (int(x0 + rng.integers(0, pw)), int(y0 + rng.integers(0, ph)))
            colour = tuple(int(v) for v in rng.integers(0, 256, 3))
            if rng.random() < 0.5:
                cv2.circle(tile, centre, int(rng.integers(5, 25)), colour, -1)
            else:
                pts = (np.asarray(centre) + rng.integers(-25, 25, (int(rng.integers(3, 6)), 2))).astype(np.int32)
                cv2.fillPoly(tile, [pts], colour)
    return tile


@dataclass(frozen=True)
class ViewJitter:
    """Small camera changes between frames."""

    dy: float
    angle_deg: float
    scale: float
    gain: float
    noise_seed: int


@dataclass
class ImageSequence:
    """A route over the mural: positions (px), segment of every frame, and the jitter."""

    mural: Mural
    x: np.ndarray  # (N,) left edge of every view on the mural, px
    segment: np.ndarray  # (N,) route segment index of every frame
    jitter: list[ViewJitter]

    def __len__(self) -> int:
        return len(self.x)

    def image(self, i: int) -> np.ndarray:
        """RGB image of frame i (0-based)."""
        return self.mural.view(float(self.x[i]), self.jitter[i])

    def ground_truth(self) -> np.ndarray:
        """(N, N) bool: frame i closes a loop with frame j (j in an earlier segment, views overlap)."""
        dx = np.abs(self.x[:, None] - self.x[None, :])
        earlier = self.segment[None, :] < self.segment[:, None]
        return (dx < (1.0 - LOOP_OVERLAP) * WIDTH) & earlier


def make_sequence(n_images: int, seed: int = 0, revisit_ratio: float = 0.35,
                  segment_length: tuple[int, int] = (60, 200)) -> ImageSequence:
    """A route of ``n_images`` frames alternating exploration and revisits.

    Args:
        n_images: frames to generate.
        seed: everything (mural, route, jitter) is deterministic for a seed.
        revisit_ratio: share of the frames spent revisiting already seen stretches.
        segment_length: min and max frames of one route segment.
    """
    rng = np.random.default_rng(seed)
    xs: list[float] = []
    segments: list[int] = []
    frontier = 0.0  # the farthest mural position explored so far
    seg = 0
    while len(xs) < n_images:
        length = int(rng.integers(*segment_length))
        revisit = seg > 0 and frontier > STEP_PX * length and rng.random() < revisit_ratio * 1.5
        if revisit:
            start = float(rng.uniform(0, frontier - STEP_PX * length))
            direction = 1.0
        else:
            start, direction = frontier, 1.0
        x = start
        for _ in range(length):
            xs.append(x)
            segments.append(seg)
            # Stops: the camera stays still for a while now and then (rehearsal raises weights).
            if rng.random() < 0.02:
                for _ in range(int(rng.integers(3, 12))):
                    xs.append(x + rng.normal(0, 2))
                    segments.append(seg)
            x += direction * STEP_PX * rng.uniform(0.8, 1.2)
        if not revisit:
            frontier = x
        seg += 1
    xs, segments = xs[:n_images], segments[:n_images]
    jitter = [ViewJitter(dy=float(rng.uniform(-MARGIN * 0.6, MARGIN * 0.6)), angle_deg=float(rng.normal(0, 1.5)),
                         scale=float(rng.uniform(0.95, 1.05)), gain=float(rng.uniform(0.85, 1.15)),
                         noise_seed=int(rng.integers(1 << 31)))
              for _ in range(len(xs))]
    return ImageSequence(Mural(seed), np.asarray(xs), np.asarray(segments), jitter)


def write_sequence(sequence: ImageSequence, out_dir: str | Path, jpeg_quality: int = 92) -> Path:
    """Write ``1.jpg ... N.jpg`` and ``ground_truth.png`` into ``out_dir``."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    for i in range(len(sequence)):
        bgr = cv2.cvtColor(sequence.image(i), cv2.COLOR_RGB2BGR)
        cv2.imwrite(str(out / f"{i + 1}.jpg"), bgr, [cv2.IMWRITE_JPEG_QUALITY, jpeg_quality])
    cv2.imwrite(str(out / "ground_truth.png"), sequence.ground_truth().astype(np.uint8) * 255)
    return out
