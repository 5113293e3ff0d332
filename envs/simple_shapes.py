"""Simple Shapes: one 2D shape on a 32x32 black image, to be moved to the centre and turned upright.

Paper, section "Environments / Simple Shapes". Where the paper is silent this follows the group's public
dataset generator (ruflab/simple-shapes-dataset) for the drawing and their RL environment
(leopoldmt/RL_Simple_Shapes) for actions, attribute encoding, reward and termination.

State of one environment: class c in {0 diamond, 1 egg, 2 triangle}, integer position (x, y) (y axis
pointing up, pixel units), integer size s in [7, 14], rotation theta in [0, 2pi), RGB colour.

Observation ``{"image": uint8 (32, 32, 3), "attr": float32 (11,)}`` with
``attr = [one_hot(c) (3), x/32*2-1, y/32*2-1, (s-7)/14*2-1, cos theta, sin theta, r/255*2-1, g/255*2-1,
b/255*2-1]``.

Actions (``Discrete(7)``): 0 no-op, 1 x+1, 2 y+1 (up), 3 x-1, 4 y-1, 5 theta+pi/32, 6 theta-pi/32.
Reward after each step: ``-||(x, y) - (16, 16)|| - rotation_reward_coef * angle(theta, upright)`` with the
angle in [0, pi]. The episode terminates when (x, y) == (16, 16) and the angle is below pi/32, and is
truncated after ``max_episode_steps`` (100) steps. Positions are not clamped: a shape pushed past the
border leaves the frame (the image shows the part still inside, or stays black) while ``attr`` keeps
reporting the true position.

Rendering is our own numpy code: exact area coverage of the outline in every pixel (what Agg, the
matplotlib back-end of the dataset, computes), colour times coverage on black. ``SimpleShapesVectorEnv``
steps and renders N environments at once; ``SimpleShapesEnv`` is the same machinery with N = 1.
"""

from __future__ import annotations

import functools
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces
from gymnasium.vector import AutoresetMode

IMAGE_SIZE = 32
N_CLASSES = 3
CLASS_NAMES = ("diamond", "egg", "triangle")
SIZE_MIN, SIZE_MAX = 7, 14  # integer sizes, both ends included
MARGIN = SIZE_MAX // 2  # initial positions are integers in [7, 25)
LIGHTNESS_MIN = 46  # OpenCV HLS ranges: H 0-180, L 46-255, S 0-255
TARGET = np.array([16.0, 16.0])
ROTATION_STEP = np.pi / 32
N_ACTIONS = 7
ATTR_DIM = 11
# (dx, dy, dtheta) of each action, as in the group's RL environment.
ACTION_DELTAS = np.array(
    [
        [0.0, 0.0, 0.0],
        [1.0, 0.0, 0.0],
        [0.0, 1.0, 0.0],
        [-1.0, 0.0, 0.0],
        [0.0, -1.0, 0.0],
        [0.0, 0.0, ROTATION_STEP],
        [0.0, 0.0, -ROTATION_STEP],
    ]
)


# --------------------------------------------------------------------------------------------------
# Outlines, in a unit square whose centre (0.5, 0.5) is the shape's position (dataset generator facts).
# --------------------------------------------------------------------------------------------------
def _flatten_cubics(points: np.ndarray, pieces: int) -> np.ndarray:
    """Closed path of cubic Bezier segments (start, then 3 points per segment) -> polygon vertices."""
    t = np.arange(1, pieces + 1)[:, None] / pieces
    out = []
    for k in range(0, len(points) - 1, 3):
        p0, p1, p2, p3 = points[k : k + 4]
        out.append((1 - t) ** 3 * p0 + 3 * (1 - t) ** 2 * t * p1 + 3 * (1 - t) * t**2 * p2 + t**3 * p3)
    return np.concatenate(out)  # the last vertex equals the start: the polygon closes on itself


_DIAMOND = np.array([[0.5, 0.0], [1.0, 0.3], [0.5, 1.0], [0.0, 0.3]])
_TRIANGLE = np.array([[0.5, 1.0], [0.2, 0.0], [0.8, 0.0]])  # isosceles, apex up at theta = 0
_EGG_BEZIER = np.array(
    [
        [0.5, 0.0],
        [0.8, 0.0],
        [0.9, 0.1],
        [0.9, 0.3],
        [0.9, 0.5],
        [0.7, 1.0],
        [0.5, 1.0],
        [0.3, 1.0],
        [0.1, 0.5],
        [0.1, 0.3],
        [0.1, 0.1],
        [0.2, 0.0],
        [0.5, 0.0],
    ]
)
# 12 chords per cubic keep the flattened egg within 1e-3 pixel of the curve at size 14.
OUTLINES = (_DIAMOND, _flatten_cubics(_EGG_BEZIER, 12), _TRIANGLE)
# Largest distance of any outline point from the centre, in units of size (triangle base corners).
_RADIUS = max(float(np.max(np.hypot(*(o - 0.5).T))) for o in OUTLINES)


def shape_polygon(cls: int, x, y, size, rotation) -> np.ndarray:
    """Outline vertices in pixel coordinates (y up): origin + size * R(theta) (p - 0.5).

    Scalars give (K, 2); arrays of n shapes of the same class give (n, K, 2)."""
    x, y, size, rotation = (np.asarray(v, dtype=np.float64)[..., None] for v in (x, y, size, rotation))
    c, s = np.cos(rotation), np.sin(rotation)
    p = OUTLINES[int(cls)] - 0.5
    return np.stack([x + size * (c * p[:, 0] - s * p[:, 1]), y + size * (s * p[:, 0] + c * p[:, 1])], -1)


# --------------------------------------------------------------------------------------------------
# Rasteriser: exact area of the polygon inside every pixel.
# --------------------------------------------------------------------------------------------------
def _expand(start: np.ndarray, count: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For items with integer ranges [start, start + count): (parent index, value) of every element."""
    parent = np.repeat(np.arange(len(count)), count)
    offset = np.arange(len(parent)) - np.repeat(np.cumsum(count) - count, count)
    return parent, start[parent] + offset


def coverage(polygons: np.ndarray, width: int) -> np.ndarray:
    """Fraction of each pixel of a ``width`` x ``width`` window covered by each polygon.

    ``polygons`` (n, K, 2) holds closed simple polygons in window pixel units (y up; pixel (j, i)
    is the square [i, i+1] x [j, j+1]). By Green's theorem the area of a polygon inside column strip
    [c, c+1] of a row strip equals the boundary integral of clip(x - c, 0, 1) dy, so each edge, cut at
    pixel borders, adds dy * (mean x - c) to the pixel it crosses and dy to every pixel on its left;
    a right-to-left cumulative sum collects the latter. Returns (n, width, width) float64, rows y-up.
    """
    n, k, _ = polygons.shape
    nxt = np.roll(polygons, -1, axis=1)
    x0, y0 = polygons[..., 0].ravel(), polygons[..., 1].ravel()
    x1, y1 = nxt[..., 0].ravel(), nxt[..., 1].ravel()
    img = np.repeat(np.arange(n), k)
    keep = y0 != y1  # horizontal edges add nothing
    x0, y0, x1, y1, img = x0[keep], y0[keep], x1[keep], y1[keep], img[keep]
    slope = (x1 - x0) / (y1 - y0)
    ylo, yhi = np.minimum(y0, y1), np.maximum(y0, y1)
    sign = np.sign(y1 - y0)

    # Cut edges at row borders.
    r0 = np.floor(ylo).astype(np.int64)
    e, row = _expand(r0, np.ceil(yhi).astype(np.int64) - r0)
    ya, yb = np.maximum(ylo[e], row), np.minimum(yhi[e], row + 1)
    xa, xb = x0[e] + (ya - y0[e]) * slope[e], x0[e] + (yb - y0[e]) * slope[e]
    dy = (yb - ya) * sign[e]
    img = img[e]

    # Cut the row pieces at column borders.
    xlo, xhi = np.minimum(xa, xb), np.maximum(xa, xb)
    c0 = np.floor(xlo).astype(np.int64)
    p, col = _expand(c0, np.maximum(np.ceil(xhi).astype(np.int64) - c0, 1))
    lo, hi = np.maximum(xlo[p], col), np.minimum(xhi[p], col + 1)
    span = (xhi - xlo)[p]
    dys = dy[p] * np.where(span > 0, (hi - lo) / np.where(span > 0, span, 1.0), 1.0)
    inside = 0.5 * (lo + hi) - col  # mean x within the pixel, in [0, 1]

    # Accumulate: columns shifted by one so that column -1 (everything left of the window, never shown)
    # is bin 0, and everything right of the window piles into the last bin.
    stride = width + 2
    base = (img[p] * width + row[p]) * stride
    index = np.concatenate([base + np.clip(col + 1, 0, stride - 1), base + np.clip(col, 0, stride - 1)])
    acc = np.bincount(
        index, weights=np.concatenate([dys * inside, dys * (1.0 - inside)]), minlength=n * width * stride
    ).reshape(n, width, stride)
    cover = np.cumsum(acc[:, :, ::-1], axis=2)[:, :, ::-1][:, :, 1 : width + 1]
    return np.minimum(np.abs(cover), 1.0)


def _colourise(alpha: np.ndarray, rgb: np.ndarray) -> np.ndarray:
    """round(alpha * rgb / 255) as uint8 (colour over black with 8-bit coverage, as Agg blends) for
    alpha (n, h, w) and rgb (n, 3). Float32 is exact here: a product never lands within 1/510 of a
    rounding tie (checked for all 256 x 256 pairs in the tests)."""
    af = alpha.astype(np.float32) * np.float32(1 / 255)
    out = np.empty(alpha.shape + (3,), dtype=np.uint8)
    for ch in range(3):  # one contiguous pass per channel is much faster than broadcasting over 3
        out[..., ch] = af * rgb[:, ch, None, None].astype(np.float32) + np.float32(0.5)
    return out


def hls_to_rgb(hls: np.ndarray) -> np.ndarray:
    """OpenCV's 8-bit HLS -> RGB (H in [0, 180], L and S in [0, 255]), rounded to uint8."""
    hls = np.asarray(hls, dtype=np.float64)
    h = (hls[..., 0] * 2.0 / 60.0) % 6.0
    lum, sat = hls[..., 1] / 255.0, hls[..., 2] / 255.0
    p2 = np.where(lum <= 0.5, lum * (1 + sat), lum + sat - lum * sat)
    p1 = 2 * lum - p2
    sector = np.floor(h).astype(np.int64)
    frac = h - sector
    tab = np.stack([p2, p1, p1 + (p2 - p1) * (1 - frac), p1 + (p2 - p1) * frac], -1)
    # For each sector, which entry of tab gives (r, g, b).
    order = np.array([[0, 3, 1], [2, 0, 1], [1, 0, 3], [1, 2, 0], [3, 1, 0], [0, 1, 2]])
    rgb = np.take_along_axis(tab, order[sector], axis=-1)
    rgb = np.where((sat == 0)[..., None], lum[..., None], rgb)
    return np.clip(np.round(rgb * 255.0), 0, 255).astype(np.uint8)


class ShapeCanvas:
    """Per-environment picture of the shape, so that moving it is a crop rather than a redraw.

    The coverage window of each shape (drawn centred on its integer position, times its colour) sits in
    the middle of a zero canvas padded by one image width on every side; the 32x32 observation is the
    crop at the shape's current position. Only a rotation, a new episode or a new shape redraws.
    """

    def __init__(self, n: int, max_size: float = SIZE_MAX):
        self.window = 2 * int(np.ceil(_RADIUS * max_size)) + 4
        self.side = self.window + 2 * IMAGE_SIZE
        self.pixels = np.zeros((n, self.side, self.side, 3), dtype=np.uint8)
        # All 32x32 crops of each canvas as one strided view, so a batch of crops is one indexing.
        st = self.pixels.strides
        self._crops = np.lib.stride_tricks.as_strided(
            self.pixels,
            shape=(n, self.side - IMAGE_SIZE + 1, self.side - IMAGE_SIZE + 1, IMAGE_SIZE, IMAGE_SIZE, 3),
            strides=(st[0], st[1], st[2], st[1], st[2], st[3]),
            writeable=False,
        )

    def draw(self, idx, cls, x, y, size, rotation, rgb) -> None:
        """Redraw the shapes of environments ``idx``."""
        idx = np.asarray(idx)
        if idx.size == 0:
            return
        w = self.window
        x, y = np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64)
        ax, ay = np.floor(x).astype(np.int64) - w // 2, np.floor(y).astype(np.int64) - w // 2
        cover = np.empty((idx.size, w, w))
        cls = np.asarray(cls)
        for c in np.unique(cls):
            sel = np.flatnonzero(cls == c)
            polys = shape_polygon(c, x[sel] - ax[sel], y[sel] - ay[sel], size[sel], rotation[sel])
            cover[sel] = coverage(polys, w)
        alpha = np.round(cover[:, ::-1, :] * 255.0).astype(np.uint8)  # image rows go top-down
        o = IMAGE_SIZE
        self.pixels[idx, o : o + w, o : o + w] = _colourise(alpha, np.asarray(rgb))

    def images(self, x, y, idx: np.ndarray | slice = slice(None)) -> np.ndarray:
        """(n, 32, 32, 3) uint8 frames of environments ``idx`` whose shapes are now at (x, y): the
        drawing moved by the whole pixels the shape travelled since it was drawn."""
        w = self.window
        x, y = np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64)
        # The window corner follows the shape; clipped where the window is wholly outside the frame
        # (the crop then falls on the canvas's zero padding).
        ax = np.clip(np.floor(x).astype(np.int64) - w // 2, -w, IMAGE_SIZE)
        ay = np.clip(np.floor(y).astype(np.int64) - w // 2, -w, IMAGE_SIZE)
        env = np.arange(self.pixels.shape[0])[idx]
        return self._crops[env, ay + w, IMAGE_SIZE - ax]


def render_shapes(cls, x, y, size, rotation, rgb, chunk: int = 4096) -> np.ndarray:
    """Images (n, 32, 32, 3) uint8 of n shapes; positions and sizes may be fractional."""
    cls, x, y = np.atleast_1d(cls).astype(np.int64), np.atleast_1d(x), np.atleast_1d(y)
    size, rotation = np.atleast_1d(size).astype(np.float64), np.atleast_1d(rotation)
    rgb = np.atleast_2d(rgb)
    if np.any((cls < 0) | (cls >= N_CLASSES)):
        raise ValueError(f"shape class must be 0 (diamond), 1 (egg) or 2 (triangle), got {cls}")
    out = np.empty((len(cls), IMAGE_SIZE, IMAGE_SIZE, 3), dtype=np.uint8)
    for a in range(0, len(cls), chunk):
        sl = slice(a, a + chunk)
        canvas = ShapeCanvas(len(cls[sl]), max_size=max(SIZE_MAX, float(size[sl].max())))
        canvas.draw(np.arange(len(cls[sl])), cls[sl], x[sl], y[sl], size[sl], rotation[sl], rgb[sl])
        out[sl] = canvas.images(x[sl], y[sl])
    return out


def draw_shape(cls: int, x: float, y: float, size: float, rotation: float, rgb) -> np.ndarray:
    """One 32x32x3 uint8 image: x, y, size in pixels (y up), rotation in radians, rgb in 0-255."""
    return render_shapes([cls], [x], [y], [size], [rotation], np.asarray(rgb).reshape(1, 3))[0]


# --------------------------------------------------------------------------------------------------
# States, attribute vectors, reward.
# --------------------------------------------------------------------------------------------------
def sample_states(rng: np.random.Generator, n: int) -> dict[str, np.ndarray]:
    """n random initial states, as the dataset draws them (uniform class, size, position, angle, HLS)."""
    cls = rng.integers(0, N_CLASSES, n)
    pos = rng.integers(MARGIN, IMAGE_SIZE - MARGIN, (n, 2)).astype(np.float64)
    size = rng.integers(SIZE_MIN, SIZE_MAX + 1, n)
    rotation = rng.random(n) * 2 * np.pi
    hls = rng.integers([0, LIGHTNESS_MIN, 0], [181, 256, 256], (n, 3))
    return {"cls": cls, "pos": pos, "size": size, "rotation": rotation, "rgb": hls_to_rgb(hls)}


def state_to_attr(cls, pos, size, rotation, rgb) -> np.ndarray:
    """Normalised 11-float attribute vectors (n, 11), the encoding of the group's RL environment."""
    cls, size, rotation = np.atleast_1d(cls), np.atleast_1d(size), np.atleast_1d(rotation)
    pos, rgb = np.atleast_2d(pos), np.atleast_2d(rgb)
    return np.concatenate(
        [
            np.eye(N_CLASSES)[cls],
            pos / IMAGE_SIZE * 2 - 1,
            ((size - SIZE_MIN) / 14 * 2 - 1)[:, None],
            np.cos(rotation)[:, None],
            np.sin(rotation)[:, None],
            rgb / 255.0 * 2 - 1,
        ],
        axis=1,
    ).astype(np.float32)


def attr_to_state(attr: np.ndarray) -> dict[str, np.ndarray]:
    """Inverse of :func:`state_to_attr` for (n, 11) vectors, e.g. decoded by a VAE (values are clipped
    to the valid range; the class is the arg-max of the first three entries)."""
    a = np.clip(np.atleast_2d(np.asarray(attr, dtype=np.float64)), -1.0, 1.0)
    if a.shape[1] != ATTR_DIM:
        raise ValueError(f"attribute vectors must have {ATTR_DIM} entries, got shape {a.shape}")
    return {
        "cls": np.argmax(a[:, :3], axis=1),
        "pos": (a[:, 3:5] + 1) / 2 * IMAGE_SIZE,
        "size": (a[:, 5] + 1) / 2 * 14 + SIZE_MIN,
        "rotation": np.arctan2(a[:, 7], a[:, 6]) % (2 * np.pi),
        "rgb": np.round((a[:, 8:11] + 1) / 2 * 255).astype(np.uint8),
    }


def draw_from_attr(attr: np.ndarray) -> np.ndarray:
    """Images (n, 32, 32, 3) (or one image for a single vector) from normalised attribute vectors."""
    s = attr_to_state(attr)
    out = render_shapes(s["cls"], s["pos"][:, 0], s["pos"][:, 1], s["size"], s["rotation"], s["rgb"])
    return out[0] if np.ndim(attr) == 1 else out


def angle_to_upright(rotation: np.ndarray) -> np.ndarray:
    """Smallest angle in [0, pi] between theta and 0: arccos(cos theta), computed without arccos's
    loss of precision near 0."""
    r = np.mod(rotation, 2 * np.pi)
    return np.minimum(r, 2 * np.pi - r)


def reward_and_goal(pos, rotation, rotation_reward_coef: float = 10.0):
    """Reward -||pos - (16, 16)|| - coef * angle, and whether the goal state is reached."""
    pos = np.atleast_2d(pos)
    dist = np.hypot(pos[:, 0] - TARGET[0], pos[:, 1] - TARGET[1])
    angle = angle_to_upright(np.atleast_1d(rotation))
    goal = (pos[:, 0] == TARGET[0]) & (pos[:, 1] == TARGET[1]) & (angle < ROTATION_STEP)
    return -dist - rotation_reward_coef * angle, goal


def greedy_action(pos, rotation, rotation_reward_coef: float = 10.0) -> np.ndarray:
    """Scripted greedy policy: the action whose next state has the highest reward (defines return 1
    of the normalised return). It never stalls: a move toward the target always helps when the angle
    cannot improve, and the angle test of the goal is met within pi/64 of upright."""
    pos, rotation = np.atleast_2d(pos), np.atleast_1d(rotation)
    nxt_pos = pos[:, None, :] + ACTION_DELTAS[None, :, :2]
    nxt_rot = rotation[:, None] + ACTION_DELTAS[None, :, 2]
    r, _ = reward_and_goal(nxt_pos.reshape(-1, 2), nxt_rot.reshape(-1), rotation_reward_coef)
    return np.argmax(r.reshape(-1, N_ACTIONS), axis=1)


def _check_actions(actions, n: int) -> np.ndarray:
    a = np.asarray(actions)
    if a.shape != (n,) or not (np.issubdtype(a.dtype, np.integer) or a.dtype == bool):
        if a.shape == (n,) and np.issubdtype(a.dtype, np.floating) and np.all(a == np.round(a)):
            a = a.astype(np.int64)
        else:
            raise ValueError(
                f"actions must be {n} integer(s) in [0, {N_ACTIONS}), got {actions!r} "
                f"(shape {a.shape}, dtype {a.dtype})"
            )
    if np.any((a < 0) | (a >= N_ACTIONS)):
        raise ValueError(
            f"actions must be integers in [0, {N_ACTIONS}) (0 no-op, 1 x+1, 2 y+1, 3 x-1, 4 y-1, "
            f"5 rotate +pi/32, 6 rotate -pi/32), got {actions!r}"
        )
    return a.astype(np.int64)


def _spaces(max_episode_steps: int) -> tuple[spaces.Dict, spaces.Discrete]:
    # Positions drift at most one pixel per step from [7, 24], so these bounds hold for any episode.
    reach = np.array([MARGIN - max_episode_steps, IMAGE_SIZE - MARGIN - 1 + max_episode_steps])
    p_lo, p_hi = reach / IMAGE_SIZE * 2 - 1
    low = np.array([0, 0, 0, p_lo, p_lo, -1, -1, -1, -1, -1, -1], dtype=np.float32)
    high = np.array([1, 1, 1, p_hi, p_hi, 0, 1, 1, 1, 1, 1], dtype=np.float32)
    obs = spaces.Dict(
        {
            "image": spaces.Box(0, 255, (IMAGE_SIZE, IMAGE_SIZE, 3), dtype=np.uint8),
            "attr": spaces.Box(low, high, dtype=np.float32),
        }
    )
    return obs, spaces.Discrete(N_ACTIONS)


class _ShapesCore:
    """State arrays and dynamics of n environments (shared by the single and the vector env)."""

    def __init__(self, n: int, rotation_reward_coef: float, max_episode_steps: int):
        if max_episode_steps < 1:
            raise ValueError(f"max_episode_steps must be >= 1, got {max_episode_steps}")
        self.n, self.coef, self.max_steps = n, float(rotation_reward_coef), int(max_episode_steps)
        self.cls = np.zeros(n, dtype=np.int64)
        self.pos = np.zeros((n, 2))
        self.size = np.zeros(n, dtype=np.int64)
        self.rotation = np.zeros(n)
        self.rgb = np.zeros((n, 3), dtype=np.uint8)
        self.steps = np.zeros(n, dtype=np.int64)
        self.goal = np.zeros(n, dtype=bool)  # goal test of the current state, kept for info()
        self.canvas = ShapeCanvas(n)

    def set_states(self, idx: np.ndarray, st: dict[str, np.ndarray]) -> None:
        self.cls[idx], self.pos[idx], self.size[idx] = st["cls"], st["pos"], st["size"]
        self.rotation[idx], self.rgb[idx], self.steps[idx] = st["rotation"], st["rgb"], 0
        self.goal[idx] = reward_and_goal(self.pos[idx], self.rotation[idx], self.coef)[1]
        self._redraw(idx)

    def reset(self, idx: np.ndarray, rngs: list[np.random.Generator], options: dict | None) -> None:
        if options and "state" in options:
            self.set_states(idx, _validate_state(options["state"], len(idx)))
            return
        states = [sample_states(rngs[i], 1) for i in idx.tolist()]
        self.set_states(idx, {k: np.concatenate([s[k] for s in states]) for k in states[0]})

    def _redraw(self, idx: np.ndarray) -> None:
        x, y = self.pos[idx, 0], self.pos[idx, 1]
        self.canvas.draw(idx, self.cls[idx], x, y, self.size[idx], self.rotation[idx], self.rgb[idx])

    def step(self, actions: np.ndarray):
        d = ACTION_DELTAS[actions]
        self.pos += d[:, :2]
        # theta kept modulo 2pi, as in the reference environment.
        self.rotation = np.mod(self.rotation + d[:, 2], 2 * np.pi)
        self._redraw(np.flatnonzero(d[:, 2] != 0))
        self.steps += 1
        reward, terminated = reward_and_goal(self.pos, self.rotation, self.coef)
        self.goal = terminated.copy()  # an autoreset rewrites self.goal; the returned flags must stay
        truncated = (self.steps >= self.max_steps) & ~terminated
        return reward, terminated, truncated

    def obs(self, idx: np.ndarray | slice = slice(None)) -> dict[str, np.ndarray]:
        pos = self.pos[idx]
        return {
            "image": self.canvas.images(pos[:, 0], pos[:, 1], idx),
            "attr": state_to_attr(self.cls[idx], pos, self.size[idx], self.rotation[idx], self.rgb[idx]),
        }

    def info(self) -> dict[str, np.ndarray]:
        return {
            "distance": np.hypot(*(self.pos - TARGET).T),
            "angle": angle_to_upright(self.rotation),
            "is_success": self.goal.copy(),
        }


def _whole(name: str, value, n: int, low: int, high: int) -> np.ndarray:
    """``value`` broadcast to n whole numbers in [low, high], or a ValueError naming ``name``."""
    v = np.broadcast_to(np.asarray(value, dtype=np.float64), (n,))
    if not np.all(np.isfinite(v)) or np.any(v != np.round(v)) or np.any((v < low) | (v > high)):
        raise ValueError(f"{name} must be whole numbers in [{low}, {high}], got {value}")
    return v.astype(np.int64)


STATE_KEYS = {"cls", "x", "y", "size", "rotation", "rgb"}


def _validate_state(state: dict[str, Any], n: int) -> dict[str, np.ndarray]:
    """A user-given state (keys cls, x, y, size, rotation, rgb) as arrays for n environments. It must lie
    where the environment itself starts episodes (whole pixels in [7, 24], so that an episode of
    max_episode_steps stays inside the observation space), with a finite rotation."""
    missing, unknown = sorted(STATE_KEYS - set(state)), sorted(set(state) - STATE_KEYS)
    if missing:
        raise ValueError(f"options['state'] lacks {missing}; give cls, x, y, size, rotation, rgb")
    if unknown:
        raise ValueError(f"options['state'] has unknown keys {unknown}; give cls, x, y, size, rotation, rgb")
    cls = _whole("cls (0 diamond, 1 egg, 2 triangle)", state["cls"], n, 0, N_CLASSES - 1)
    x = _whole("x (pixels)", state["x"], n, MARGIN, IMAGE_SIZE - MARGIN - 1)
    y = _whole("y (pixels)", state["y"], n, MARGIN, IMAGE_SIZE - MARGIN - 1)
    size = _whole("size", state["size"], n, SIZE_MIN, SIZE_MAX)
    rotation = np.broadcast_to(np.asarray(state["rotation"], dtype=np.float64), (n,))
    if not np.all(np.isfinite(rotation)):
        raise ValueError(f"rotation must be a finite angle in radians, got {state['rotation']}")
    rgb = np.broadcast_to(np.asarray(state["rgb"], dtype=np.float64), (n, 3))
    if not np.all(np.isfinite(rgb)) or np.any(rgb != np.round(rgb)) or np.any((rgb < 0) | (rgb > 255)):
        raise ValueError(f"rgb must be three whole numbers in [0, 255], got {state['rgb']}")
    return {
        "cls": cls,
        "pos": np.stack([x, y], 1).astype(np.float64),
        "size": size,
        "rotation": np.mod(rotation, 2 * np.pi),
        "rgb": rgb.astype(np.uint8),
    }


def _upscale(image: np.ndarray, factor: int = 8) -> np.ndarray:
    return np.repeat(np.repeat(image, factor, axis=-3), factor, axis=-2)


class SimpleShapesEnv(gym.Env):
    """One Simple Shapes environment (see the module docstring). ``reset(options={"state": {...}})``
    starts from a given state with keys cls, x, y, size, rotation, rgb."""

    metadata = {"render_modes": ["rgb_array"], "render_fps": 10}

    def __init__(
        self, render_mode: str | None = None, rotation_reward_coef: float = 10.0, max_episode_steps: int = 100
    ):
        if render_mode not in (None, "rgb_array"):
            raise ValueError(f"render_mode must be None or 'rgb_array', got {render_mode!r}")
        self.render_mode = render_mode
        self.observation_space, self.action_space = _spaces(max_episode_steps)
        self._core = _ShapesCore(1, rotation_reward_coef, max_episode_steps)
        self._obs: dict[str, np.ndarray] | None = None
        self._ended = False  # stepping past the end is an error (gymnasium leaves it undefined)

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        self._core.reset(np.array([0]), [self.np_random], options)
        self._ended = False
        return self._observe(), self._info()

    def step(self, action):
        if self._obs is None:
            raise RuntimeError("call reset() before step()")
        if self._ended:
            raise RuntimeError("the episode has ended (terminated or truncated): call reset() before step()")
        a = _check_actions(np.reshape(action, (1,)) if np.ndim(action) == 0 else action, 1)
        reward, terminated, truncated = self._core.step(a)
        self._ended = bool(terminated[0] or truncated[0])
        return self._observe(), float(reward[0]), bool(terminated[0]), bool(truncated[0]), self._info()

    def render(self):
        if self.render_mode == "rgb_array":
            if self._obs is None:
                raise RuntimeError("call reset() before render()")
            return _upscale(self._obs["image"])
        return None

    @property
    def state(self) -> dict[str, Any]:
        c = self._core
        return {
            "cls": int(c.cls[0]),
            "x": float(c.pos[0, 0]),
            "y": float(c.pos[0, 1]),
            "size": int(c.size[0]),
            "rotation": float(c.rotation[0]),
            "rgb": c.rgb[0].copy(),
        }

    def _observe(self):
        obs = self._core.obs()
        self._obs = {k: v[0] for k, v in obs.items()}
        return self._obs

    def _info(self):
        return {k: v[0].item() for k, v in self._core.info().items()}


class SimpleShapesVectorEnv(gym.vector.VectorEnv):
    """N Simple Shapes environments stepped and rendered together in numpy.

    Environment i with seed s behaves exactly like ``SimpleShapesEnv`` reset with seed s + i (a list of
    seeds may be given instead). Finished environments reset in the same step (``autoreset_mode`` SAME_STEP):
    the returned observation starts the new episode and ``info["final_obs"]`` holds the last observation
    of every environment, valid where ``info["_final_obs"]`` is True. The other ``info`` entries
    (distance, angle, is_success) describe the state the step reached, before any reset.
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": 10, "autoreset_mode": AutoresetMode.SAME_STEP}

    def __init__(
        self,
        num_envs: int = 1,
        render_mode: str | None = None,
        rotation_reward_coef: float = 10.0,
        max_episode_steps: int = 100,
    ):
        if num_envs < 1:
            raise ValueError(f"num_envs must be >= 1, got {num_envs}")
        if render_mode not in (None, "rgb_array"):
            raise ValueError(f"render_mode must be None or 'rgb_array', got {render_mode!r}")
        self.num_envs, self.render_mode = num_envs, render_mode
        self.single_observation_space, self.single_action_space = _spaces(max_episode_steps)
        self.observation_space = gym.vector.utils.batch_space(self.single_observation_space, num_envs)
        self.action_space = gym.vector.utils.batch_space(self.single_action_space, num_envs)
        self._core = _ShapesCore(num_envs, rotation_reward_coef, max_episode_steps)
        self.np_randoms = [np.random.default_rng() for _ in range(num_envs)]
        self._obs: dict[str, np.ndarray] | None = None

    def reset(self, *, seed: int | list[int] | None = None, options: dict | None = None):
        if seed is not None:
            seeds = [seed + i for i in range(self.num_envs)] if isinstance(seed, int) else list(seed)
            if len(seeds) != self.num_envs:
                raise ValueError(f"got {len(seeds)} seeds for {self.num_envs} environments")
            # gymnasium's seeding: Generator(PCG64(SeedSequence(s))), the same as Env.reset(seed=s).
            self.np_randoms = [np.random.default_rng(s) for s in seeds]
        self._core.reset(np.arange(self.num_envs), self.np_randoms, options)
        self._obs = self._core.obs()
        return self._obs, self._core.info()

    def step(self, actions):
        if self._obs is None:
            raise RuntimeError("call reset() before step()")
        reward, terminated, truncated = self._core.step(_check_actions(actions, self.num_envs))
        info = self._core.info()
        obs = self._core.obs()
        done = np.flatnonzero(terminated | truncated)
        if done.size:
            info["final_obs"] = obs
            info["_final_obs"] = terminated | truncated
            self._core.reset(done, self.np_randoms, None)
            obs = {k: v.copy() for k, v in obs.items()}
            fresh = self._core.obs(done)  # only the environments that restarted
            for k in obs:
                obs[k][done] = fresh[k]
        self._obs = obs
        return obs, reward, terminated, truncated, info

    def render(self):
        if self.render_mode == "rgb_array" and self._obs is not None:
            return _upscale(self._obs["image"])
        return None


# Positions the wider share of ``sample_dataset`` draws from: up to 16 px past each border, where the
# largest shape (reaching 0.6 x 14 px from its centre) has wholly left the frame.
WIDE_POSITIONS = (-16, IMAGE_SIZE + 16)


def sample_dataset(n: int, seed: int = 0, wide_share: float = 0.0) -> dict[str, np.ndarray]:
    """n paired observations of random states (the paper's 500,000-sample pre-training data):
    ``{"image": (n, 32, 32, 3) uint8, "attr": (n, 11) float32, "wide": (n,) bool}``.

    ``wide_share`` of the samples (drawn at random) take their position uniformly from
    ``WIDE_POSITIONS`` instead of the initial-state range [7, 25): states at and past the border, which
    an agent reaches by pushing the shape out but which the dataset's draw never shows."""
    if not 0.0 <= wide_share <= 1.0:
        raise ValueError(f"wide_share must be in [0, 1], got {wide_share}")
    rng = np.random.default_rng(seed)
    st = sample_states(rng, n)
    wide = rng.random(n) < wide_share  # drawn after the states: a share of 0 keeps the dataset's draw
    st["pos"][wide] = rng.integers(*WIDE_POSITIONS, (int(wide.sum()), 2))
    images = render_shapes(st["cls"], st["pos"][:, 0], st["pos"][:, 1], st["size"], st["rotation"], st["rgb"])
    attr = state_to_attr(st["cls"], st["pos"], st["size"], st["rotation"], st["rgb"])
    return {"image": images, "attr": attr, "wide": wide}


@functools.lru_cache
def reference_returns(episodes: int = 1_000, seed: int = 10_000) -> tuple[float, float]:
    """Mean returns of a uniformly random policy and of ``greedy_action`` over ``episodes`` episodes:
    the 0 and the 1 of the normalised return every agent script logs (docs/paper_readings.md). Measured
    once per process (a few seconds: every episode renders its images)."""
    out = []
    for policy in ("random", "greedy"):
        env = SimpleShapesVectorEnv(episodes)
        env.reset(seed=seed)
        rng = np.random.default_rng(seed)
        total, alive = np.zeros(episodes), np.ones(episodes, bool)
        while alive.any():
            if policy == "random":
                a = rng.integers(0, N_ACTIONS, episodes)
            else:
                a = greedy_action(env._core.pos, env._core.rotation)
            _, r, term, trunc, _ = env.step(a)
            total += r * alive
            alive &= ~(term | trunc)
        out.append(float(total.mean()))
    return out[0], out[1]
