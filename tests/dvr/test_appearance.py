"""Per-view appearance (exposure and white balance): smoke, bad input, shapes, gradcheck; the bake's inverse; and
the generator's exposure recovered by training."""

import json

import cv2
import numpy as np
import pytest
import torch
from torch.autograd import gradcheck

from dvr.appearance import ViewAppearance
from pipeline.cli import main
from pipeline.texture.appearance import photos_for_bake, undo_appearance
from pipeline.texture.config import TextureConfig
from synth import write_scene
from tests.conftest import small_scene


def test_identity_at_start_and_zero_regulariser():
    a = ViewAppearance(4)
    c = torch.rand(10, 3)
    assert torch.equal(a(c, torch.randint(0, 4, (10,))), c)
    assert float(a.regulariser().detach()) == 0.0 and torch.equal(a.gains(), torch.ones(4, 3))


def test_bad_input():
    a = ViewAppearance(4)
    with pytest.raises(ValueError, match="at least one view"):
        ViewAppearance(0)
    with pytest.raises(ValueError, match="colour must be"):
        a(torch.rand(10, 4), torch.zeros(10, dtype=torch.long))
    with pytest.raises(ValueError, match="view must be"):
        a(torch.rand(10, 3), torch.zeros(10))
    with pytest.raises(ValueError, match="view must be"):
        a(torch.rand(10, 3), torch.zeros(9, dtype=torch.long))


def test_shapes_forward_and_undo_are_inverse():
    a = ViewAppearance(3)
    with torch.no_grad():
        a.log_gain.copy_(torch.tensor([[0.1, -0.2, 0.05], [0.0, 0.0, 0.0], [-0.3, 0.2, 0.1]]))
    c = torch.rand(7, 3)
    v = torch.full((7,), 2, dtype=torch.long)
    out = a(c, v)
    assert out.shape == (7, 3)
    assert torch.allclose(a.undo(out, 2), c, atol=1e-6)


def test_gradcheck():
    a = ViewAppearance(3).double()
    with torch.no_grad():
        a.log_gain.normal_(0, 0.1)
    v = torch.tensor([0, 2, 1, 2])

    def f(c, g):
        return c * torch.exp(g[v])

    c = torch.rand(4, 3, dtype=torch.double, requires_grad=True)
    g = a.log_gain.detach().clone().requires_grad_()
    assert gradcheck(f, (c, g))
    assert torch.allclose(f(c, g), ViewAppearance.forward(a, c, v))  # the module computes what is checked


def test_undo_appearance_maps_photos_back_and_survives_a_zero_gain():
    shared = np.random.default_rng(0).random((8, 8, 3)).astype(np.float32) * 0.6
    looks = {"a": {"gain": [1.2, 0.9, 1.1]}, "b": {"gain": [1 / 1.2, 1 / 0.9, 1 / 1.1]}}
    photo = shared * np.float32([1.2, 0.9, 1.1])
    (back, other), common = undo_appearance([photo, shared], ["a", "not fitted"], looks)
    assert np.allclose(back, shared, atol=1e-6) and np.allclose(common, 1.0)
    assert other is shared
    (zero,), _ = undo_appearance([shared], ["z"], {"z": {"gain": [0.0, 1, 1]}, "y": {"gain": [1, 1, 1]}})
    assert np.isfinite(zero).all()  # a zero gain (a hand-edited file) gives no inf or NaN


def test_undo_appearance_leaves_a_drift_common_to_all_views_out_of_the_texture():
    """Training on photos with no exposure change at all, every gain drifted the same way (1.07 / 1.05 / 1.01 on
    the cow): the bake must not divide the photos by that (a darker, tinted texture: held-out PSNR 1.8 dB lower)."""
    rng = np.random.default_rng(1)
    photos = [rng.random((8, 8, 3)).astype(np.float32) * 0.8 for _ in range(3)]
    drift = [1.066, 1.049, 1.014]
    looks = {f"v{i}": {"gain": drift} for i in range(3)}
    back, common = undo_appearance(photos, list(looks), looks)
    assert all(np.allclose(b, p, atol=1e-6) for b, p in zip(back, photos))
    assert np.allclose(common, drift)


def test_unseen_texels_take_the_field_colour_times_the_common_gain():
    from dvr.config import FieldConfig
    from dvr.fields import make_field
    from pipeline.texture.stage import fill_unseen

    field = make_field(FieldConfig(kind="grid", base_res=8, plane_res=(16,)))
    pts = np.random.default_rng(0).uniform(-0.5, 0.5, (5, 3))
    unseen = np.ones(5, bool)
    plain = fill_unseen(pts, np.zeros((5, 3)), unseen, field)
    scaled = fill_unseen(pts, np.zeros((5, 3)), unseen, field, field_gain=np.array([1.1, 1.0, 0.5]))
    assert np.allclose(scaled, np.clip(plain * [1.1, 1.0, 0.5], 0, 1), atol=1e-6)


def test_the_bake_finds_clipped_pixels_in_the_photos_as_taken_and_only_with_gains(tmp_path):
    """With fitted gains the over-exposed pixels come from the photo as taken (dividing by a gain of 1.25 moves a
    clipped 1.0 to 0.8, where a threshold on the undone photo would miss it); without gains none are kept out."""
    photo = np.full((6, 8, 3), 0.5, np.float32)
    photo[2, 3] = 1.0
    path = tmp_path / "a.png"
    cv2.imwrite(str(path), (photo * 255).round().astype(np.uint8))
    looks = tmp_path / "appearance.json"
    cfg = TextureConfig()
    images, gain, clipped = photos_for_bake([path], looks, cfg)
    assert clipped is None and np.allclose(gain, 1) and np.allclose(images[0], photo, atol=1 / 255)
    looks.write_text(json.dumps({"a": {"gain": [1.25, 1.25, 1.25]}, "b": {"gain": [0.8, 0.8, 0.8]}}))
    images, gain, clipped = photos_for_bake([path], looks, cfg)
    assert np.allclose(images[0][2, 3], 0.8, atol=0.01)  # undone: below the clipping level
    assert clipped[0][2, 3] and clipped[0].sum() == 9  # found in the photo as taken (and its neighbours)


def test_a_broken_appearance_file_is_one_clear_error(tmp_path):
    from pipeline.errors import StageError
    from pipeline.texture.appearance import read_appearance

    good = tmp_path / "appearance.json"
    good.write_text(json.dumps({"a": {"gain": [1.0, 0.9, 1.1]}}))
    assert read_appearance(good) == {"a": {"gain": [1.0, 0.9, 1.1]}}
    for text in ('{"a": {"gain": [1.0, NaN, 1]}}', '{"a": {"gain": [1.0, -1, 1]}}', '{"a": {"gain": [1, 1]}}',
                 '{"a": {"gains": [1, 1, 1]}}', "[1, 2", '{"a": 3}',
                 # scalar gains, three views: reshaped to one row of 3 they passed, and relative_gains' message
                 # (naming no file) reached the user
                 '{"a": {"gain": 1.2}, "b": {"gain": 0.9}, "c": {"gain": 1.0}}',
                 '{"a": {"gain": [1, 1, 1, 1, 1, 1]}, "b": {"gain": []}}'):
        good.write_text(text)
        with pytest.raises(StageError, match="appearance.json"):
            read_appearance(good)


def test_relative_gains_rejects_bad_input():
    from dvr.appearance import relative_gains

    rel, common = relative_gains(np.array([[2.0, 1, 1], [0.5, 1, 4]]))
    assert np.allclose(common, [1, 1, 2]) and np.allclose(rel * common, [[2, 1, 1], [0.5, 1, 4]])
    for bad in (np.ones((2, 2)), np.zeros((0, 3)), np.array([[1.0, 0, 1]]), np.array([[1.0, np.nan, 1]])):
        with pytest.raises(ValueError, match="relative_gains"):
            relative_gains(bad)


def test_report_lists_the_fitted_gains(tmp_path):
    from pipeline.report.stage import appearance_section
    from pipeline.workspace import Workspace

    assert appearance_section(Workspace(tmp_path)) == ""  # not fitted: no section
    (tmp_path / "model").mkdir()
    looks = {"000000": {"gain": [1.21, 0.9, 1.0]}, "000001": {"gain": [0.8, 1, 1]}}
    (tmp_path / "model" / "appearance.json").write_text(json.dumps(looks))
    html = appearance_section(Workspace(tmp_path))
    # relative to the average view: R's common part is sqrt(1.21 · 0.8) = 0.984, 1.21 / 0.984 = 1.230
    assert "Per-view appearance" in html and "000001" in html and "1.230" in html and "0.81–1.23" in html
    assert "0.984 / 0.949 / 1.000" in html
    (tmp_path / "model" / "appearance.json").write_text('{"000000": {"gain": [1, NaN, 1]}}')
    assert "must be finite and positive" in appearance_section(Workspace(tmp_path))  # a line, not a traceback


def fitted_gain_error(folder, albedo: dict, *options: str) -> tuple[float, float]:
    """Train a small torus photographed with per-view exposure and white balance (±25 % gain, ±8 % per channel)
    with the per-view appearance on: the largest relative error of the fitted gains against the generator's (both
    normalised by their mean over the views: a common factor belongs to the texture), and the largest true gain's
    departure from 1."""
    sc = small_scene(albedo=albedo, cameras={"n_views": 12, "width": 80, "height": 80},
                     effects=[{"kind": "exposure", "amount": 0.25, "white_balance": 0.08}])
    write_scene(sc, folder)
    args = ["train", str(folder), "--train.iterations", "400", "--train.no-progress", "--train.preview-every", "0",
            "--train.appearance", "on", *options]
    assert main(args) == 0
    truth = json.loads((folder / "gt" / "exposure.json").read_text())["images"]
    fitted = json.loads((folder / "model" / "appearance.json").read_text())
    names = sorted(truth)
    g_true = np.array([truth[n] for n in names])
    g_fit = np.array([fitted[n]["gain"] for n in names])
    g_true, g_fit = g_true / g_true.mean(0), g_fit / g_fit.mean(0)
    return float(np.abs(g_fit / g_true - 1).max()), float(np.abs(g_true - 1).max())


@pytest.mark.slow
@pytest.mark.long
def test_training_recovers_the_generators_exposure_where_views_clip(tmp_path):
    """A bright albedo that the brighter views clip at white: the fitted gains match the generator's within 5 %,
    because a clipped channel only says "at least this bright" (the censored RGB loss); with plain L1 on the
    clipped pixels (``--train.clipped-level 2``) the bright views' gains come out lower."""
    bright = {"kind": "noise", "scale": 2.0, "contrast": 0.3, "color": [0.92, 0.88, 0.85]}
    err, spread = fitted_gain_error(tmp_path / "censored", bright)
    plain, _ = fitted_gain_error(tmp_path / "plain", bright, "--train.clipped-level", "2")
    print("censored", err, "plain L1", plain)
    assert spread > 0.1  # the exposure was there to recover
    assert err < 0.05
    assert plain > 1.5 * err  # what the censored loss prevents
