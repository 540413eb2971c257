"""View-dependent shading residual (dvr/shading.py): smoke, bad input, shapes, gradcheck; its encodings checked
against their definitions."""

import math

import pytest
import torch
from torch.autograd import gradcheck

from dvr.fields import fourier_encode
from dvr.shading import ViewShading, reflect, sh_degree2


def unit(v: torch.Tensor) -> torch.Tensor:
    return v / v.norm(dim=-1, keepdim=True)


def test_zero_at_start_and_zero_regulariser():
    torch.manual_seed(0)
    s = ViewShading()
    p, d, n = torch.rand(50, 3) * 2 - 1, unit(torch.randn(50, 3)), unit(torch.randn(50, 3))
    r = s(p, d, n)
    assert r.shape == (50, 3) and torch.equal(r, torch.zeros(50, 3))
    assert ViewShading.regulariser(r) == 0
    assert ViewShading.regulariser(torch.zeros(0, 3)) == 0  # no hits: exact 0, no NaN


def test_bad_input():
    s = ViewShading()
    with pytest.raises(ValueError, match="ViewShading"):
        s(torch.zeros(4, 3), torch.zeros(4, 2), torch.zeros(4, 3))
    with pytest.raises(ValueError, match="ViewShading"):
        s(torch.zeros(4, 3), torch.zeros(4, 3), torch.zeros(5, 3))
    with pytest.raises(ValueError, match="ViewShading"):
        s(torch.zeros(4), torch.zeros(4), torch.zeros(4))
    with pytest.raises(ValueError, match="ViewShading"):
        ViewShading(max_shading=0.0)


def test_shapes_bounds_and_view_dependence():
    torch.manual_seed(1)
    s = ViewShading(hidden=16, n_freqs=3, max_shading=0.2)
    torch.nn.init.normal_(s.net[-1].weight, std=5.0)  # far from identity: the tanh saturates
    p, n = torch.rand(200, 3) * 2 - 1, unit(torch.randn(200, 3))
    d1, d2 = unit(torch.randn(200, 3)), unit(torch.randn(200, 3))
    r1, r2 = s(p, d1, n), s(p, d2, n)
    assert r1.shape == (200, 3) and r1.abs().max() <= 0.2
    assert (r1 - r2).abs().max() > 1e-3  # the same points seen from elsewhere shade differently
    assert fourier_encode(p, s.freqs).shape == (200, 3 + 18)
    assert s(torch.zeros(0, 3), torch.zeros(0, 3), torch.zeros(0, 3)).shape == (0, 3)


def test_gradcheck():
    torch.manual_seed(2)
    s = ViewShading(hidden=8).double()
    torch.nn.init.normal_(s.net[-1].weight, std=0.5)
    p = (torch.rand(6, 3, dtype=torch.float64) * 2 - 1).requires_grad_()
    d = unit(torch.randn(6, 3, dtype=torch.float64)).requires_grad_()
    n = unit(torch.randn(6, 3, dtype=torch.float64)).requires_grad_()
    assert gradcheck(lambda a, b, c: s(a, b, c), (p, d, n), eps=1e-6, atol=1e-5)


def test_spherical_harmonics_are_orthonormal():
    """Monte Carlo over the sphere: ∫ Y_i Y_j dω = δ_ij (4π × the mean over uniform directions)."""
    torch.manual_seed(3)
    d = unit(torch.randn(400000, 3, dtype=torch.float64))
    y = sh_degree2(d)
    gram = 4 * math.pi * (y.T @ y) / len(d)
    assert torch.allclose(gram, torch.eye(9, dtype=torch.float64), atol=0.02)


def test_reflect_keeps_the_angle_and_is_its_own_inverse():
    torch.manual_seed(4)
    d, n = unit(torch.randn(100, 3)), unit(torch.randn(100, 3))
    r = reflect(d, n)
    assert torch.allclose(r.norm(dim=-1), torch.ones(100), atol=1e-6)
    assert torch.allclose((r * n).sum(-1), -(d * n).sum(-1), atol=1e-6)
    assert torch.allclose(reflect(r, n), d, atol=1e-6)


def test_training_keeps_highlights_out_of_the_diffuse_field(tmp_path):
    """A lit torus with specular highlights: with ``view_shading`` the diffuse field trained on its photos is closer
    to the same scene photographed without highlights (at the training views) than without it."""
    import numpy as np

    from dvr.config import FieldConfig
    from dvr.data import load_scene
    from dvr.march import render_view
    from dvr.metrics import masked_psnr
    from dvr.trainer import train
    from synth import write_scene
    from tests.conftest import small_scene
    from tests.dvr.test_hard_cases import tiny_cfg

    look = dict(albedo={"kind": "noise", "scale": 2.0, "contrast": 0.5, "color": [0.55, 0.5, 0.45]},
                lighting={"kind": "lambertian"}, cameras={"n_views": 16, "width": 64, "height": 64})
    write_scene(small_scene(**look, effects=[{"kind": "specular", "amount": 0.4, "shininess": 6.0}]),
                tmp_path / "glossy")
    write_scene(small_scene(**look), tmp_path / "matte")
    data = load_scene(tmp_path / "glossy", torch.device("cpu"))
    score = {}
    for on in (False, True):
        torch.manual_seed(0)
        t = train(tiny_cfg(iterations=600, view_shading=on, checkpoint_every=1000, log_every=100,
                           field=FieldConfig(base_res=32, plane_res=(32, 64), hidden=32)),
                  data, tmp_path / f"out{on}")
        psnr = []
        for i in range(0, 16, 4):
            with torch.no_grad():
                img, hit = render_view(t.model, t.data, i)
            matte = load_scene(tmp_path / "matte", torch.device("cpu")).images[i].numpy()
            psnr.append(masked_psnr(img.numpy(), matte, hit.numpy() & (data.masks[i].numpy() > 0.5)))
        score[on] = float(np.mean(psnr))
    print("diffuse field against the matte photos: without", score[False], "with view shading", score[True])
    assert score[True] > score[False] + 0.5
