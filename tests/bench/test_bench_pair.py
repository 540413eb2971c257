"""bench/pair.py: the saved mapping holds no object matches (each arm runs them) and is mapped from the photos as
the arms get them (JPEGs where the overrides say so)."""

import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

import bench.pair as pair  # noqa: E402


def _stubbed(tmp_path, monkeypatch):
    """pair's folders under tmp_path; rendering, photo folders and stages recorded instead of run."""
    calls = []
    monkeypatch.setattr(pair, "PAIRS", tmp_path / "pairs")
    monkeypatch.setattr(pair.ev, "scene", lambda name, over: tmp_path / "scenes" / f"{name}{len(over)}")

    def photos_folder(syn, out, jpeg_quality=None):
        calls.append(("photos", syn.name, jpeg_quality))
        return out

    def stages(names, ws, cfg, **sources):
        calls.append(("stages", names, cfg.cameras.object_matches))
        (ws / "sfm" / "sparse" / "best").mkdir(parents=True)

    monkeypatch.setattr(pair.ev, "photos_folder", photos_folder)
    monkeypatch.setattr(pair.ev, "stages", stages)
    return calls


def _stamp(mapping: Path, note):
    (mapping / ".stages").mkdir(parents=True, exist_ok=True)
    (mapping / ".stages" / "cameras.json").write_text(json.dumps({"rung": "default", "object_matches": note}))


def test_the_mapping_is_made_without_object_matches_from_the_arms_jpegs(tmp_path, monkeypatch):
    calls = _stubbed(tmp_path, monkeypatch)
    over = {"cameras": {"photo_scale": 3}, "photos_jpeg": 92}
    mapping = pair.map_once("cow", over)
    assert mapping == tmp_path / "pairs" / "cow1-jpeg92" / "mapping"  # the scene rendered without photos_jpeg
    assert calls == [("photos", "cow1", 92), ("stages", ("cameras",), False)]


def test_a_saved_mapping_is_kept_unless_it_holds_the_object_matches(tmp_path, monkeypatch):
    calls = _stubbed(tmp_path, monkeypatch)
    mapping = pair.map_once("cow", {})
    _stamp(mapping, None)
    assert pair.map_once("cow", {}) == mapping and len(calls) == 2  # kept: nothing mapped again
    _stamp(mapping, "15 sparse points for the object's sphere ...: 73")  # mapped before the arms ran them
    pair.map_once("cow", {})
    assert calls[2:] == [("photos", "cow0", None), ("stages", ("cameras",), False)]
