"""The same code on every device (``device: auto``): each op run on CPU and, where CUDA is present, on the GPU,
against the CPU result. On a machine without CUDA only the CPU cases exist (nothing is skipped)."""

import pytest
import torch
from torch.autograd import gradcheck

from dvr.config import FieldConfig
from dvr.data import load_scene
from dvr.extract import extract_mesh
from dvr.fields import make_field
from dvr.implicit import implicit_depth
from dvr.march import HIT, find_surface
from dvr.trainer import Trainer, train
from tests.dvr.test_hard_cases import tiny_cfg

DEVICES = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])


@pytest.fixture(params=DEVICES)
def device(request):
    return torch.device(request.param)


def _sphere(c, r, k=4.0):
    return lambda p: k * (r - (p - c).norm(dim=-1))


def test_find_surface_on_device(device):
    o = torch.tensor([[-3.0, y, 0.0] for y in (-0.3, 0.0, 0.2)], device=device)
    w = torch.tensor([[1.0, 0.0, 0.0]] * 3, device=device)
    c = torch.zeros(3, device=device)
    res = find_surface(_sphere(c, 0.5), o, w, n_steps=64, n_secant=8)
    assert res.depth.device.type == device.type and (res.status == HIT).all()
    expect = 3.0 - torch.sqrt(0.25 - o[:, 1] ** 2)
    assert torch.allclose(res.depth, expect, atol=1e-5)


def test_implicit_depth_gradcheck_on_device(device):
    D = torch.float64
    o0 = torch.tensor([[-2.5, 0.1, 0.05], [0.2, -2.4, 0.3]], dtype=D, device=device)
    w0 = -o0 / o0.norm(dim=-1, keepdim=True)

    def depth(c, r, o, w):
        f = _sphere(c, r)
        d = find_surface(f, o.detach(), w.detach(), n_steps=64, n_secant=60).depth
        return implicit_depth(f, [c, r], o, w, d)

    c = torch.tensor([0.05, -0.02, 0.03], dtype=D, device=device, requires_grad=True)
    r = torch.tensor(0.5, dtype=D, device=device, requires_grad=True)
    assert gradcheck(depth, (c, r, o0.clone().requires_grad_(True), w0.clone().requires_grad_(True)),
                     eps=1e-6, atol=1e-5, rtol=1e-4)


@pytest.mark.parametrize("kind", ["grid", "mlp"])
def test_field_on_device_matches_cpu(device, kind):
    cpu = make_field(FieldConfig(kind=kind, base_res=16, plane_res=(8, 16), hidden=16))
    with torch.no_grad():
        for p in cpu.parameters():
            p.normal_(0.0, 0.5)
    moved = make_field(FieldConfig(kind=kind, base_res=16, plane_res=(8, 16), hidden=16)).to(device)
    moved.load_state_dict(cpu.state_dict())
    p = torch.rand(500, 3) * 2 - 1
    assert torch.allclose(moved.occupancy(p.to(device)).cpu(), cpu.occupancy(p), atol=1e-5)
    assert torch.allclose(moved.texture(p.to(device)).cpu(), cpu.texture(p), atol=1e-5)


def test_training_on_device_computes_the_cpu_losses(small_ws, tmp_path, device):
    """The full loss on the device: the same batch gives the CPU's hit fraction, RGB and depth terms (no jitter; the
    free-space and carving points are random draws of the device's own generator), and a few optimiser steps stay
    finite with every parameter on the device."""
    terms = {}
    for dev in ("cpu", device.type):
        torch.manual_seed(0)
        t = Trainer(tiny_cfg(iterations=4, jitter=False, device=dev, gpu_batch_scale=1),  # the CPU's batch
                    load_scene(small_ws, torch.device(dev)), tmp_path / dev)
        _, stats = t.losses(0)
        terms[dev] = {k: float(stats[k]) for k in ("hit_frac", "rgb", "depth", "psnr")}
        last = t.fit()
        assert all(torch.isfinite(torch.tensor(v)) for v in last.values())
        assert all(torch.isfinite(p).all() and p.device.type == dev for p in t.model.parameters())
    assert terms["cpu"]["hit_frac"] > 0 and terms["cpu"]["rgb"] > 0
    for k, v in terms["cpu"].items():
        assert abs(terms[device.type][k] - v) <= 1e-4 * max(1.0, abs(v)), k


def test_a_gpu_trains_its_own_steps_and_says_so(small_ws, tmp_path, device, capsys):
    """``train`` runs :func:`dvr.trainer.device_schedule`'s steps to the end and writes the model, its parameters
    finite: on a GPU fewer steps of more rays, which the train stage names; on the CPU the options' own, without a
    word."""
    from pipeline.train.stage import report_schedule

    cfg = tiny_cfg(iterations=8, checkpoint_every=4, device=device.type, gpu_batch_scale=4)
    t = train(cfg, load_scene(small_ws, device), tmp_path)
    report_schedule(cfg, t.cfg, t.device)
    gpu = device.type != "cpu"
    assert (t.cfg.iterations, t.cfg.batch_rays) == ((2, 1024) if gpu else (8, 256))
    said = capsys.readouterr().out
    assert f"train: on {device.type}, 2 steps of 1024 rays" in said if gpu else said == ""
    assert t.step == t.cfg.iterations and (tmp_path / "final.pt").exists()
    assert all(torch.isfinite(p).all() for p in t.model.parameters())


def test_extract_mesh_on_device_matches_cpu(device):
    from tests.dvr.test_extract_metrics import SphereField

    v0, f0, c0 = extract_mesh(SphereField(), resolution=32)
    v1, f1, c1 = extract_mesh(SphereField().to(device), resolution=32)
    assert len(f0) > 0 and (f1 == f0).all()
    assert abs(v1 - v0).max() < 1e-5 and abs(c1.astype(int) - c0.astype(int)).max() <= 1


def test_a_device_that_cannot_be_had_is_a_value_error():
    """A user's option, one line through the CLI (not torch's RuntimeError listing some thirty device types,
    nor a RuntimeError for CUDA without a GPU: both tracebacks)."""
    from dvr.device import resolve_device

    with pytest.raises(ValueError, match="'tpu' is not a torch device; use device: auto, cpu or cuda"):
        resolve_device("tpu")
    if not torch.cuda.is_available():
        with pytest.raises(ValueError, match="CUDA is not available"):
            resolve_device("cuda")
    assert resolve_device("cpu") == torch.device("cpu")
