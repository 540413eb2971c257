"""bench/reaim.py: the rotation about a held-out camera's centre that lines a render up with its photo."""
import cv2
import numpy as np
import pytest

from bench.reaim import degrees_turned, fit_rotation

H, W = 120, 160
K = np.array([[150.0, 0, 83.0], [0, 150.0, 57.0], [0, 0, 1]])


def _render() -> tuple[np.ndarray, np.ndarray]:
    """A textured disc on black (a render and its coverage)."""
    rng = np.random.default_rng(0)
    noise = cv2.GaussianBlur(rng.random((H, W, 3)), (0, 0), 3.0)
    img = (noise - noise.min()) / (noise.max() - noise.min())
    jj, ii = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
    hit = (jj - 80) ** 2 + (ii - 60) ** 2 < 40 ** 2
    return img * hit[..., None], hit


def _turned(a: np.ndarray, Rd: np.ndarray) -> np.ndarray:
    """What a camera turned by Rd about its centre sees, by OpenCV (pixel centres at integers there, at +0.5 here)."""
    S = np.array([[1, 0, 0.5], [0, 1, 0.5], [0, 0, 1]])
    Hm = np.linalg.inv(S) @ K @ Rd @ np.linalg.inv(K) @ S
    return cv2.warpPerspective(a.astype(np.float64), Hm, (W, H), flags=cv2.INTER_LINEAR)


def _rot(axis, deg) -> np.ndarray:
    return cv2.Rodrigues(np.radians(deg) * np.asarray(axis, float) / np.linalg.norm(axis))[0]


def _angle(Ra, Rb) -> float:
    """Degrees between two rotations."""
    return degrees_turned(Ra.T @ Rb)


@pytest.mark.parametrize("axis,deg", [((0, 1, 0), 0.4), ((1, 0.5, 0), -0.3), ((0.2, -1, 0.3), 0.8)])
def test_recovers_a_known_turn(axis, deg):
    img, hit = _render()
    Rd = _rot(axis, deg)
    photo, mask = _turned(img, Rd), _turned(hit.astype(float), Rd) > 0.5
    fit = fit_rotation(img, hit, photo, mask, K)
    assert _angle(fit, Rd) < 0.02 * abs(deg) + 0.005  # against a turn of 0.3–0.8° (≈ 1–2 px)
    assert _angle(fit, np.eye(3)) > 0.5 * abs(deg)


def test_a_render_that_already_lines_up_is_not_turned():
    img, hit = _render()
    fit = fit_rotation(img, hit, img, hit, K)
    assert _angle(fit, np.eye(3)) < 1e-3


def test_shapes_are_checked():
    img, hit = _render()
    with pytest.raises(ValueError, match="fit_rotation"):
        fit_rotation(img, hit, img[:-1], hit, K)


def textured_ball(seed: int = 1):
    """A unit ball (trimesh, UVs on its visual) with a smooth random texture on spherical UVs, and that texture."""
    import trimesh

    ball = trimesh.creation.icosphere(subdivisions=4)
    x, y, z = ball.vertices.T
    uv = np.stack([np.arctan2(y, x) / (2 * np.pi) + 0.5, np.arccos(np.clip(z, -1, 1)) / np.pi], -1)
    tex = cv2.GaussianBlur(np.random.default_rng(seed).random((128, 128, 3)), (0, 0), 2.0)
    visual = trimesh.visual.TextureVisuals(uv=uv)
    return trimesh.Trimesh(ball.vertices, ball.faces, visual=visual, process=False), \
        (tex - tex.min()) / (tex.max() - tex.min())


def _textured_ball():
    """:func:`textured_ball` ready to be ray-cast (TexturedCaster)."""
    from pipeline.render.textured import TexturedCaster

    tm, tex = textured_ball()
    return TexturedCaster(tm.vertices, tm.faces, tm.visual.uv, tex)


def test_reaim_turns_a_render_onto_a_photo_taken_from_a_turned_camera():
    from bench.evaluate import image_psnr
    from bench.reaim import reaim

    caster = _textured_ball()
    R, centre = np.eye(3), np.array([0.0, 0.0, -4.0])
    Rd_true = _rot((0.3, 1, -0.2), 0.35)  # ≈ 0.9 px at this focal length
    photo, mask = caster.render(K, Rd_true @ R, centre, W, H)
    img0, hit0 = caster.render(K, R, centre, W, H)
    Rd, img, hit = reaim(caster, K, R, centre, photo, mask)
    # the viewing direction to the compass search's last step (0.06 px ≈ 0.023°); a roll about a ball in the image
    # centre moves its picture by hundredths of a pixel, so the roll is only as good as that
    look, look_true = Rd.T @ [0, 0, 1], Rd_true.T @ [0, 0, 1]
    assert np.degrees(np.arccos(np.clip(look @ look_true, -1, 1))) < 0.025
    before, after = image_psnr(img0, hit0, photo, mask), image_psnr(img, hit, photo, mask)
    assert after > 35 and after > before + 10, (before, after)


def test_reaim_leaves_a_camera_that_already_sees_the_photo_unturned():
    from bench.reaim import reaim

    caster = _textured_ball()
    R, centre = np.eye(3), np.array([0.0, 0.0, -4.0])
    photo, mask = caster.render(K, R, centre, W, H)
    Rd, img, hit = reaim(caster, K, R, centre, photo, mask)
    assert np.array_equal(Rd, np.eye(3)) and np.array_equal(hit, mask) and np.allclose(img, photo)
