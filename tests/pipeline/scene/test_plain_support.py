"""The plain support (pipeline/scene/plain_support.py): a surface with no SfM points under an object's base, found
from the base's rim and a plane sweep of the photos; never under an object floating before a textured backdrop."""

import numpy as np
import pytest

from pipeline.scene.plain_support import (
    base_direction,
    disagreement,
    find_plain_support,
    ring_colours,
    ring_points,
)

RNG = np.random.default_rng(0)
W, H, FOCAL = 160, 120, 150.0
K = np.array([[FOCAL, 0, W / 2], [0, FOCAL, H / 2], [0, 0, 1.0]])


def _look_at(c, target, up=(0.0, 0.0, 1.0)):
    f = np.asarray(target, float) - c
    f /= np.linalg.norm(f)
    r = np.cross(f, up)
    r /= np.linalg.norm(r)
    return np.stack([r, np.cross(f, r), f])


def _cameras(n=24, radius=3.0, target=(0.0, 0.0, 0.25)):
    """Two rings looking at the object, 25° and 45° up."""
    az = np.linspace(0, 2 * np.pi, n, endpoint=False)
    elev = np.radians(np.where(np.arange(n) % 2, 25.0, 45.0))
    C = np.stack([radius * np.cos(az) * np.cos(elev), radius * np.sin(az) * np.cos(elev),
                  target[2] + radius * np.sin(elev)], 1)
    R = np.stack([_look_at(c, target) for c in C])
    P = np.stack([K @ np.c_[r, -r @ c] for r, c in zip(R, C)])
    return C, R, P


def _texture(x, y, z=0.0):
    """A faint, smooth pattern: the same colour at a point from every view."""
    g = 0.8 + 0.04 * np.sin(7.1 * x + 1.3) * np.cos(5.3 * y) + 0.03 * np.sin(11.7 * y + 3.1 * x + 0.4 * z)
    return np.stack([g, g, 0.97 * g], -1)


def _photos(C, R, on_table: bool):
    """Each view of a textured plane z = 0 (``on_table``) or, for a floating object, of a textured backdrop sphere
    of radius 8 around it (the object itself is never drawn: the sweep reads only beside it)."""
    v, u = np.mgrid[0:H, 0:W] + 0.5
    rays = np.stack([(u - W / 2) / FOCAL, (v - H / 2) / FOCAL, np.ones_like(u)], -1)
    images = []
    for c, r in zip(C, R):
        d = rays @ r  # camera → world: rows of R are the camera axes
        d /= np.linalg.norm(d, axis=-1, keepdims=True)
        if on_table:
            t = -c[2] / np.minimum(d[..., 2], -1e-6)
        else:  # |c + t d| = 8
            b = d @ c
            t = -b + np.sqrt(b * b - (c @ c - 64.0))
        p = c + t[..., None] * d
        colour = _texture(3 * p[..., 0], 3 * p[..., 1], 3 * p[..., 2]) if not on_table else _texture(p[..., 0],
                                                                                                       p[..., 1])
        if not on_table:
            colour = 0.5 + 1.5 * (colour - 0.8)  # a backdrop's stronger pattern
        images.append(colour.astype(np.float32))
    return images


def _puck(n=1500, radius=0.5, low=0.12, high=0.45):
    """SfM points of a low round object standing on z = 0 whose lowest band (below ``low``) gave SIFT nothing: its
    side and top."""
    a = RNG.random(n) * 2 * np.pi
    side = np.stack([radius * np.cos(a), radius * np.sin(a), RNG.uniform(low, high, n)], 1)
    r, b = radius * np.sqrt(RNG.random(n // 2)), RNG.random(n // 2) * 2 * np.pi
    top = np.stack([r * np.cos(b), r * np.sin(b), np.full(n // 2, high)], 1)
    return np.concatenate([side, top]) + RNG.normal(0, 0.003, (n + n // 2, 3))


TARGET = np.array([0.0, 0.0, 0.25])


def test_a_plain_table_under_the_base_is_found_at_its_height():
    C, R, P = _cameras()
    pl = find_plain_support(_puck(), C, R, P, TARGET, _photos(C, R, on_table=True))
    assert pl is not None and pl.kind == "base"
    assert pl.normal @ [0, 0, 1] > np.cos(np.radians(1.0))
    height_of_origin = pl.offset  # n·0 + d: the true table's height above the plane found
    assert abs(height_of_origin) < 0.03, height_of_origin  # the rim's points stood 0.12 above it
    assert pl.object_height == pytest.approx(0.45, abs=0.04)


def test_nothing_under_an_object_floating_before_a_textured_backdrop():
    C, R, P = _cameras()
    assert base_direction(_puck(), C, R, TARGET, 0.01 * 3.0) is not None  # its base alone would make a plane
    assert find_plain_support(_puck(), C, R, P, TARGET, _photos(C, R, on_table=False)) is None


def test_a_round_bottom_or_cameras_below_give_no_base():
    C, R, _ = _cameras()
    u = RNG.normal(size=(1500, 3))
    ball = TARGET + 0.4 * u / np.linalg.norm(u, axis=1, keepdims=True)
    assert base_direction(ball, C, R, TARGET, 0.03) is None  # a tangent plane holds a cap, not a rim all around
    below = C.copy()
    below[::3, 2] = -1.0  # a third of the views from under the table's level
    R_below = np.stack([_look_at(c, TARGET) for c in below])
    assert base_direction(_puck(), below, R_below, TARGET, 0.03) is None


def test_the_ring_lies_around_the_object_on_the_plane():
    obj = _puck()
    foot = np.zeros(3)
    ring = ring_points(obj, np.array([0.0, 0.0, 1.0]), 0.0, foot)
    assert np.allclose(ring[:, 2], 0.0)
    dist = np.hypot(ring[:, 0], ring[:, 1])
    assert dist.min() > 1.0 * 0.5 and dist.max() < 1.45 * 0.51


def test_disagreement_is_zero_where_every_photo_sees_the_same_colour_and_ignores_unseen_points():
    C, R, P = _cameras()
    flat = [np.full((H, W, 3), 0.6, np.float32) for _ in C]
    ring = ring_points(_puck(), np.array([0.0, 0.0, 1.0]), 0.0, np.zeros(3))
    far = np.array([[50.0, 0.0, 0.0]])  # outside every frame
    colours = ring_colours(flat, P, C, np.concatenate([ring, far]), np.array([0.0, 0.0, 1.0]), np.zeros(3))
    score = disagreement(colours)
    assert score == pytest.approx(0.0, abs=1e-6)
    assert np.isnan(colours[:, -1]).all()
    assert np.isfinite(score)
