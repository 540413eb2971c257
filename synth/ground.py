"""The ``ground`` effect: the plane the object rests on or hangs from.

The plane is a floor (``normal`` +z of the canonical frame, the default) or any other plane at the object's far
side, a wall it hangs on (``normal`` [1, 0, 0]: the wall at the object's smallest x): it lies at the object's
extreme point along −``normal`` plus ``sink`` (the object sinks that far into it, so it touches everywhere it
rests), runs beyond every frame (an infinite plane: rays that reach it never see the backdrop), and hides whatever
of the object lies behind it. Its albedo is a procedural pattern of the plane coordinates (on a wall: along it
horizontally, and up it) (``wood`` planks, ``tiles`` with grout, ``checker``, quantised ``noise``). With
lighting on it is shaded by the scene's lights with a soft shadow: each light is an area light sampled by a fixed
set of directions (the same in every view, so the shadow is part of the floor, as a real one is), and the ambient
term is darkened near the object (a contact shadow, ``shadow`` strength, ``softness`` radius). With ``board``
a printed ChArUco board on white paper lies on it under the object (the scene's metric scale: ``metres_per_unit``).
"""

from __future__ import annotations

import functools

import cv2
import numpy as np

from pipeline.scene.support import plane_basis
from synth.scene import Effect

PATTERNS = ("wood", "tiles", "checker", "noise")
LIGHT_RADIUS = 0.06
"""Angular radius (rad) of the area light behind each directional light: the penumbra of the shadows."""
LIGHT_SAMPLES = 6
"""Directions per light for the soft shadow (fixed, so every view sees the same shadow)."""


UP = (0.0, 0.0, 1.0)


def plane_normal(e: Effect) -> np.ndarray:
    """The unit normal (3,) of a ground effect's plane, towards the object."""
    n = np.asarray(e.normal, float)
    if n.shape != (3,) or not np.isfinite(n).all() or np.linalg.norm(n) < 1e-9:
        raise ValueError(f"ground normal must be 3 finite numbers, not all 0, got {e.normal}")
    return n / np.linalg.norm(n)


def plane_hits(origins: np.ndarray, dirs: np.ndarray, z0: float,
               normal: np.ndarray | tuple = UP) -> tuple[np.ndarray, np.ndarray]:
    """Rays (M, 3) that reach the plane x·normal = z0 from its front (the side ``normal`` points to), and their depth
    (inf where they do not)."""
    h_o = origins[:, 2] if tuple(normal) == UP else origins @ normal
    rate = dirs[:, 2] if tuple(normal) == UP else dirs @ normal
    down = (rate < -1e-12) & (h_o > z0)
    t = np.full(len(origins), np.inf)
    t[down] = (z0 - h_o[down]) / rate[down]
    return down, t


def plane_coords(points: np.ndarray, normal: np.ndarray | tuple = UP) -> np.ndarray:
    """Coordinates (M, 2) of points on the plane of unit ``normal``: (x, y) on a floor; elsewhere along the plane
    horizontally, then up it (a wall's pattern stands upright)."""
    if tuple(normal) == UP:
        return points[:, :2]
    n = np.asarray(normal, float)
    e1 = np.cross(UP, n)
    if np.linalg.norm(e1) < 1e-6:  # a ceiling: any frame on it
        e1, e2 = plane_basis(n)
    else:
        e1 /= np.linalg.norm(e1)
        e2 = np.cross(n, e1)
    return np.stack([points @ e1, points @ e2], 1)


def _hash(ij: np.ndarray, seed: int, k: int = 0) -> np.ndarray:
    """Deterministic pseudo-random values in [0, 1) per integer cell (M, 2)."""
    v = np.sin(ij[:, 0] * 12.9898 + ij[:, 1] * 78.233 + seed * 37.719 + k * 4.581) * 43758.5453
    return v - np.floor(v)


def _wood(xy: np.ndarray, e: Effect, c1: np.ndarray, c2: np.ndarray) -> np.ndarray:
    """Planks along x (1/scale wide, 4/scale long, staggered joints), grain streaks, dark seams."""
    w = 1.0 / e.scale
    row = np.floor(xy[:, 1] / w)
    off = _hash(np.stack([row, row], 1), e.seed, 1) * 4 * w
    col = np.floor((xy[:, 0] + off) / (4 * w))
    cell = np.stack([row, col], 1)
    v = xy[:, 1] / w - row  # across the plank, [0, 1)
    u = (xy[:, 0] + off) / (4 * w) - col  # along it
    phase = _hash(cell, e.seed, 2) * 6.28
    wobble = 0.08 * np.sin(6.28 * (1.3 * u + phase)) + 0.03 * np.sin(6.28 * (5.1 * u + 2 * phase))
    grain = 0.5 + 0.5 * np.sin(6.28 * (7.0 + 5 * _hash(cell, e.seed, 3)) * (v + wobble))
    tone = 0.8 + 0.4 * _hash(cell, e.seed, 4)
    # fibres: noise stretched along the plank, and a knot here and there
    from synth.noise import procedural_noise

    fibre = procedural_noise(np.stack([xy[:, 0] * 0.25, xy[:, 1] * 3.0, row], 1), 6.0 * e.scale, e.seed, 0)[:, 0]
    knot_c = np.stack([_hash(cell, e.seed, 5), _hash(cell, e.seed, 6)], 1)
    knot = np.hypot((u - 0.15 - 0.7 * knot_c[:, 0]) * 4, (v - 0.25 - 0.5 * knot_c[:, 1]) * 1.0)
    knot = (knot < 0.12) & (_hash(cell, e.seed, 7) < 0.5)
    out = (c1 + (c2 - c1) * grain[:, None] ** 2) * (tone * (0.7 + 0.6 * fibre))[:, None]
    out[knot] *= 0.45
    seam = (np.minimum(v, 1 - v) < 0.04) | (np.minimum(u, 1 - u) * 4 < 0.03)
    out[seam] *= 0.35
    return out


def _tiles(xy: np.ndarray, e: Effect, c1: np.ndarray, c2: np.ndarray) -> np.ndarray:
    """Square tiles (1/scale) of random tints between the two colours, light grout between them."""
    ij = np.floor(xy * e.scale)
    f = xy * e.scale - ij
    t = _hash(ij, e.seed)
    out = c1 + (c2 - c1) * t[:, None]
    out = out * (0.85 + 0.3 * _hash(ij, e.seed, 1))[:, None]
    grout = np.minimum(f, 1 - f).min(1) < 0.05
    out[grout] = 0.85
    return out


def ground_albedo(xy: np.ndarray, e: Effect) -> np.ndarray:
    """Albedo (M, 3) in [0, 1] of the ground at plane coordinates (M, 2)."""
    c1, c2 = np.asarray(e.color, float), np.asarray(e.color2, float)
    if e.pattern == "wood":
        out = _wood(xy, e, c1, c2)
    elif e.pattern == "tiles":
        out = _tiles(xy, e, c1, c2)
    elif e.pattern == "checker":
        k = (np.floor(xy[:, 0] * e.scale) + np.floor(xy[:, 1] * e.scale)).astype(int) % 2
        out = np.where(k[:, None] == 0, c1, c2)
    elif e.pattern == "noise":  # blocky stone-like tones between the two colours, a little colour variation
        from synth.noise import procedural_noise

        n = procedural_noise(np.concatenate([xy, np.zeros((len(xy), 1))], 1), e.scale, e.seed, 4)
        out = c1 + (c2 - c1) * (0.8 * n[:, :1] + 0.2 * n)
    else:
        raise ValueError(f"unknown ground pattern '{e.pattern}' ({', '.join(PATTERNS)})")
    if e.board:
        out = _with_board(xy, e, out)
    return np.clip(out, 0.0, 1.0)


PAPER, INK = 0.9, 0.05
"""Albedo of the board's white paper and of its black print."""
BOARD_MARGIN_M = 0.015
"""White paper around the printed board (m)."""
BOARD_PX = 64
"""Texture pixels per board square (bilinear sampling; a square spans ≈ 65 photo pixels in the board scenes)."""


@functools.lru_cache(maxsize=4)
def _board_texture(squares: tuple[int, int], square_mm: float, marker_mm: float, dictionary: str) -> np.ndarray:
    from pipeline.cameras.board import board_spec, board_texture

    spec = board_spec(squares, square_mm, marker_mm, dictionary, "scene ground effect")
    return board_texture(spec, BOARD_PX).astype(np.float32) / 255.0


def board_spec_of(e: Effect):
    """The :class:`pipeline.cameras.board.BoardSpec` of a ground effect's board."""
    from pipeline.cameras.board import board_spec

    return board_spec(e.board, e.board_square_mm, e.board_marker_mm, e.board_dictionary, "scene ground effect")


def _with_board(xy: np.ndarray, e: Effect, out: np.ndarray) -> np.ndarray:
    """``out`` with the printed board (and its paper) where it lies: centred at the origin of the plane, its rows
    along x, the top of the print towards +y (x_board = x, y_board = −y in metres, board frame y down)."""
    spec = board_spec_of(e)
    w, h = spec.size_m
    m = xy * e.metres_per_unit
    bx, by = m[:, 0] + w / 2, h / 2 - m[:, 1]
    paper = (bx > -BOARD_MARGIN_M) & (bx < w + BOARD_MARGIN_M) & (by > -BOARD_MARGIN_M) & (by < h + BOARD_MARGIN_M)
    tex = _board_texture(tuple(spec.squares), e.board_square_mm, e.board_marker_mm, e.board_dictionary)
    u = (bx[paper] / spec.square_m * BOARD_PX - 0.5).astype(np.float32)
    v = (by[paper] / spec.square_m * BOARD_PX - 0.5).astype(np.float32)
    val = np.concatenate([cv2.remap(tex, u[s:s + 32000][None], v[s:s + 32000][None], cv2.INTER_LINEAR,
                                    borderMode=cv2.BORDER_CONSTANT, borderValue=1.0)[0]
                          for s in range(0, len(u), 32000)]) if len(u) else np.zeros(0, np.float32)
    out = out.copy()
    out[paper] = (INK + (PAPER - INK) * val.astype(float))[:, None]
    return out


def light_directions(direction: np.ndarray, n: int = LIGHT_SAMPLES, radius: float = LIGHT_RADIUS) -> np.ndarray:
    """``n`` fixed unit directions spread over a cone of half-angle ``radius`` around ``direction``
    (a Fibonacci spiral over the disc), (n, 3)."""
    a = direction / np.linalg.norm(direction)
    b1, b2 = plane_basis(a)
    k = np.arange(n) + 0.5
    r = radius * np.sqrt(k / n)
    phi = k * 2.39996323  # golden angle
    out = a[None] + r[:, None] * (np.cos(phi)[:, None] * b1 + np.sin(phi)[:, None] * b2)
    return out / np.linalg.norm(out, axis=1, keepdims=True)


def ground_shading(points: np.ndarray, lights: list[list[float]], ambient: float, e: Effect, occluded,
                   distance) -> np.ndarray:
    """Shading factor (M,) of ground points under directional ``lights`` ([dx, dy, dz, intensity]), the plane's
    normal that of ``e``.

    ``occluded(origins, dirs)`` → bool (M,): the object blocks the ray; ``distance(points)`` → (M,) distance to the
    object. Ambient × contact shadow + Σ intensity · cos · (fraction of the area light the object leaves visible).
    """
    contact = 1.0 - e.shadow * np.exp(-np.maximum(distance(points), 0.0) / max(e.softness, 1e-6))
    shade = ambient * contact
    n = plane_normal(e)
    lifted = points + 1e-4 * n
    for lx, ly, lz, li in lights:
        ldir = np.array([lx, ly, lz], float)
        ldir /= np.linalg.norm(ldir)
        cos = float(ldir @ n)
        if cos <= 0:
            continue  # a light from behind the plane (below the floor) does not light it
        dirs = light_directions(ldir)
        seen = np.zeros(len(points))
        for dv in dirs:
            seen += ~occluded(lifted, np.broadcast_to(dv, points.shape).copy())
        shade = shade + li * cos * seen / len(dirs)
    return shade
