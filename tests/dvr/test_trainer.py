"""Trainer: resume after a kill equals an uninterrupted run; log.jsonl; previews; losses are means."""

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch

from dvr import losses as L
from dvr.checkpoint import load_model
from dvr.data import RaySampler, load_scene
from dvr.hull import grid_points
from dvr.trainer import Trainer, device_schedule, train
from tests.dvr.test_hard_cases import tiny_cfg


@pytest.mark.parametrize("extras", [{}, {"appearance": "on", "view_shading": True}])
def test_resume_matches_uninterrupted(small_ws, tmp_path, extras):
    """A run killed after its checkpoint and resumed equals an uninterrupted one (field, and the per-view gains and
    view-shading MLP when they are on)."""
    cfg = tiny_cfg(iterations=8, checkpoint_every=4, **extras)
    data = load_scene(small_ws, torch.device("cpu"))
    a = train(cfg, data, tmp_path / "a")
    # "killed" after 4 steps (the checkpoint at step 4 is on disk), then a fresh process resumes
    train(cfg, data, tmp_path / "b", stop_after=4)
    b = Trainer(cfg, data, tmp_path / "b")
    assert b.try_resume() and b.step == 4
    b.fit()
    for mod_a, mod_b in ((a.model, b.model), (a.appearance, b.appearance), (a.shading, b.shading)):
        if mod_a is None:
            continue
        for (k, va), vb in zip(mod_a.state_dict().items(), mod_b.state_dict().values()):
            assert torch.allclose(va, vb, atol=1e-5), k
    if extras:
        assert a.shading.net[-1].weight.abs().max() > 0  # it trained (zero at start)


def test_log_and_outputs(small_ws, tmp_path):
    cfg = tiny_cfg(iterations=4, log_every=2, preview_every=2)
    data = load_scene(small_ws, torch.device("cpu"))
    t = train(cfg, data, tmp_path)
    lines = [json.loads(x) for x in (tmp_path / "log.jsonl").read_text().splitlines()]
    assert [r["step"] for r in lines] == [2, 4]
    for key in ("seconds", "loss", "psnr", "rgb", "freespace", "occupancy", "carve", "rays_per_s"):
        assert key in lines[-1]
    assert (tmp_path / "preview_000002.png").exists() and (tmp_path / "preview_final.png").exists()
    model, scale, _ = load_model(tmp_path / "final.pt", torch.device("cpu"))
    p = torch.zeros(4, 3)
    assert torch.allclose(model.occupancy(p), t.model.occupancy(p))


class _RunsCode:
    """Unpickled, it creates ``marker``: what a hostile model file could do with code of its own."""

    def __init__(self, marker):
        self.marker = marker

    def __reduce__(self):
        return (Path.touch, (self.marker,))


def test_damaged_saves_are_a_value_error_naming_the_file(small_ws, tmp_path):
    """final.pt or checkpoint.pt cut short (a full disk, a copy), empty, another program's or another version's:
    a ValueError naming the file (not torch's "failed finding central directory", EOFError, KeyError or TypeError),
    and a damaged checkpoint leaves the trainer as it was."""
    cfg = tiny_cfg(iterations=4, checkpoint_every=2)
    data = load_scene(small_ws, torch.device("cpu"))
    train(cfg, data, tmp_path)
    final, ck = tmp_path / "final.pt", tmp_path / "checkpoint.pt"
    saved = torch.load(final, weights_only=False)
    newer = {**saved, "field_config": {**saved["field_config"], "a_later_knob": 1}}
    cut = final.read_bytes()[:1000]
    damages = {"cut": lambda p: p.write_bytes(cut), "empty": lambda p: p.write_bytes(b""),
               "list": lambda p: torch.save([1, 2], p), "no-config": lambda p: torch.save({"field": {}}, p),
               "newer": lambda p: torch.save(newer, p)}
    for name, damage in damages.items():
        bad = tmp_path / f"final-{name}.pt"
        damage(bad)
        with pytest.raises(ValueError, match=f"final-{name}.pt"):
            load_model(bad, torch.device("cpu"))
    marker = tmp_path / "ran"
    torch.save({**saved, "field_config": _RunsCode(marker)}, tmp_path / "final-code.pt")  # a file from elsewhere
    with pytest.raises(ValueError, match="final-code.pt: damaged or not saved by this trainer"):
        load_model(tmp_path / "final-code.pt", torch.device("cpu"))
    assert not marker.exists()  # read with weights_only: unpickling it ran nothing
    ck.write_bytes(ck.read_bytes()[:1000])
    t = Trainer(cfg, data, tmp_path)
    before = {k: v.clone() for k, v in t.model.state_dict().items()}
    with pytest.raises(ValueError, match="checkpoint.pt"):
        t.try_resume()
    assert t.step == 0 and all(torch.equal(v, t.model.state_dict()[k]) for k, v in before.items())


def test_losses_are_means_not_sums():
    x = torch.randn(100)
    big = x.repeat(10)
    assert torch.allclose(L.freespace_loss(x), L.freespace_loss(big))
    assert torch.allclose(L.depth_loss(x, x * 0), L.depth_loss(big, big * 0))


def test_rgb_loss_is_censored_at_over_exposed_channels():
    """A clipped photo channel (≥ clipped_level) only says "at least this bright": a brighter prediction costs
    nothing and gets no gradient there, a darker one costs its plain L1; unclipped channels are plain L1."""
    target = torch.tensor([[1.0, 1.0, 0.5], [1.0, 0.3, 0.2]])
    pred = torch.tensor([[1.25, 0.9, 0.6], [1.1, 0.3, 0.2]], requires_grad=True)
    loss = L.rgb_loss(pred, target, clipped_level=0.98)
    loss.backward()
    # row 0: 0 (brighter than clipped) + 0.1 (darker than clipped) + 0.1 (unclipped); row 1: 0
    assert torch.isclose(loss, torch.tensor((0.0 + 0.1 + 0.1) / 3 / 2))
    assert pred.grad[0, 0] == 0 and pred.grad[1, 0] == 0  # brighter than a clipped channel: free
    assert pred.grad[0, 1] < 0 and pred.grad[0, 2] > 0
    plain = L.rgb_loss(pred.detach(), target)  # off by default: the brighter predictions cost
    assert torch.isclose(plain, torch.tensor((0.25 + 0.1 + 0.1 + 0.1) / 3 / 2))


def test_sampler_boundary_oversampling(small_ws):
    data = load_scene(small_ws, torch.device("cpu"))
    s = RaySampler(data, boundary_fraction=1.0, generator=torch.Generator().manual_seed(0))
    o, d, rgb, m, view = s.sample(512)
    assert o.shape == (512, 3) and rgb.shape == (512, 3) and m.shape == (512,) and view.shape == (512,)
    assert view.dtype == torch.long and 0 <= view.min() and view.max() < data.images.shape[0]
    assert torch.allclose(d.norm(dim=-1), torch.ones(512))
    frac = m.mean().item()  # rays in the band straddle the boundary: both classes present
    assert 0.1 < frac < 0.9


def test_coarse_to_fine_upsamples_and_resume_across_it(small_ws, tmp_path):
    """The occupancy grid starts coarse, is upsampled at upsample_at; a run killed after the upsampling resumes
    into the fine grid and ends where an uninterrupted run ends."""
    from dvr.config import FieldConfig

    cfg = tiny_cfg(iterations=8, checkpoint_every=2, coarse_res=16, upsample_at=0.5,
                   field=FieldConfig(base_res=32, plane_res=(16, 32), hidden=16))
    data = load_scene(small_ws, torch.device("cpu"))
    t = Trainer(cfg, data, tmp_path / "probe")
    assert t.model.base.shape[-1] == 17
    a = train(cfg, data, tmp_path / "a")
    assert a.model.base.shape[-1] == 33
    train(cfg, data, tmp_path / "b", stop_after=6)  # checkpoint at step 6, after the upsampling at step 4
    b = Trainer(cfg, data, tmp_path / "b")
    assert b.model.base.shape[-1] == 17 and b.try_resume() and b.step == 6 and b.model.base.shape[-1] == 33
    b.fit()
    for (k, va), vb in zip(a.model.state_dict().items(), b.model.state_dict().values()):
        assert torch.allclose(va, vb, atol=1e-5), k
    t = Trainer(tiny_cfg(coarse_res=64), data, tmp_path / "c")  # not below base_res: one resolution
    assert t.upsample_step is None and t.model.base.shape[-1] == 33


def test_upsampling_keeps_the_function():
    """Upsampling the logit grid keeps the field: exactly on the old lattice, closely between."""
    from dvr.config import FieldConfig
    from dvr.fields import GridField

    f = GridField(FieldConfig(base_res=8, plane_res=(8,), hidden=8))
    with torch.no_grad():
        f.base.copy_(torch.randn_like(f.base))
    lattice = torch.stack(torch.meshgrid(*[torch.linspace(-1, 1, 9)] * 3, indexing="ij"), -1).view(-1, 3)
    p = torch.rand(2000, 3) * 2 - 1
    before_l, before_p = f.occupancy(lattice), f.occupancy(p)
    old, new = f.resize_base(16)
    assert new is f.base and old is not new and f.base.shape[-1] == 17
    assert torch.allclose(f.occupancy(lattice), before_l, atol=1e-5)
    assert (f.occupancy(p) - before_p).abs().mean() < 0.2 * before_p.abs().mean()


def test_fitted_frame_is_saved_and_consistent(small_ws, tmp_path):
    """Training in the hull's tighter sphere: final.pt's scale_mat = cameras' scale_mat · frame, and the field
    sits where the object is (the GT torus surface has logits near 0 through that frame)."""
    import numpy as np
    import trimesh


    cfg = tiny_cfg(iterations=2, carve_min_views=1)  # 8 views of 64 px: the two-view hull nearly fills the sphere
    data = load_scene(small_ws, torch.device("cpu"))
    t = train(cfg, data, tmp_path)
    _, scale, frame = load_model(tmp_path / "final.pt", torch.device("cpu"))
    assert frame[0, 0] < 0.95  # the torus (radius 0.7) does not fill the unit sphere: a tighter frame
    assert np.allclose(scale, data.cams.scale_mat @ frame)
    assert np.allclose(t.data.cams.P[0] / np.linalg.norm(t.data.cams.P[0]),
                       (data.cams.P[0] @ frame) / np.linalg.norm(data.cams.P[0] @ frame))
    gt = trimesh.load(small_ws / "gt" / "mesh.ply")
    v = np.asarray(gt.vertices)
    v_f = (v - scale[:3, 3]) / scale[0, 0]
    assert np.abs(v_f).max() < 1.0  # the whole object is inside the working sphere


def test_one_mask_cannot_push_the_contact_band_free(small_ws, tmp_path):
    """Within ``contact_band`` above the support plane a mask-background ray's surface point is pushed free only
    when two views' masks carve it (one automatic mask missing the contact strip cut the bottom off a book) — or one
    mask that puts it deep in its background (``carve_sure_depth``, off by default)."""
    from dataclasses import replace

    import numpy as np

    data = load_scene(small_ws, torch.device("cpu"))
    t = Trainer(tiny_cfg(iterations=1, carve_sure_depth=0.0), data, tmp_path)
    t.data.masks[:] = 1.0
    t.data.masks[0] = 0.0  # view 0 alone calls everything background
    t.data.cams = replace(t.data.cams, ground=np.array([0.0, 0.0, 1.0, 0.3]))  # z = −0.3
    pts = torch.tensor([[0.0, 0.0, -0.28], [0.0, 0.0, 0.3]])  # in the band; well above it
    assert t.contact_doubt(pts).tolist() == [True, False]
    t.data.masks[1] = 0.0  # a second view agrees: free
    assert t.contact_doubt(pts).tolist() == [False, False]
    t.cfg.contact_band = 0.0
    t.data.masks[1] = 1.0
    assert t.contact_doubt(pts).tolist() == [False, False]  # no band: one view is enough
    data.masks[:] = 1.0
    data.masks[0] = 0.0
    data.cams = replace(data.cams, ground=np.array([0.0, 0.0, 1.0, 0.3]))
    sure = Trainer(tiny_cfg(iterations=1, fit_frame=False, carve_sure_depth=0.01), data, tmp_path / "sure")
    assert sure.contact_doubt(pts).tolist() == [False, False]  # view 0 has no object pixel: sure background


def test_loss_terms_are_named_after_their_weights(small_ws, tmp_path):
    """Every loss term is logged (unweighted) under the name of its LossWeights field, and the total is
    Σ weight × term."""
    from dataclasses import fields

    from dvr.config import LossWeights

    cfg = tiny_cfg(iterations=1, appearance="on", view_shading=True,
                   weights=LossWeights(tv=0.5, normal=0.3, appearance=2.0, shading=0.7))
    t = Trainer(cfg, load_scene(small_ws, torch.device("cpu")), tmp_path)
    total, stats = t.losses(0)
    names = {f.name for f in fields(LossWeights)}
    terms = {k: v for k, v in stats.items() if k in names}
    assert set(terms) == names  # all of them here: hits exist, appearance and view shading are on
    assert set(stats) - names == {"psnr", "hit_frac"}
    assert torch.allclose(total.detach(), sum(getattr(cfg.weights, k) * v for k, v in terms.items()))


def test_render_batch_fields(small_ws, tmp_path):
    cfg = tiny_cfg(iterations=1)
    t = Trainer(cfg, load_scene(small_ws, torch.device("cpu")), tmp_path)
    b = t.render_batch(0)
    n = cfg.batch_rays
    assert b.origins.shape == b.dirs.shape == (n, 3) and b.in_mask.shape == b.hit.shape == (n,)
    assert torch.equal(b.hit, b.surface.hit) and b.surface_points.shape == (int(b.hit.sum()), 3)
    assert b.rendered_rgb.shape == b.observed_rgb.shape == (int((b.hit & b.in_mask).sum()), 3)
    assert b.surface_points.requires_grad and b.rendered_rgb.requires_grad


def test_mlp_field_trains_at_one_resolution(small_ws, tmp_path):
    """coarse_res below base_res asks for coarse to fine, which a field without ``supports_resize`` ignores."""
    from dvr.config import FieldConfig

    cfg = tiny_cfg(iterations=2, coarse_res=16, field=FieldConfig(kind="mlp", hidden=16, mlp_layers=1))
    t = train(cfg, load_scene(small_ws, torch.device("cpu")), tmp_path)
    assert not t.coarse and t.upsample_step is None and t.step == 2


def test_training_time_counts_its_setup_and_a_resume_adds_its_own(small_ws, tmp_path):
    """What training took, as the train stage reports it, includes the initial occupancy (the visual hull; the
    photo hull's carving), which the steps' time alone hid; a resumed run adds its own setup to the checkpoint's."""
    import torch as _torch

    cfg = tiny_cfg(iterations=4, checkpoint_every=2)
    data = load_scene(small_ws, _torch.device("cpu"))
    fresh = Trainer(cfg, data, tmp_path / "a")
    assert fresh.setup_seconds > 0 and fresh.elapsed == fresh.setup_seconds
    train(cfg, data, tmp_path / "b", stop_after=2)
    saved = _torch.load(tmp_path / "b" / "checkpoint.pt", weights_only=False)["elapsed"]
    resumed = Trainer(cfg, data, tmp_path / "b")
    assert resumed.try_resume()
    assert resumed.elapsed == pytest.approx(saved + resumed.setup_seconds)


def test_the_hull_needs_two_masks_to_carve_and_one_photo_alone_still_carves(small_ws):
    """``carve_min_views`` (2 by default): a point one mask alone calls background stays in the initial hull; a
    scene of one photo is carved by that photo (the rule asks for no more views than there are). The sure-background
    rule off (``carve_sure_depth`` 0): view 0's mask without object pixels would carve all it sees."""
    from types import SimpleNamespace

    from dvr.trainer import initial_inside

    data = load_scene(small_ws, torch.device("cpu"))
    cfg = tiny_cfg(photo_hull=False, carve_sure_depth=0.0)
    assert cfg.carve_min_views == 2
    masks = torch.ones_like(data.masks)
    masks[0] = 0.0  # view 0 alone calls everything background
    two = SimpleNamespace(P=data.P, masks=masks, images=data.images, sizes=None, cams=SimpleNamespace(ground=None))
    kept, _ = initial_inside(cfg, two)
    one = SimpleNamespace(P=data.P[:1], masks=masks[:1], images=data.images[:1], sizes=None,
                          cams=SimpleNamespace(ground=None))
    alone, _ = initial_inside(cfg, one)
    assert kept.sum() > 0.4 * kept.size  # the unit sphere's lattice points (≈ 52 %), less what no view sees
    assert alone.sum() == 0


def test_sparse_views_let_one_mask_carve_in_the_hull_and_the_carving_term(small_ws, tmp_path):
    """``carve_sparse_views``: where fewer views than it see a point, one mask carves it — in the initial hull and in
    the carving term (:meth:`Trainer.carved`) alike. With more than the scene's 8 views every point is sparsely seen,
    so view 0's all-background mask carves everything it sees (all but the points behind it or outside its frame); at
    the default (5) the two-mask rule holds (the sure-background rule off, ``carve_sure_depth`` 0: view 0's mask
    without object pixels would carve all it sees)."""
    from dvr.trainer import initial_inside

    data = load_scene(small_ws, torch.device("cpu"))
    data.masks[:] = 1.0
    data.masks[0] = 0.0  # view 0 alone calls everything background
    centre = torch.zeros(1, 3)
    default = tiny_cfg(photo_hull=False, carve_sure_depth=0.0)
    assert default.carve_sparse_views == 5 < data.P.shape[0]
    kept = initial_inside(default, data)[0]
    assert Trainer(default, data, tmp_path / "two").carved(centre).tolist() == [False]
    sparse = tiny_cfg(photo_hull=False, carve_sure_depth=0.0, carve_sparse_views=data.P.shape[0] + 1)
    cut = initial_inside(sparse, data)[0]
    assert cut.sum() < 0.1 * kept.sum()  # what is left, view 0 does not see
    assert Trainer(sparse, data, tmp_path / "one").carved(centre).tolist() == [True]


def test_framing_empties_what_too_few_photos_frame_in_the_hull_and_the_carving_term(small_ws, tmp_path):
    """``framing``: with every mask all object (each reaching its frame's edge), "off" keeps the sphere's points that
    only a few of the 8 views frame; "on" with all 8 asked for keeps fewer, the centre among them, and carves the
    others in the carving term too; asking for more than there are asks for all 8. "auto" is "on" here (every
    mask reaches the edge) and "off" with the scene's own masks (the torus inside every frame)."""
    from dvr.trainer import framing_views, initial_inside

    data = load_scene(small_ws, torch.device("cpu"))
    assert framing_views(tiny_cfg(), data) == (1, 0)  # the scene's masks: auto is off
    data.masks[:] = 1.0
    centre = torch.zeros(1, 3)
    cfg = dict(photo_hull=False, carve_sure_depth=0.0)
    off = tiny_cfg(framing="off", **cfg)
    kept = initial_inside(off, data)[0]
    all_8 = tiny_cfg(framing="on", min_framing_views=8, **cfg)
    framed_by_all = initial_inside(all_8, data)[0]
    assert 0 < framed_by_all.sum() < kept.sum()
    assert np.array_equal(initial_inside(tiny_cfg(framing="on", min_framing_views=9, **cfg), data)[0], framed_by_all)
    assert framing_views(tiny_cfg(**cfg), data) == (5, 8)  # auto, every mask cut by its frame
    assert np.array_equal(initial_inside(tiny_cfg(**cfg), data)[0],
                          initial_inside(tiny_cfg(framing="on", min_framing_views=5, **cfg), data)[0])
    few = torch.from_numpy(np.flatnonzero((kept & ~framed_by_all).ravel())[:50])
    points = grid_points(off.hull_res)[few]  # in the hull with the rule off, framed by fewer than all 8
    assert Trainer(all_8, data, tmp_path / "eight").carved(torch.cat([centre, points])).tolist() == \
        [False] + [True] * len(few)
    assert not Trainer(off, data, tmp_path / "off").carved(points).any()


def test_sure_background_lets_one_mask_carve_in_the_hull_and_the_carving_term(small_ws, tmp_path):
    """``carve_sure_depth`` (a fraction of the image's diagonal; off by default): one view's mask carves a point it
    puts farther than that into its background, in the initial hull and in the carving term alike. View 0's object
    is a band at the left edge of its 64 px: the centre, about 22 px away from it, goes at 0.01 (0.9 px) and stays
    under the two-mask rule alone (0, the default) and at 0.3 of the diagonal (27 px)."""
    from dvr.trainer import initial_inside

    data = load_scene(small_ws, torch.device("cpu"))
    data.masks[:] = 1.0
    data.masks[0, :, 11:] = 0.0
    centre = torch.zeros(1, 3)
    off, sure, far = tiny_cfg(photo_hull=False), tiny_cfg(photo_hull=False, carve_sure_depth=0.01), \
        tiny_cfg(photo_hull=False, carve_sure_depth=0.3)
    assert off.carve_sure_depth == 0
    assert initial_inside(sure, data)[0].sum() < 0.5 * initial_inside(off, data)[0].sum()
    assert Trainer(sure, data, tmp_path / "sure").carved(centre).tolist() == [True]
    assert Trainer(off, data, tmp_path / "off").carved(centre).tolist() == [False]
    assert Trainer(far, data, tmp_path / "far").carved(centre).tolist() == [False]


def test_sparse_views_reach_the_training_frame(small_ws):
    """``carve_sparse_views`` also decides the training frame (:func:`training_frame`, the hull's bounding sphere):
    every view's mask is a disc in its centre, small in views 0 and 2 (a quarter turn apart). Under the two-mask rule
    what only one of those two calls background stays, their two cones' union reaches the sphere and the frame stays;
    where one mask may carve (more sparse views than the scene's 8) the hull is about the cones' intersection and the
    frame tightens around it (the sure-background rule off, ``carve_sure_depth`` 0: it would carve the discs' far
    background too)."""
    from dvr.trainer import training_frame

    data = load_scene(small_ws, torch.device("cpu"))
    _, H, W = data.masks.shape
    v, u = torch.meshgrid(torch.arange(H) + 0.5, torch.arange(W) + 0.5, indexing="ij")

    def disc(radius: float) -> torch.Tensor:
        return (((u - W / 2) ** 2 + (v - H / 2) ** 2) < (radius * W) ** 2).float()

    data.masks[:] = disc(0.35)
    data.masks[[0, 2]] = disc(0.15)
    assert training_frame(tiny_cfg(carve_sure_depth=0.0), data) is data
    framed = training_frame(tiny_cfg(carve_sure_depth=0.0, carve_sparse_views=data.P.shape[0] + 1), data)
    radius = framed.cams.scale_mat[0, 0] / data.cams.scale_mat[0, 0]
    assert framed is not data and radius < 0.8


def test_the_train_stage_says_and_records_its_framing_choice(small_ws, capsys):
    """pipeline.train.stage.report_framing: off on the scene's own masks (the torus inside every frame), on with 5 views
    when every mask reaches its frame's edge, as the stamp records it."""
    from pipeline.train.stage import report_framing

    data = load_scene(small_ws, torch.device("cpu"))
    cfg = tiny_cfg()
    assert report_framing(cfg, data) == {"framing": "off", "min_framing_views": 1, "cut_views": 0, "auto": True}
    assert "every framed point may be object (auto: the object reaches the frame's edge in 0 of 8" in \
        capsys.readouterr().out
    data.masks[:] = 1.0
    assert report_framing(cfg, data) == {"framing": "on", "min_framing_views": 5, "cut_views": 8, "auto": True}
    assert "5 photos must frame a point to be object (auto: the object reaches the frame's edge in 8 of 8 photos, " \
        "more than 50 %)" in capsys.readouterr().out


def test_a_resumed_log_keeps_its_steps_once_and_no_line_cut_short(small_ws, tmp_path):
    """A kill after the checkpoint of step 2 but after the log's line of step 3, in the middle of writing step 4's:
    the resumed run logs steps 3 and 4 again; its log holds each step once and no line the kill cut short (the
    report's curves read it)."""
    cfg = tiny_cfg(iterations=4, checkpoint_every=2, log_every=1)
    data = load_scene(small_ws, torch.device("cpu"))
    train(cfg, data, tmp_path, stop_after=3)
    log = tmp_path / "log.jsonl"
    log.write_text(log.read_text() + '{"step": 4, "loss": 0.')
    t = Trainer(cfg, data, tmp_path)
    assert t.try_resume() and t.step == 2
    t.fit()
    assert [json.loads(x)["step"] for x in log.read_text().splitlines()] == [1, 2, 3, 4]


def test_hull_gate_px_lets_the_occupancy_term_reach_the_silhouettes(small_ws, tmp_path):
    """The hull gate with the masks as they are holds back points on the true surface (the views' silhouettes meet
    it within a pixel, and bilinear lookups there read under 0.5) and most of those half a pixel outside, which
    shrinks the object; with the masks widened by ``hull_gate_px`` 2 it lets those through and still holds back
    points ten pixels outside (0.3 at 64 px from 2.6 away: a pixel is about 0.03)."""
    import trimesh

    data = load_scene(small_ws, torch.device("cpu"))
    mesh = trimesh.load(small_ws / "gt" / "mesh.ply")
    v, n = np.asarray(mesh.vertices), np.asarray(mesh.vertex_normals)

    def gated(px: float, offset: float) -> float:
        t = Trainer(tiny_cfg(fit_frame=False, hull_gate_px=px), data, tmp_path / f"{px}")
        return float(t.gated(torch.from_numpy(v + offset * n).float()).float().mean())

    assert gated(0.0, 0.0) > 0.05 and gated(0.0, 0.015) > 0.3
    assert gated(2.0, 0.0) == 0.0 and gated(2.0, 0.015) == 0.0
    assert gated(0.0, 0.3) > 0.8 and gated(2.0, 0.3) > 0.8


def test_a_gpu_trains_fewer_larger_steps_and_the_cpu_the_options_own():
    """device_schedule: on a GPU, gpu_batch_scale times the rays and points a step in as many times fewer steps
    (rounded up), the learning rates × √scale, checkpoints, log lines and previews as many times fewer steps apart;
    on the CPU, or with a scale of 1, the options themselves."""
    cfg = tiny_cfg(iterations=1001, batch_rays=2048, depth_rays=256, carve_points=4096, lr_grid=0.04, lr_mlp=0.004,
                   lr_appearance=0.01, checkpoint_every=250, log_every=2, preview_every=0, gpu_batch_scale=4)
    assert device_schedule(cfg, torch.device("cpu")) is cfg
    assert device_schedule(replace(cfg, gpu_batch_scale=1), torch.device("cuda")).iterations == 1001
    gpu = device_schedule(cfg, torch.device("cuda"))
    assert (gpu.iterations, gpu.batch_rays, gpu.depth_rays, gpu.carve_points) == (251, 8192, 1024, 16384)
    assert (gpu.lr_grid, gpu.lr_mlp, gpu.lr_appearance) == pytest.approx((0.08, 0.008, 0.02))
    assert (gpu.checkpoint_every, gpu.log_every, gpu.preview_every) == (62, 1, 0)
    assert (cfg.iterations, cfg.batch_rays, cfg.lr_grid) == (1001, 2048, 0.04)  # the options are left as they were


def test_a_checkpoint_of_other_steps_is_not_resumed(small_ws, tmp_path):
    """A checkpoint written under another step count (another device's schedule, :func:`device_schedule`) is a
    ValueError naming it, with the trainer untouched (the train stage then starts afresh, as for a damaged one)."""
    data = load_scene(small_ws, torch.device("cpu"))
    train(tiny_cfg(iterations=8, checkpoint_every=4), data, tmp_path, stop_after=4)
    t = Trainer(tiny_cfg(iterations=2, checkpoint_every=4), data, tmp_path)
    with pytest.raises(ValueError, match=r"checkpoint.pt: a checkpoint of 8 steps, where this run trains 2 "
                                         r"\(another device's schedule\)"):
        t.try_resume()
    assert t.step == 0


def test_the_train_stage_says_when_the_device_trains_other_steps(capsys):
    """report_schedule: a line naming the steps the GPU trains and the option that sets them; nothing on the CPU."""
    from pipeline.train.stage import report_schedule

    cfg = tiny_cfg(iterations=1000, batch_rays=2048, gpu_batch_scale=4)
    report_schedule(cfg, device_schedule(cfg, torch.device("cpu")), torch.device("cpu"))
    assert capsys.readouterr().out == ""
    report_schedule(cfg, device_schedule(cfg, torch.device("cuda")), torch.device("cuda"))
    assert capsys.readouterr().out == ("train: on cuda, 250 steps of 8192 rays (--train.gpu-batch-scale 4; 1 trains "
                                       "1000 steps of 2048)\n")
