"""Discrete view selection for the bake (pipeline/texture/view_select.py): the Potts labelling on hand-made scores, the
chart weights, bad input, and the bake taking the sharp view of a plane where a blend mixes in a blurred one."""

import numpy as np
import pytest

from pipeline.texture.config import TextureConfig
from pipeline.texture.view_select import chart_weights, face_adjacency, select_views
from tests.pipeline.texture.test_texture import SYNTH, inner_rms_error, plane_mesh, sharp_and_blurred_views


def _energy(labels, scores, adjacency, smoothness):
    best = scores.max(1)
    data = -np.log(scores[np.arange(len(labels)), labels] / best).sum()
    a, b = adjacency.nonzero()
    return data + smoothness * (labels[a] != labels[b]).sum() / 2


def _noisy_halves(seed=0):
    """A 21 × 21 vertex plane: view 0 a little better on the left half, view 1 on the right, with noise that makes
    the per-face best view flip here and there."""
    mesh = plane_mesh()
    faces = np.asarray(mesh.faces)
    x = mesh.vertices[faces].mean(1)[:, 0]
    rng = np.random.default_rng(seed)
    scores = np.stack([1.0 - 0.2 * x, 1.0 + 0.2 * x], 1) * rng.uniform(0.8, 1.2, (len(faces), 2))
    return faces, scores, x


def test_smoothness_makes_few_charts_at_lower_energy():
    faces, scores, x = _noisy_halves()
    adj = face_adjacency(faces)
    plain = select_views(scores, adj, 0.0, data_rings=0)
    smooth = select_views(scores, adj, 1.0, data_rings=0)
    assert (plain == scores.argmax(1)).all()
    a, b = adj.nonzero()
    borders = {k: int((lab[a] != lab[b]).sum() // 2) for k, lab in (("plain", plain), ("smooth", smooth))}
    print("border edges", borders)
    assert borders["plain"] > 100  # the noise scatters the best view
    assert borders["smooth"] < 0.2 * borders["plain"]
    assert _energy(smooth, scores, adj, 1.0) < _energy(plain, scores, adj, 1.0)
    # the charts follow the data: view 0 on the left, view 1 on the right
    assert (smooth[x < -0.4] == 0).mean() > 0.95 and (smooth[x > 0.4] == 1).mean() > 0.95


def test_a_view_that_alone_sees_a_face_keeps_it_and_unseen_faces_get_none():
    faces, scores, _ = _noisy_halves()
    scores[:, 1] = np.where(np.arange(len(faces)) % 7 == 0, 0.0, scores[:, 1])
    scores[5] = [0.0, 3.0]  # only view 1 sees face 5, in the middle of view 0's half
    scores[6] = 0.0  # nothing sees face 6
    labels = select_views(scores, face_adjacency(faces), 5.0, data_rings=1)
    assert labels[5] == 1 and labels[6] == -1
    assert (labels[(scores[:, 1] == 0) & (scores[:, 0] > 0)] == 0).all()


def test_chart_weights_blend_at_borders_only():
    faces = np.asarray(plane_mesh().faces)
    adj = face_adjacency(faces)
    x = plane_mesh().vertices[faces].mean(1)[:, 0]
    labels = (x > 0).astype(int)
    labels[:3] = -1
    hard = chart_weights(labels, 3, adj, 0, 0.1)
    assert np.allclose(hard[labels == 1], [0.1, 1.0, 0.1]) and np.allclose(hard[labels == 0], [1.0, 0.1, 0.1])
    assert np.allclose(hard[:3], 1.0)  # unlabelled: the plain blend
    soft = chart_weights(labels, 3, adj, 2, 0.0)
    assert np.allclose(soft.sum(1)[3:], 1.0)
    mixed = (soft[:, 0] > 0) & (soft[:, 1] > 0)
    assert mixed.any() and np.abs(x[mixed]).max() < 0.3  # a band about the border x = 0
    assert np.allclose(soft[np.abs(x) > 0.5].max(1), 1.0)


def test_bad_input_is_refused_clearly():
    faces, scores, _ = _noisy_halves()
    adj = face_adjacency(faces)
    with pytest.raises(ValueError, match="select_views"):
        select_views(scores[:-1], adj, 1.0)
    with pytest.raises(ValueError, match="finite and non-negative"):
        select_views(np.where(np.arange(len(scores))[:, None] == 3, np.nan, scores), adj, 1.0)
    with pytest.raises(ValueError, match="finite and non-negative"):
        select_views(-scores, adj, 1.0)
    with pytest.raises(ValueError, match="smoothness"):
        select_views(scores, adj, -1.0)
    with pytest.raises(ValueError, match="chart_weights"):
        chart_weights(np.zeros(3, int), 2, adj, 1, 0.1)
    with pytest.raises(ValueError, match="floor"):
        chart_weights(np.zeros(len(faces), int), 2, adj, 1, 1.5)
    with pytest.raises(ValueError, match="face_adjacency"):
        face_adjacency(faces[:, :2])


def test_bake_takes_the_sharp_view_where_a_blend_mixes_in_the_blurred_one():
    """Two equally placed views of a finely patterned plane, one defocused: the sharpness-weighted blend still
    mixes the blurred view in; with view selection most faces take the sharp view (near the plane's far edge the
    blurred one is more frontal and closer, and may win) and the error drops by a third."""
    mesh, cams, imgs = sharp_and_blurred_views()
    err = {select: inner_rms_error(mesh, imgs, cams, TextureConfig(**{**SYNTH, "sharpness_power": 1.0},
                                                                   seam_levelling=False, outlier_threshold=0.0,
                                                                   view_selection=select))
           for select in (True, False)}
    print("RMS error with / without view selection", err)
    assert err[True] < 0.7 * err[False]
