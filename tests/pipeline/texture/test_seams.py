"""Global seam levelling (pipeline/texture/seams.py): per-view, per-vertex colour offsets solved in least squares. A
known brightness offset between two views of a plane is removed from the bake; the solver on hand-made samples; clear
errors for bad input."""

import numpy as np
import pytest

from pipeline.texture.config import TextureConfig
from pipeline.texture.seams import fit_seam_offsets, mesh_edges, texel_offsets
from tests.pipeline.texture.test_texture import SYNTH, bake_texels, make_cameras, plane_mesh, render_mesh, smooth_colour


def test_levelling_removes_a_known_offset_between_two_views():
    """Two cameras over a textured plane, one photo +0.1 brighter: without levelling the baked colour's error steps
    by ~0.1 where the weights hand over from one view to the other; with it, the error is flat across the plane."""
    mesh = plane_mesh()
    cams = make_cameras([(-0.7, 0.0, 2.2), (0.7, 0.0, 2.2)], (0, 0, 0), 40.0, 96, down=(0.0, -1.0, 0.0))
    imgs = render_mesh(mesh, smooth_colour, cams, 96)
    imgs[1] = imgs[1] + 0.1
    bins = np.linspace(-0.8, 0.8, 9)
    step = {}
    for levelling in (True, False):
        baked, true, pts = bake_texels(mesh, imgs, cams, TextureConfig(**SYNTH, seam_levelling=levelling))
        err = (baked - true).mean(1)
        which = np.digitize(pts[:, 0], bins)
        inner = (np.abs(pts[:, 1]) < 0.8) & (which > 0) & (which < len(bins))
        profile = np.array([err[inner & (which == b)].mean() for b in range(1, len(bins))])
        step[levelling] = profile.max() - profile.min()
        print("levelling" if levelling else "plain", "error profile along x:", profile.round(3))
    assert step[False] > 0.06  # the offset shows as a ramp from one view to the other
    assert step[True] < 0.015


def test_solver_recovers_offsets_on_a_strip():
    """Hand-made samples: views 0 and 1 overlap in the middle of a strip of vertices, view 1 reads +0.2 in red.
    The fitted offsets make them agree everywhere (also where only one view sees), split around the mean."""
    n = 11  # vertices 0..10 along a strip of degenerate "faces" (i, i+1, i+1)
    faces = np.array([[i, i + 1, i + 1] for i in range(n - 1)])
    texel_vertices = np.array([[i, i + 1, i + 1] for i in range(n - 1) for _ in range(5)])
    t = np.tile(np.linspace(0.1, 0.9, 5), n - 1)
    texel_bary = np.stack([1 - t, t, np.zeros_like(t)], 1)
    texel = np.arange(len(t))
    seen0, seen1 = texel < 35, texel >= 15  # overlap: texels 15..34
    colour = np.full((len(t), 3), 0.5)
    view = np.concatenate([np.zeros(seen0.sum(), int), np.ones(seen1.sum(), int)])
    tex = np.concatenate([texel[seen0], texel[seen1]])
    col = np.concatenate([colour[seen0], colour[seen1] + [0.2, 0.0, 0.0]])
    off = fit_seam_offsets(view, tex, col, np.ones(len(view)), texel_vertices, texel_bary, faces, n, 2)
    assert off.shape == (2, n, 3) and off.dtype == np.float32 and np.isfinite(off).all()
    level0 = col[view == 0] + texel_offsets(off[0], texel_vertices[tex[view == 0]], texel_bary[tex[view == 0]])
    level1 = col[view == 1] + texel_offsets(off[1], texel_vertices[tex[view == 1]], texel_bary[tex[view == 1]])
    assert np.abs(level0[:, 0] - 0.6).max() < 0.01 and np.abs(level1[:, 0] - 0.6).max() < 0.01
    assert np.abs(off[:, :, 1:]).max() < 1e-6  # green and blue agreed already


def test_no_overlap_means_no_offsets():
    faces = np.array([[0, 1, 2]])
    off = fit_seam_offsets(np.array([0, 1]), np.array([0, 1]), np.array([[0.2] * 3, [0.8] * 3]), np.ones(2),
                           np.array([[0, 1, 2]] * 2), np.full((2, 3), 1 / 3), faces, 3, 2)
    assert np.abs(off).max() == 0.0


def test_bad_input_is_refused_clearly():
    faces = np.array([[0, 1, 2]])
    tv, tb = np.array([[0, 1, 2]]), np.full((1, 3), 1 / 3)
    args = dict(sample_view=np.array([0]), sample_texel=np.array([0]), sample_colour=np.full((1, 3), 0.5),
                sample_weight=np.ones(1), texel_vertices=tv, texel_bary=tb, faces=faces, n_verts=3, n_views=1)
    fit_seam_offsets(**args)  # fine
    for key, bad, msg in [("sample_colour", np.zeros((1, 4)), "sample_colour"),
                          ("sample_texel", np.array([0, 0]), "shape"),
                          ("texel_bary", np.zeros((1, 2)), "texel_bary"),
                          ("faces", np.zeros((1, 4), int), "faces"),
                          ("faces", np.array([[0, 1, 7]]), "faces must index"),
                          ("sample_view", np.array([3]), "sample_view"),
                          ("sample_texel", np.array([5]), "sample_texel"),
                          ("sample_weight", np.array([np.nan]), "finite")]:
        with pytest.raises(ValueError, match=msg):
            fit_seam_offsets(**{**args, key: bad})
    with pytest.raises(ValueError, match="zero_pull"):
        fit_seam_offsets(**args, zero_pull=0.0)
    with pytest.raises(ValueError, match="view_offsets"):
        texel_offsets(np.zeros((3, 2)), tv, tb)
    with pytest.raises(ValueError, match="texel_vertices"):
        texel_offsets(np.zeros((3, 3)), tv, np.zeros((2, 3)))
    with pytest.raises(ValueError, match="faces"):
        mesh_edges(np.zeros((2, 2), int))
    assert mesh_edges(np.array([[0, 1, 2], [2, 1, 3]])).tolist() == [[0, 1], [0, 2], [1, 2], [1, 3], [2, 3]]


def test_fast_helpers_match_their_references():
    """mesh_edges (integer keys) is np.unique of the sorted edge rows; texel_offsets (channel by channel) is the
    einsum of barycentrics and corner offsets, bit for bit."""
    rng = np.random.default_rng(0)
    faces = rng.integers(0, 30, (200, 3))
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    e.sort(axis=1)
    assert np.array_equal(mesh_edges(faces), np.unique(e[e[:, 0] != e[:, 1]], axis=0))
    assert mesh_edges(np.zeros((0, 3), int)).shape == (0, 2)
    offsets = rng.normal(size=(30, 3)).astype(np.float32)
    tv, tb = rng.integers(0, 30, (500, 3)), rng.random((500, 3))
    want = np.einsum("kc,kcj->kj", tb.astype(np.float32), offsets[tv])
    assert np.array_equal(texel_offsets(offsets, tv, tb), want)


def test_fit_does_not_depend_on_the_order_of_the_samples():
    """The samples are grouped by view inside the fit: handing them over shuffled changes nothing but rounding."""
    mesh = plane_mesh(n=6)
    rng = np.random.default_rng(2)
    n_tex = 300
    face = rng.integers(0, len(mesh.faces), n_tex)
    bary = rng.dirichlet(np.ones(3), n_tex)
    view = np.repeat(np.arange(3), n_tex)
    texel = np.tile(np.arange(n_tex), 3)
    colour = rng.random((3 * n_tex, 3)) * 0.1 + np.repeat([[0.5] * 3, [0.6] * 3, [0.45] * 3], n_tex, 0)
    weight = rng.random(3 * n_tex)
    args = (mesh.faces[face], bary, mesh.faces, len(mesh.vertices), 3)
    ordered = fit_seam_offsets(view, texel, colour, weight, *args)
    p = rng.permutation(len(view))
    shuffled = fit_seam_offsets(view[p], texel[p], colour[p], weight[p], *args)
    assert np.abs(ordered).max() > 0.01
    assert np.allclose(ordered, shuffled, atol=1e-6)
