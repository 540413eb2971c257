"""dvr.surface_graph.SurfaceFinder: the trainer's surface finding, eager on CPU and replayed as CUDA graphs on a GPU,
against dvr.march.find_surface with the same jitter. The CUDA cases run where a GPU is present (bench/gpu_check.sh
runs them on the lent one)."""

import pytest
import torch

from dvr.march import HIT, find_surface
from dvr.surface_graph import SurfaceFinder
from tests.dvr.test_march import mixed_rays

DEVICES = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])
cuda_only = pytest.mark.skipif(not torch.cuda.is_available(), reason="CUDA graphs need a GPU")


class Balls(torch.nn.Module):
    """Two balls whose centres are parameters (the optimizer moves them in place) and a buffer scale."""

    def __init__(self):
        super().__init__()
        self.centres = torch.nn.Parameter(torch.tensor([[0.3, 0.0, 0.0], [-0.4, 0.1, 0.0]]))
        self.register_buffer("radii", torch.tensor([0.35, 0.25]))

    def occupancy(self, p: torch.Tensor) -> torch.Tensor:
        return 20.0 * (self.radii - (p[:, None, :] - self.centres).norm(dim=-1)).max(dim=1).values


def _finder(field: Balls, graphs: bool = True, keep: int = 4) -> SurfaceFinder:
    return SurfaceFinder(field.occupancy, lambda: [*field.parameters(), *field.buffers()], n_secant=6, graphs=graphs,
                         keep=keep)


def _same(got, ref):
    assert torch.equal(got.status, ref.status)
    assert torch.allclose(got.depth, ref.depth, atol=1e-5) and torch.allclose(got.max_depth, ref.max_depth, atol=1e-5)


@pytest.mark.parametrize("device", DEVICES)
def test_finder_equals_find_surface_with_the_same_jitter(device):
    field = Balls().to(device)
    o, d = (x.to(device) for x in mixed_rays())
    finder = _finder(field)
    for n_steps in (40, 40, 56):
        torch.manual_seed(5)
        ref = find_surface(field.occupancy, o, d, n_steps=n_steps, n_secant=6, jitter=True)
        torch.manual_seed(5)
        got = finder(o, d, n_steps=n_steps, jitter=True)
        _same(got, ref)
        assert (ref.status == HIT).sum() > 100 and got.depth.device.type == device
    assert finder.captures == (2 if device == "cuda" else 0)  # one graph per sample count; none on CPU


@cuda_only
def test_a_graph_sees_parameters_changed_in_place_and_recaptures_for_replaced_ones():
    field = Balls().cuda()
    o, d = (x.cuda() for x in mixed_rays())
    finder = _finder(field)
    finder(o, d, n_steps=48, jitter=False)
    with torch.no_grad():
        field.centres.add_(0.05)  # as an optimizer step: in place, the graph reads the new values
    _same(finder(o, d, n_steps=48, jitter=False), find_surface(field.occupancy, o, d, n_steps=48, n_secant=6))
    assert finder.captures == 1
    field.centres = torch.nn.Parameter(field.centres.detach() - 0.1)  # replaced, as the grid's upsampling does
    _same(finder(o, d, n_steps=48, jitter=False), find_surface(field.occupancy, o, d, n_steps=48, n_secant=6))
    assert finder.captures == 2


@cuda_only
def test_graphs_kept_are_bounded_and_the_copies_survive_the_next_replay():
    field = Balls().cuda()
    o, d = (x.cuda() for x in mixed_rays())
    finder = _finder(field, keep=2)
    first = finder(o, d, n_steps=32, jitter=False)
    kept = first.depth.clone()
    finder(o, d[torch.randperm(d.shape[0], device="cuda")], n_steps=32, jitter=False)  # same graph, other rays
    assert torch.equal(first.depth, kept)
    for n in (33, 34, 35):
        finder(o, d, n_steps=n, jitter=False)
    assert len(finder.graphs) == 2 and finder.captures == 4


@cuda_only
def test_training_with_and_without_graphs_computes_the_same_losses(small_ws, tmp_path):
    """The first step's loss terms (same seed, jitter on) with the graphs as without; then a short fit runs on the
    graphs (the batch's rays and the sparse depth's: two) and stays finite. Later steps are not compared: CUDA's
    atomic adds make the backward pass differ in the last bits, and Adam's steps amplify that."""
    from dvr.data import load_scene
    from dvr.trainer import Trainer
    from tests.dvr.test_hard_cases import tiny_cfg

    terms = {}
    for graphs in (False, True):
        t = Trainer(tiny_cfg(iterations=5, device="cuda", cuda_graphs=graphs),
                    load_scene(small_ws, torch.device("cuda")), tmp_path / str(graphs))
        _, stats = t.losses(0)
        terms[graphs] = {k: float(stats[k]) for k in ("hit_frac", "rgb", "depth", "psnr")}
        last = t.fit()
        assert all(torch.isfinite(torch.tensor(v)) for v in last.values())
        assert t.find_surface.captures == (2 if graphs else 0)
    assert terms[False]["hit_frac"] > 0
    for k, v in terms[False].items():
        assert abs(terms[True][k] - v) <= 1e-5 * max(1.0, abs(v)), k


@cuda_only
@pytest.mark.parametrize("kind,occ_planes", [("grid", ()), ("grid", (16, 32)), ("mlp", ())])
def test_every_field_kind_is_captured(kind, occ_planes):
    """Each field the trainer can train is captured (no fallback to eager) and found as eagerly, with a support
    plane set (moved to the device on its first call, before the capture)."""
    from dvr.config import FieldConfig
    from dvr.fields import make_field

    field = make_field(FieldConfig(kind=kind, base_res=16, plane_res=(8, 16), occ_plane_res=occ_planes,
                                   hidden=16)).cuda()
    with torch.no_grad():
        for p in field.parameters():
            p.normal_(0.0, 0.5)
    field.set_support([0.0, 0.0, 1.0, 0.4])
    finder = SurfaceFinder(field.occupancy, lambda: [*field.parameters(), *field.buffers(), field.support], 6)
    o, d = (x.cuda() for x in mixed_rays())
    got = finder(o, d, n_steps=48, jitter=False)
    assert finder.graphs_on and finder.captures == 1
    _same(got, find_surface(field.occupancy, o, d, n_steps=48, n_secant=6))
