"""The pipeline API (pipeline/stages.py): the bookkeeping run_stage owns, bad input, and reconstruct end to end."""

import json
import os
import shutil

import pytest

from pipeline import stages
from pipeline.config import Config
from pipeline.errors import StageError
from pipeline.mesh import stage as mesh
from pipeline.report import stage as report
from pipeline.stages import Stage, reconstruct, run_stage
from pipeline.workspace import Done, Workspace
from tests.conftest import tiny_training


def _counting_stage(calls: list, name="count"):
    """A stage of the table's shape that copies a file and counts its runs."""

    def body(job):
        calls.append(job.config_hash)
        (job.ws.root / "out.txt").write_text((job.ws.root / "in.txt").read_text())
        return Done({"chars": len((job.ws.root / "out.txt").read_text())})

    return Stage(name, "copy in.txt to out.txt", body, None,
                 requires=lambda ws: [(ws.root / "in.txt", "make-input")],
                 inputs=lambda ws, src: [ws.root / "in.txt"], outputs=lambda ws: [ws.root / "out.txt"])


def test_run_stage_skips_when_up_to_date_and_reruns_when_stale_or_forced(tmp_path, monkeypatch, capsys):
    calls = []
    monkeypatch.setattr(stages, "STAGES", (*stages.STAGES, _counting_stage(calls)))
    (tmp_path / "in.txt").write_text("abc")
    assert run_stage("count", tmp_path) is True
    stamp = Workspace(tmp_path).stamp("count")
    assert stamp["chars"] == 3 and stamp["seconds"] >= 0 and len(calls) == 1
    assert run_stage("count", tmp_path) is False and "count: up to date" in capsys.readouterr().out
    assert run_stage("count", tmp_path, force=True) is True and len(calls) == 2
    import os

    t = Workspace(tmp_path).stages / "count.json"
    os.utime(tmp_path / "in.txt", (t.stat().st_mtime + 5, t.stat().st_mtime + 5))  # a newer input: stale
    assert run_stage("count", tmp_path) is True and len(calls) == 3
    (tmp_path / "out.txt").unlink()  # a missing output: stale
    assert run_stage("count", tmp_path) is True and len(calls) == 4


def test_a_failing_rerun_removes_the_old_stamp(tmp_path, monkeypatch):
    """A stage that finished once and then fails when redone, having written part of its outputs, is not
    done: the later stages see it. One that fails before writing anything (bad input) stays done."""
    fail = []

    def body(job):
        if fail == ["before writing"]:
            raise StageError(f"{job.ws.root}: bad input")
        (job.ws.root / "x").write_text("half")
        if fail:
            raise StageError(f"{job.ws.root}: broken on purpose")
        return Done()

    flaky = Stage("flaky", "fails the second time", body, None, requires=lambda ws: [], inputs=lambda ws, src: [],
                  outputs=lambda ws: [ws.root / "x"])
    monkeypatch.setattr(stages, "STAGES", (*stages.STAGES, flaky))
    run_stage("flaky", tmp_path)
    done = Workspace(tmp_path).stamp("flaky")
    assert done is not None
    fail.append("before writing")
    with pytest.raises(StageError, match="bad input"):
        run_stage("flaky", tmp_path, force=True)
    assert Workspace(tmp_path).stamp("flaky") == done and not Workspace(tmp_path).unfinished("flaky")
    fail[0] = "after writing"
    with pytest.raises(StageError, match="broken on purpose"):
        run_stage("flaky", tmp_path, force=True)
    assert Workspace(tmp_path).stamp("flaky") is None and Workspace(tmp_path).unfinished("flaky")


def test_a_rewrite_within_the_file_systems_time_resolution_counts_as_a_change(tmp_path):
    """On FAT (2 s) or a coarse network share a failed run can rewrite an output and leave its time as it was: the
    run still changed it, so its stamp must not come back (size and inode tell, not the time alone)."""
    out = tmp_path / "x"
    out.write_text("whole output")
    ws = Workspace(tmp_path)
    ws.mark_done("flaky", "h", 1.0)
    before = ws.begin("flaky", [out])
    old = out.stat().st_mtime_ns
    out.write_text("half")  # in place, then the coarse clock's time
    os.utime(out, ns=(old, old))
    ws.undo_begin("flaky", [out], before)
    assert ws.stamp("flaky") is None and ws.unfinished("flaky")
    tmp = tmp_path / "x.tmp"  # the same length, written atomically (a new file renamed over it): a new inode
    tmp.write_text("half")
    ws.mark_done("flaky", "h", 1.0)
    before = ws.begin("flaky", [out])
    old = out.stat().st_mtime_ns
    os.replace(tmp, out)
    os.utime(out, ns=(old, old))
    ws.undo_begin("flaky", [out], before)
    assert ws.stamp("flaky") is None
    ws.mark_done("flaky", "h", 1.0)  # a run that touched nothing gets its stamp back
    before = ws.begin("flaky", [out, tmp_path / "missing"])
    ws.undo_begin("flaky", [out, tmp_path / "missing"], before)
    assert ws.stamp("flaky") is not None and not ws.unfinished("flaky")


def test_run_stage_names_the_missing_input_and_its_stage(tmp_path):
    with pytest.raises(StageError, match=r"final\.pt: missing; run the train stage first"):
        run_stage("mesh", tmp_path)
    with pytest.raises(ValueError, match="no such stage"):
        run_stage("paint", tmp_path)
    with pytest.raises(ValueError, match="takes no images"):
        run_stage("train", tmp_path, images=tmp_path)
    with pytest.raises(StageError, match="needs --images"):
        run_stage("cameras", tmp_path)
    with pytest.raises(StageError, match="no photos given and no cameras.npz"):
        reconstruct(None, tmp_path)


def test_reconstruct_does_not_ignore_given_cameras_without_photos(small_ws, tmp_path):
    """A workspace that holds images and cameras, and --given-cameras without --images: the cameras stage says what
    is missing instead of skipping the given file (and nothing is trained on the old cameras)."""
    ws = tmp_path / "ws"
    shutil.copytree(small_ws, ws)
    with pytest.raises(StageError, match="the cameras stage needs --images"):
        reconstruct(None, ws, given_cameras=ws / "cameras.npz")
    assert not (ws / ".stages" / "train.json").exists()


def test_stage_options_are_config_fields():
    cfg = Config()
    for stage in stages.STAGES:
        if stage.options is not None:
            assert isinstance(getattr(cfg, stage.name), stage.options)
    assert [s.name for s in stages.STAGES if s.options is None] == ["report"]


def test_reconstruct_a_synthetic_workspace_then_nothing_to_do(small_ws, tmp_path, capsys):
    """Without photos, reconstruct runs train → mesh → texture → report on a workspace made by synth; a second call
    redoes nothing but the report."""
    ws = tmp_path / "ws"
    shutil.copytree(small_ws, ws)
    cfg = tiny_training(Config(), iterations=30, batch_rays=256)
    cfg.mesh.resolution, cfg.mesh.max_faces, cfg.texture.size = 64, 3000, 128
    glb = reconstruct(None, ws, cfg)
    assert glb == (ws / "mesh" / "textured.glb").resolve() and glb.exists() and (ws / "report.html").exists()
    assert (ws / "mesh" / "textured.usdz").stat().st_size > 0
    done = {p.stem: json.loads(p.read_text())["finished"] for p in (ws / ".stages").glob("*.json")}
    assert set(done) == {"train", "mesh", "texture", "report"}  # no photos: cameras, masks, depth not run
    size = json.loads((ws / ".stages" / "texture.json").read_text())["object_size"]  # no board: a size, not in metres
    assert size["units"] == "arbitrary" and min(size["height"], size["width"], size["depth"]) > 0
    assert "the scale is arbitrary" in capsys.readouterr().out and "Size: the scale is arbitrary" in \
        (ws / "report.html").read_text()
    reconstruct(None, ws, cfg)
    out = capsys.readouterr().out
    assert all(f"{s}: up to date" in out for s in ("train", "mesh", "texture"))
    again = {p.stem: json.loads(p.read_text())["finished"] for p in (ws / ".stages").glob("*.json")}
    assert {k: v for k, v in again.items() if k != "report"} == {k: v for k, v in done.items() if k != "report"}


def test_damaged_model_files_are_one_line_or_start_afresh(small_ws, tmp_path, capsys):
    """model/final.pt cut short (a full disk, a copy): the mesh and texture stages say so in one line naming it and
    the fix (not torch's "PytorchStreamReader failed reading zip archive" traceback); a checkpoint cut short holds
    nothing to lose: training says so and starts afresh (not the same traceback on every rerun)."""
    ws = tmp_path / "ws"
    shutil.copytree(small_ws, ws)
    cfg = tiny_training(Config(), iterations=6, batch_rays=256)
    cfg.train.checkpoint_every, cfg.train.log_every = 3, 1
    run_stage("train", ws, cfg, stop_after=3)
    checkpoint = ws / "model" / "checkpoint.pt"
    checkpoint.write_bytes(checkpoint.read_bytes()[:1000])
    capsys.readouterr()
    assert run_stage("train", ws, cfg)
    said = capsys.readouterr().out
    assert "checkpoint.pt: damaged or not saved by this trainer (RuntimeError); starting afresh" in said
    logged = [json.loads(line)["step"] for line in (ws / "model" / "log.jsonl").read_text().splitlines()]
    assert logged == [1, 2, 3, 4, 5, 6]  # from the start, and the log of the lost steps gone with them
    cfg.mesh.resolution, cfg.mesh.max_faces, cfg.texture.size = 64, 3000, 128
    assert run_stage("mesh", ws, cfg)  # clean.ply for the texture stage
    final = ws / "model" / "final.pt"
    final.write_bytes(final.read_bytes()[:1000])
    for stage in ("texture", "mesh"):
        with pytest.raises(StageError, match=r"final.pt: damaged or not saved by this trainer \(RuntimeError\); "
                                             r"retrain \(train --force\)"):
            run_stage(stage, ws, cfg, force=True)


def test_a_training_that_cannot_start_keeps_the_model_it_had(small_ws, tmp_path):
    """Another config discards model/ (its checkpoint is not ours to resume), but a run of another config that stops
    before it starts (a mask gone) keeps it: the user is never left with neither model. A device this machine
    lacks stops it before the stage starts, naming the option."""
    ws = tmp_path / "ws"
    shutil.copytree(small_ws, ws)
    cfg = tiny_training(Config(), iterations=4, batch_rays=256)
    run_stage("train", ws, cfg)
    before = (ws / "model" / "final.pt").read_bytes()
    cfg.train.iterations = 5
    sorted((ws / "masks").glob("*.png"))[0].unlink()
    with pytest.raises(StageError, match="000000.png"):
        run_stage("train", ws, cfg)
    assert (ws / "model" / "final.pt").read_bytes() == before
    cfg.train.device = "tpu"
    with pytest.raises(ValueError, match="--train.device: device 'tpu' is not a torch device"):
        run_stage("train", ws, cfg)


def test_a_stage_that_did_not_finish_is_not_read_by_the_next(small_ws, tmp_path, monkeypatch):
    """A stage run that fails (or is stopped or killed) after writing part of its outputs leaves older or half
    written ones: ``texture`` after an interrupted ``mesh`` would bake the older clean.ply and, without the mesh
    stamp, read it in the default frame whatever frame it was written in. So its outputs are refused, naming the
    stage to run again, until it finishes. A run that fails before writing anything (bad input found first) leaves the
    workspace as it was: the stamp back, with its time, and nothing refused."""
    ws = tmp_path / "ws"
    shutil.copytree(small_ws, ws)
    cfg = tiny_training(Config(), iterations=4, batch_rays=256)
    cfg.mesh.resolution, cfg.mesh.max_faces, cfg.texture.size = 64, 3000, 128
    cfg.mesh.frame = "normalized"
    for stage in ("train", "mesh", "texture"):
        run_stage(stage, ws, cfg)
    assert not list((ws / ".stages").glob("*.unfinished"))

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt  # Ctrl-C after raw.ply was written, before clean.ply

    cfg.mesh.frame = "sfm"
    monkeypatch.setattr(mesh, "finished_mesh", interrupted)
    with pytest.raises(KeyboardInterrupt):
        run_stage("mesh", ws, cfg)
    monkeypatch.undo()
    assert (ws / "mesh" / "clean.ply").exists()  # the older mesh stays, for whoever wants it
    with pytest.raises(StageError, match=r"clean.ply: the mesh stage's last run did not finish .*; run the mesh "
                                         r"stage again"):
        run_stage("texture", ws, cfg, force=True)
    assert "last run did not finish" in report.build(Workspace(ws), tuple(st.name for st in stages.STAGES))
    run_stage("mesh", ws, cfg)
    assert run_stage("texture", ws, cfg)
    assert not (ws / ".stages" / "mesh.unfinished").exists()

    stamp = ws / ".stages" / "mesh.json"
    kept = stamp.read_bytes(), stamp.stat().st_mtime
    final = ws / "model" / "final.pt"
    trained = final.read_bytes()
    final.write_bytes(trained[:1000])  # this mesh run fails before it writes anything
    with pytest.raises(StageError, match="final.pt: damaged"):
        run_stage("mesh", ws, cfg, force=True)
    assert (stamp.read_bytes(), stamp.stat().st_mtime) == kept
    assert not (ws / ".stages" / "mesh.unfinished").exists()
    final.write_bytes(trained)
    assert run_stage("texture", ws, cfg, force=True)


@pytest.mark.parametrize("stage", ["depth", "masks"])
def test_half_written_sfm_model_is_one_line(small_ws, tmp_path, stage):
    """A cameras run killed while COLMAP wrote the undistorted model leaves its folder without its files; the
    stages that read it said pycolmap's "[reconstruction.cc:…] … files do not exist"."""
    ws = tmp_path / "ws"
    shutil.copytree(small_ws, ws)
    model = ws / "sfm" / "undistorted" / "sparse"
    model.mkdir(parents=True)
    with pytest.raises(StageError, match=r"sparse: unreadable SfM model \(\w+\); rerun the cameras stage"):
        run_stage(stage, ws)
