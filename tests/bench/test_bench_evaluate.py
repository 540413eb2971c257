"""bench/evaluate.py's PSNR of a render against a photo, raw and after fitting the photo's own colour gains."""

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

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
    from pipeline.render.textured import TexturedCaster
    from tests.bench.test_bench_reaim import H, K, W, _rot, textured_ball

    tm, tex = textured_ball(seed=2)
    centre = np.array([0.0, 0.0, -4.0])
    caster = TexturedCaster(tm.vertices, tm.faces, tm.visual.uv, tex)
    photo, mask = caster.render(K, _rot((1, 0.2, 0), 0.3), centre, W, H)
    cv2.imwrite(str(tmp_path / "p.png"), (np.clip(photo, 0, 1) * 255).round().astype(np.uint8)[..., ::-1])
    cv2.imwrite(str(tmp_path / "m.png"), mask.astype(np.uint8) * 255)
    got = reaimed_psnrs(tm, tex, [(K, np.eye(3), centre, tmp_path / "p.png", tmp_path / "m.png")])
    raw = render_psnr(tm, tex, K, np.eye(3), centre, _read_rgb(tmp_path / "p.png"), _read_mask(tmp_path / "m.png"))
    assert got["psnr_reaimed"] > raw + 10 and abs(got["reaim_deg"] - 0.3) < 0.03


def test_heldout_figures_of_a_photos_only_run(tmp_path):
    """bench/evaluate.py heldout_psnrs: one render per registered held-out photo gives the raw and the gain-fitted
    figure (a photo taken 30 % darker scores high only fitted); a photo SfM did not register counts only at its
    true pose."""
    from types import SimpleNamespace

    import cv2

    from bench.evaluate import HELDOUT, heldout_psnrs
    from pipeline.render.textured import TexturedCaster
    from tests.bench.test_bench_reaim import H, K, W, textured_ball

    tm, tex = textured_ball(seed=3)
    centres = np.array([[0.0, 0.0, -4.0], [0.3, 0.0, -4.0]])
    caster = TexturedCaster(tm.vertices, tm.faces, tm.visual.uv, tex)
    (tmp_path / "masks").mkdir()
    held = []
    for i, c in enumerate(centres):
        photo, mask = caster.render(K, np.eye(3), c, W, H)
        held.append(tmp_path / f"{i:06d}.png")
        cv2.imwrite(str(held[-1]), (np.clip(0.7 * photo, 0, 1) * 255).round().astype(np.uint8)[..., ::-1])
        cv2.imwrite(str(tmp_path / "masks" / held[-1].name), mask.astype(np.uint8) * 255)
    names = ["000000", f"{HELDOUT}000000"]  # SfM registered the first held-out photo only, as its 2nd view
    est = SimpleNamespace(K=np.stack([K, K]), R=np.stack([np.eye(3)] * 2), sfm_centers=centres[::-1].copy())
    got = heldout_psnrs(tm, tex, held, tmp_path / "masks", names, est, SimpleNamespace(R=est.R, sfm_centers=centres),
                        (1.0, np.eye(3), np.zeros(3)))
    assert len(got.at_sfm) == len(got.at_sfm_gain_fit) == 1 and len(got.at_true) == 2
    assert got.at_sfm[0] < 20.0 < 35.0 < got.at_sfm_gain_fit[0]
    assert max(got.at_true) < 20.0  # raw at the true poses too


def test_photos_folder_as_the_renders_or_as_a_phones_jpegs(tmp_path):
    """bench/evaluate.py photos_folder: the training and held-out renders (held-out ones prefixed) copied as PNG, or
    saved as JPEGs of the quality asked (lossy: close to the render, not equal)."""
    import cv2

    from bench.evaluate import HELDOUT, photos_folder

    syn = tmp_path / "syn"
    (syn / "images").mkdir(parents=True)
    (syn / "gt" / "heldout" / "images").mkdir(parents=True)
    rng = np.random.default_rng(0)
    renders = {}
    for kind, d, stem in (("images", syn / "images", "000000"), ("images", syn / "images", "000001"),
                          ("held", syn / "gt" / "heldout" / "images", "000000")):
        img = cv2.GaussianBlur(rng.integers(0, 256, (48, 64, 3), dtype=np.uint8), (0, 0), 1.5)
        cv2.imwrite(str(d / f"{stem}.png"), img)
        renders[(kind, stem)] = img
    png = photos_folder(syn, tmp_path / "png")
    assert sorted(p.name for p in png.iterdir()) == ["000000.png", "000001.png", f"{HELDOUT}000000.png"]
    assert (cv2.imread(str(png / "000001.png")) == renders[("images", "000001")]).all()
    jpg = photos_folder(syn, tmp_path / "jpg", jpeg_quality=92)
    assert sorted(p.name for p in jpg.iterdir()) == ["000000.jpg", "000001.jpg", f"{HELDOUT}000000.jpg"]
    got = cv2.imread(str(jpg / f"{HELDOUT}000000.jpg")).astype(float)
    err = np.abs(got - renders[("held", "000000")]).mean()
    assert 0.0 < err < 4.0


def test_true_cameras_brought_into_sfms_frame():
    """bench/evaluate.py true_in_sfm_frame: the registered photos' true centres and rotations, matched by name (a
    held-out photo among them, one training photo unregistered), and the similarity that maps the true centres onto
    SfM's; similarity_matrix applies it as a 4×4."""
    from types import SimpleNamespace

    from scipy.spatial.transform import Rotation

    from bench.evaluate import HELDOUT, similarity_matrix, true_in_sfm_frame

    class Cams(SimpleNamespace):
        def __len__(self):
            return len(self.R)

    rng = np.random.default_rng(0)
    train = Cams(sfm_centers=rng.normal(size=(4, 3)), R=Rotation.random(4, random_state=1).as_matrix())
    held = Cams(sfm_centers=rng.normal(size=(2, 3)), R=Rotation.random(2, random_state=2).as_matrix())
    names = ["000000", "000002", f"{HELDOUT}000001", "000003"]
    true_c = np.stack([train.sfm_centers[0], train.sfm_centers[2], held.sfm_centers[1], train.sfm_centers[3]])
    s, R, t = 2.5, Rotation.from_euler("xyz", [0.3, -0.2, 1.1]).as_matrix(), np.array([1.0, -2.0, 0.5])
    est = SimpleNamespace(sfm_centers=s * true_c @ R.T + t)
    centres, rotations, sim = true_in_sfm_frame(train, held, names, est)
    assert np.allclose(centres, true_c)
    assert np.allclose(rotations[2], held.R[1]) and np.allclose(rotations[1], train.R[2])
    assert np.isclose(sim[0], s) and np.allclose(sim[1], R) and np.allclose(sim[2], t)
    moved = np.c_[true_c, np.ones(4)] @ similarity_matrix(sim).T
    assert np.allclose(moved[:, :3], est.sfm_centers) and np.allclose(moved[:, 3], 1.0)
