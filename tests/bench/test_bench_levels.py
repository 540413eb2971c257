"""bench/levels.py: the stages it times and the whole run it compares with."""

import json

from bench import levels


def test_the_whole_run_is_the_sum_of_the_stage_stamps(tmp_path):
    (tmp_path / ".stages").mkdir()
    for stage, seconds in (("cameras", 20.5), ("train", 30.0), ("texture", 9.5), ("report", 100.0)):
        (tmp_path / ".stages" / f"{stage}.json").write_text(json.dumps({"seconds": seconds}))
    assert levels.stamped_seconds(tmp_path) == 60.0  # the report is not a stage of the run's figure


def test_both_runs_remesh_and_retexture_the_copy_with_the_levels_asked(tmp_path, monkeypatch, capsys):
    ws = tmp_path / "ws"
    (ws / "mesh" / "levels" / "raw").mkdir(parents=True)
    (ws / "model").mkdir()
    (ws / "model" / "final.pt").write_bytes(b"model")
    calls = []
    monkeypatch.setattr(levels.subprocess, "run", lambda cmd, **kw: calls.append(cmd[3:]))
    levels.main([str(ws), "--levels", "preview,full", "--whole", "100"])
    assert [c[0] for c in calls] == ["mesh", "texture", "mesh", "texture"]
    assert calls[0][-2:] == ["--mesh.detail", ""] and calls[2][-2:] == ["--mesh.detail", "preview,full"]
    assert all(c[1] != str(ws) and c[2] == "--force" for c in calls)  # a copy, never the workspace itself
    out = capsys.readouterr().out
    assert "whole run of 100 s" in out and json.loads(out.splitlines()[-1])["whole"] == 100.0


def test_the_psnr_of_each_level_is_read_from_its_glb(tmp_path, monkeypatch, capsys):
    """--psnr: one figure per GLB (the default mesh's and each level's), from every 5th photo; no stage runs."""
    import numpy as np

    ws = tmp_path / "ws"
    (ws / "mesh" / "levels" / "preview").mkdir(parents=True)
    monkeypatch.setattr(levels.subprocess, "run", lambda *a, **k: (_ for _ in ()).throw(AssertionError("ran")))
    seen = []

    def fake_psnrs(path, every=5):
        seen.append((path, every))
        return {"default": 20.0, "preview": float(np.float64(19.5))}

    monkeypatch.setattr(levels, "level_psnrs", fake_psnrs)
    levels.main([str(ws), "--psnr"])
    assert seen == [(ws, 5)]
    assert json.loads(capsys.readouterr().out.splitlines()[-1]) == {"default": 20.0, "preview": 19.5}
