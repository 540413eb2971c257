"""bench/arms.py: the pair's saved mapping holds no object matches (each arm runs them) and is mapped from the photos
as the arms get them (JPEGs where the overrides say so); each command reads its own options."""

import json
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

import bench.arms as arms  # noqa: E402


def _stubbed(tmp_path, monkeypatch):
    """The pairs' folders under tmp_path; rendering, photo folders and stages recorded instead of run."""
    calls = []
    monkeypatch.setattr(arms, "PAIRS", tmp_path / "pairs")
    monkeypatch.setattr(arms.ev, "scene", lambda name, over: tmp_path / "scenes" / f"{name}{len(over)}")

    def photos_folder(syn, out, jpeg_quality=None):
        calls.append(("photos", syn.name, jpeg_quality))
        return out

    def stages(names, ws, cfg, **sources):
        calls.append(("stages", names, cfg.cameras.object_matches))
        (ws / "sfm" / "sparse" / "best").mkdir(parents=True)

    monkeypatch.setattr(arms.ev, "photos_folder", photos_folder)
    monkeypatch.setattr(arms.ev, "stages", stages)
    return calls


def _stamp(mapping: Path, note):
    (mapping / ".stages").mkdir(parents=True, exist_ok=True)
    (mapping / ".stages" / "cameras.json").write_text(json.dumps({"rung": "default", "object_matches": note}))


def test_the_mapping_is_made_without_object_matches_from_the_arms_jpegs(tmp_path, monkeypatch):
    calls = _stubbed(tmp_path, monkeypatch)
    over = {"cameras": {"photo_scale": 3}, "photos_jpeg": 92}
    mapping = arms.map_once("cow", over)
    assert mapping == tmp_path / "pairs" / "cow1-jpeg92" / "mapping"  # the scene rendered without photos_jpeg
    assert calls == [("photos", "cow1", 92), ("stages", ("cameras",), False)]


def test_a_saved_mapping_is_kept_unless_it_holds_the_object_matches(tmp_path, monkeypatch):
    calls = _stubbed(tmp_path, monkeypatch)
    mapping = arms.map_once("cow", {})
    _stamp(mapping, None)
    assert arms.map_once("cow", {}) == mapping and len(calls) == 2  # kept: nothing mapped again
    _stamp(mapping, "15 sparse points for the object's sphere ...: 73")  # a mapping that holds them
    arms.map_once("cow", {})
    assert calls[2:] == [("photos", "cow0", None), ("stages", ("cameras",), False)]


def test_each_command_takes_its_own_options(tmp_path, monkeypatch):
    """``gt`` and ``dtu`` pass any stage's options on to the run; ``pair`` takes only its own; no command, no run."""
    runs = []
    monkeypatch.setattr(arms.ev, "RUNS", tmp_path)
    monkeypatch.setattr(arms.ev, "run_synthetic", lambda spec, work, knobs: runs.append((spec, knobs)) or {})
    monkeypatch.setattr(arms.ev, "run_dtu", lambda spec, work, knobs: runs.append((spec, knobs)) or
                        dict.fromkeys(("psnr", "psnr_train", "psnr_gain_fit", "psnr_train_gain_fit", "psnr_on_model",
                                       "psnr_reaimed", "reaim_deg", "pose", "seconds", "rung")))
    arms.main(["gt", "cow", "--preset", "balanced", "--train.seed", "1"])
    assert runs[-1] == ({"scene": "cow", "cameras": "gt", "preset": "balanced", "knob": "arm"},
                        {"arm": (["--train.seed", "1"], {})})
    arms.main(["dtu", "--cameras.seed", "2"])
    assert runs[-1] == ({"knob": "arm", "preset": "default", "reference_cameras": False},
                        {"arm": (["--cameras.seed", "2"], {})})
    for argv in (["pair", "cow", "--train.seed", "1"], ["carves"], []):
        with pytest.raises(SystemExit):
            arms.main(argv)
    assert len(runs) == 2


def test_real_trains_each_arm_on_the_bench_workspace_without_its_held_out_photos(tmp_path, monkeypatch, capsys):
    """``real``: every arm trained on the bench row's workspace less every 7th photo, with its own options; without
    that workspace one line says how to make it."""
    monkeypatch.setattr(arms.ev, "RUNS", tmp_path)
    with pytest.raises(SystemExit, match="python bench/run.py --only mouse"):
        arms.main(["real", "mouse"])
    full = tmp_path / "real_mouse"
    (full / ".stages").mkdir(parents=True)
    (full / ".stages" / "depth.json").write_text("{}")
    (full / "images").mkdir()
    for i in range(9):
        (full / "images" / f"{i:02d}.png").write_bytes(b"")
    subsets, trained = [], []
    monkeypatch.setattr(arms.ev, "subset_workspace", lambda src, ws, keep: subsets.append(list(keep)))
    monkeypatch.setattr(arms.ev, "train_mesh_texture", lambda ws, preset, options: trained.append((preset, options)))
    monkeypatch.setattr(arms.ev, "photo_scores", lambda full, ws, paths, held, hand=None: {**dict.fromkeys(
        ("psnr", "psnr_gain_fit", "psnr_reaimed", "psnr_train", "mask_covered"), float(len(held))),
        **({"psnr_hand": 7.0} if hand is not None else {})})
    monkeypatch.setattr(arms.ev, "REAL", {"mouse": tmp_path / "photos"})  # a capture without hand masks
    arms.main(["real", "mouse", "--arm=", "--arm=--train.hull-gate-px 0"])
    assert subsets == [[1, 2, 3, 4, 5, 6, 8]] * 2
    assert trained == [("default", []), ("default", ["--train.hull-gate-px", "0"])]
    out = capsys.readouterr().out
    assert "psnr 2.0000" in out and "psnr_hand" not in out
    # with hand masks the held-out photos are scored over them too
    (tmp_path / "photos" / "masks").mkdir(parents=True)
    undistorted = []
    monkeypatch.setattr(arms.ev, "undistorted_hand_masks", lambda full, hand: undistorted.append(hand) or hand)
    arms.main(["real", "mouse", "--arm="])
    assert undistorted == [tmp_path / "photos" / "masks"]
    assert "psnr_hand 7.0000" in capsys.readouterr().out


def test_masks_runs_each_arm_on_the_bench_rows_cameras(tmp_path, monkeypatch, capsys):
    """``masks``: each arm's masks stage on a copy of the bench row's photos and cameras with its own options, scored
    against the hand masks; without the row one line says how to make it; a capture without hand masks is no
    choice."""
    monkeypatch.setattr(arms.ev, "RUNS", tmp_path)
    photos = tmp_path / "photos"
    (photos / "masks").mkdir(parents=True)
    monkeypatch.setattr(arms.ev, "REAL", {"blowtorch": photos, "mouse": tmp_path / "none"})
    with pytest.raises(SystemExit, match="python bench/run.py --only blowtorch"):
        arms.main(["masks", "blowtorch"])
    with pytest.raises(SystemExit):
        arms.main(["masks", "mouse"])
    full = tmp_path / "real_blowtorch"
    (full / ".stages").mkdir(parents=True)
    (full / ".stages" / "cameras.json").write_text("{}")
    (full / "images").mkdir()
    (full / "images" / "a.png").write_bytes(b"x")
    (full / "cameras.npz").write_bytes(b"y")
    runs = []

    def stages(names, ws, cfg):
        runs.append((names, cfg.masks.carve_fraction, sorted(p.name for p in ws.iterdir())))
        (ws / ".stages" / "masks.json").write_text('{"seconds": 3.5}')

    monkeypatch.setattr(arms.ev, "stages", stages)
    monkeypatch.setattr(arms.ev, "undistorted_hand_masks", lambda full, hand: hand)
    monkeypatch.setattr(arms.ev, "masks_iou", lambda ws, hand: 0.5 if hand == photos / "masks" else 0.0)
    arms.main(["masks", "blowtorch", "--arm=", "--arm=--masks.carve-fraction 0.07"])
    assert [r[:2] for r in runs] == [(("masks",), 0.0), (("masks",), 0.07)]
    assert runs[0][2] == [".stages", "cameras.npz", "images"]
    out = capsys.readouterr().out
    assert out.count("mask_iou 0.5000  seconds 3.5") == 2
