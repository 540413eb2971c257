"""Trainer: resume after a kill equals an uninterrupted run; log.jsonl; previews; losses are means."""

import json

import torch

from dvr import losses as L
from dvr.data import RaySampler, load_scene
from dvr.trainer import Trainer, load_model, train
from tests.test_hard_cases import tiny_cfg


def test_resume_matches_uninterrupted(small_ws, tmp_path):
    cfg = tiny_cfg(iterations=8, checkpoint_every=4)
    data = load_scene(small_ws, torch.device("cpu"))
    a = train(cfg, data, tmp_path / "a")
    # "killed" after 4 steps (the checkpoint at step 4 is on disk), then a fresh process resumes
    train(cfg, data, tmp_path / "b", stop_after=4)
    b = Trainer(cfg, data, tmp_path / "b")
    assert b.try_resume() and b.step == 4
    b.fit()
    for (k, va), vb in zip(a.model.state_dict().items(), b.model.state_dict().values()):
        assert torch.allclose(va, vb, atol=1e-5), k


def test_log_and_outputs(small_ws, tmp_path):
    cfg = tiny_cfg(iterations=4, log_every=2, preview_every=2)
    data = load_scene(small_ws, torch.device("cpu"))
    t = train(cfg, data, tmp_path)
    lines = [json.loads(x) for x in (tmp_path / "log.jsonl").read_text().splitlines()]
    assert [r["step"] for r in lines] == [2, 4]
    for key in ("seconds", "loss", "psnr", "rgb", "freespace", "occupancy", "carve", "rays_per_s"):
        assert key in lines[-1]
    assert (tmp_path / "preview_000002.png").exists() and (tmp_path / "preview_final.png").exists()
    model, scale = load_model(tmp_path / "final.pt", torch.device("cpu"))
    p = torch.zeros(4, 3)
    assert torch.allclose(model.occupancy(p), t.model.occupancy(p))


def test_losses_are_means_not_sums():
    x = torch.randn(100)
    big = x.repeat(10)
    assert torch.allclose(L.freespace_loss(x), L.freespace_loss(big))
    assert torch.allclose(L.depth_loss(x, x * 0), L.depth_loss(big, big * 0))


def test_sampler_boundary_oversampling(small_ws):
    data = load_scene(small_ws, torch.device("cpu"))
    s = RaySampler(data, boundary_fraction=1.0, generator=torch.Generator().manual_seed(0))
    o, d, rgb, m = s.sample(512)
    assert o.shape == (512, 3) and rgb.shape == (512, 3) and m.shape == (512,)
    assert torch.allclose(d.norm(dim=-1), torch.ones(512))
    frac = m.mean().item()  # rays in the band straddle the boundary: both classes present
    assert 0.1 < frac < 0.9
