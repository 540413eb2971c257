"""Detail levels (pipeline/mesh/levels.py): the names, and several levels written from one training."""

import json
import shutil

import pytest
import trimesh

from pipeline.config import Config
from pipeline.errors import StageError
from pipeline.mesh.levels import LEVELS, budget, parse_levels
from pipeline.stages import reconstruct, run_stage
from pipeline.texture.export import MAP_FILES, read_textured
from tests.conftest import tiny_training


def test_level_names_in_order_each_once():
    assert parse_levels("medium, preview,medium") == ["medium", "preview"]
    assert parse_levels("") == []
    assert [budget(n) for n in ("preview", "reduced", "medium", "full")] == [25_000, 50_000, 100_000, 250_000]
    assert budget("raw") > 10**9 and LEVELS["raw"] is None


def test_an_unknown_level_is_one_line_naming_the_option_and_the_levels():
    with pytest.raises(StageError) as e:
        parse_levels("preview,fine")
    text = str(e.value)
    assert "\n" not in text and text.startswith("--mesh.detail: unknown level 'fine'")
    assert all(name in text for name in LEVELS)


def test_levels_share_one_training_and_keep_their_face_budgets(small_ws, tmp_path, monkeypatch, capsys):
    """Two levels (preview's budget made small enough to decimate this small mesh) beside the default mesh, the
    lighter decimated from the heavier's clean mesh: each a clean.ply within its budget and a textured GLB (its
    colours carried from the default mesh's texture), faces and
    GLB sizes in the stamps and the report, a progress line while each bakes (every 0.05 s here, 20 s by default);
    asking for one level afterwards redoes the mesh and
    texture stages, not the training, and removes the other level."""
    import pipeline.mesh.stage as mesh_stage
    import pipeline.texture.stage as texture_stage
    from pipeline.messages import heartbeat

    cleaned = []  # (faces in, face budget, faces out) of every mesh finished (decimated, tidied)
    real_repaired, real_finished = mesh_stage.repaired_mesh, mesh_stage.finished_mesh
    repairs = []

    def repaired_mesh(verts, faces, cfg):
        repairs.append(len(faces))
        return real_repaired(verts, faces, cfg)

    def finished_mesh(verts, faces, cfg, points=None):
        out = real_finished(verts, faces, cfg, points)
        cleaned.append((len(faces), cfg.max_faces, len(out[1])))
        return out

    monkeypatch.setattr(mesh_stage, "repaired_mesh", repaired_mesh)
    monkeypatch.setattr(mesh_stage, "finished_mesh", finished_mesh)
    monkeypatch.setitem(LEVELS, "preview", 1500)
    monkeypatch.setattr(texture_stage, "heartbeat", lambda what: heartbeat(what, every=0.05))
    ws = tmp_path / "ws"
    shutil.copytree(small_ws, ws)
    cfg = tiny_training(Config(), iterations=30, batch_rays=256)
    cfg.mesh.resolution, cfg.mesh.max_faces, cfg.texture.size = 64, 3000, 128
    cfg.mesh.detail = "preview,raw"
    reconstruct(None, ws, cfg)
    mesh = json.loads((ws / ".stages" / "mesh.json").read_text())
    texture = json.loads((ws / ".stages" / "texture.json").read_text())
    assert list(mesh["levels"]) == ["preview", "raw"] and mesh["levels"]["preview"] <= 1500
    assert 0.5 < texture["normal_map_sure"] <= 1.0
    assert mesh["levels"]["raw"] > mesh["clean_faces"] > mesh["levels"]["preview"]
    # the levels are a chain, heaviest first: raw from the extracted mesh as the default mesh repaired it (repaired
    # once), preview decimated from raw's clean mesh
    default, raw, preview = cleaned[:3]
    assert repairs == [mesh["raw_faces"]] and len(cleaned) == 3
    assert raw[0] == default[0] <= mesh["raw_faces"] and preview[0] == raw[2] == mesh["levels"]["raw"]
    assert preview[1] == 1500
    for level in ("preview", "raw"):
        folder = ws / "mesh" / "levels" / level
        assert len(trimesh.load(folder / "clean.ply").faces) == mesh["levels"][level]
        glb_mesh, tex = read_textured(folder / "textured.glb")
        assert texture["levels"][level]["glb_bytes"] == (folder / "textured.glb").stat().st_size > 0
        assert (folder / "textured.usdz").stat().st_size > 0
        assert all((folder / name).stat().st_size > 0 for name in MAP_FILES.values())  # baked per level
        assert texture["levels"][level]["faces"] == mesh["levels"][level] and tex.shape[2] == 3
        assert texture["levels"][level]["carried"] > 0.98, texture["levels"]  # the default mesh's colours
    out = capsys.readouterr().out
    assert "texture: detail level preview (" in out and "texture: detail level raw (" in out, out
    report = (ws / "report.html").read_text()
    assert "Detail levels" in report and "mesh/levels/preview/textured.glb" in report

    trained = (ws / "model" / "final.pt").stat().st_mtime_ns
    cfg.mesh.detail = "preview"
    run_stage("mesh", ws, cfg)
    run_stage("texture", ws, cfg)
    assert (ws / "model" / "final.pt").stat().st_mtime_ns == trained
    assert not (ws / "mesh" / "levels" / "raw").exists() and (ws / "mesh" / "levels" / "preview").is_dir()
    assert list(json.loads((ws / ".stages" / "texture.json").read_text())["levels"]) == ["preview"]
