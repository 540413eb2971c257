"""bench/evaluate.py's PSNR of a render against a photo, raw and after fitting the photo's own colour gains."""

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.evaluate import image_psnr  # noqa: E402


def _photo(seed=0):
    rng = np.random.default_rng(seed)
    photo = rng.uniform(0.1, 0.8, (24, 32, 3))
    mask = np.zeros((24, 32), bool)
    mask[4:20, 6:26] = True
    return photo, mask


def test_a_darker_photo_of_the_right_texture_scores_high_only_with_its_gains_fitted():
    photo, mask = _photo()
    gains = np.array([0.7, 0.75, 0.8])
    render = np.where(mask[..., None], photo / gains, 0.0)  # the texture, seen by a view exposed 20-30 % darker
    raw = image_psnr(render, mask, photo, mask)
    fitted = image_psnr(render, mask, photo, mask, gain_fit=True)
    assert raw < 20.0
    assert fitted > 60.0


def test_gain_fitting_does_not_hide_a_wrong_texture_or_a_missing_mesh():
    photo, mask = _photo()
    wrong = np.where(mask[..., None], _photo(seed=1)[0], 0.0)
    assert image_psnr(wrong, mask, photo, mask, gain_fit=True) < 15.0
    hit = mask.copy()
    hit[4:12] = False  # the mesh misses half the object: those pixels stay black
    partial = np.where(hit[..., None], photo, 0.0)
    assert image_psnr(partial, hit, photo, mask, gain_fit=True) == image_psnr(partial, hit, photo, mask)


def test_over_exposed_pixels_neither_fit_the_gains_nor_count_against_a_clipped_render():
    radiance, mask = _photo()
    band = mask & (np.arange(32) < 12)[None, :]
    radiance[band] = 1.6  # brighter than the camera records: the photo clips it at 1
    photo = np.clip(radiance, 0.0, 1.0)
    render = np.where(mask[..., None], radiance * 0.5, 0.0)  # the right texture, half as bright
    assert image_psnr(render, mask, photo, mask, gain_fit=True) > 60.0


def test_reaimed_heldout_figure_turns_each_view_onto_its_photo(tmp_path):
    """bench/evaluate.py reaimed_psnrs: a textured ball's held-out photo taken from a turned camera scores higher
    re-aimed than at the camera given, and the mean turn is the one applied."""
    import cv2

    from bench.evaluate import _read_mask, _read_rgb, reaimed_psnrs, render_psnr
    from pipeline.texture import TexturedCaster
    from tests.test_bench_reaim import H, K, W, _rot, textured_ball

    tm, tex = textured_ball(seed=2)
    centre = np.array([0.0, 0.0, -4.0])
    caster = TexturedCaster(tm.vertices, tm.faces, tm.visual.uv, tex)
    photo, mask = caster.render(K, _rot((1, 0.2, 0), 0.3), centre, W, H)
    cv2.imwrite(str(tmp_path / "p.png"), (np.clip(photo, 0, 1) * 255).round().astype(np.uint8)[..., ::-1])
    cv2.imwrite(str(tmp_path / "m.png"), mask.astype(np.uint8) * 255)
    got = reaimed_psnrs(tm, tex, [(K, np.eye(3), centre, tmp_path / "p.png", tmp_path / "m.png")])
    raw = render_psnr(tm, tex, K, np.eye(3), centre, _read_rgb(tmp_path / "p.png"), _read_mask(tmp_path / "m.png"))
    assert got["psnr_reaimed"] > raw + 10 and abs(got["reaim_deg"] - 0.3) < 0.03
