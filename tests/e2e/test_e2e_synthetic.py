"""End to end on the standard synthetic object (textured torus, 24 views, 128 px, GT cameras and masks):
synth → train (CLI) → mesh (API); Chamfer to the GT mesh ≤ 2 % of its diagonal; with sparse depth
added, no worse."""

import json
import shutil

import pytest
import trimesh

from dvr.metrics import chamfer_fscore
from pipeline.cli import main
from pipeline.config import load_config
from pipeline.stages import run_stage
from synth import load_scene_file, write_scene
from tests.conftest import ROOT

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def torus_ws(tmp_path_factory):
    ws = tmp_path_factory.mktemp("torus")
    sc = load_scene_file(ROOT / "configs" / "scenes" / "torus.yaml")
    sc.sparse_depth = 100
    write_scene(sc, ws)
    return ws


def _reconstruct(ws, extra=()):
    args = ["--config", str(ROOT / "configs" / "fast.yaml")]
    assert main(["train", str(ws), *args, "--train.no-progress", *extra]) == 0  # the CLI a user runs
    run_stage("mesh", ws, load_config(ROOT / "configs" / "fast.yaml"))  # the API the CLI calls
    pred = trimesh.load(ws / "mesh" / "clean.ply")
    gt = trimesh.load(ws / "gt" / "mesh.ply")
    return chamfer_fscore(pred, gt, n=50000)


def test_torus_without_and_with_sparse_depth(torus_ws, tmp_path):
    no_depth = tmp_path / "nodepth"
    shutil.copytree(torus_ws, no_depth)
    shutil.rmtree(no_depth / "depth")
    steps = ("--train.iterations", "400")  # fewer than the fast preset's 500: enough for the bounds below
    r0 = _reconstruct(no_depth, steps)
    r1 = _reconstruct(torus_ws, steps)
    print(json.dumps({"no_depth": r0, "depth": r1}))
    assert r0["chamfer_rel"] <= 0.02
    assert r1["chamfer_rel"] <= 0.02
    assert r1["chamfer_rel"] <= r0["chamfer_rel"] * 1.10  # depth supervision does not make it worse
    # the log has the required fields and a rerun is a no-op (up to date)
    rec = json.loads((torus_ws / "model" / "log.jsonl").read_text().splitlines()[-1])
    assert rec["depth"] is not None and rec["depth"] >= 0
    mtime = (torus_ws / "mesh" / "clean.ply").stat().st_mtime
    assert main(["mesh", str(torus_ws), "--config", str(ROOT / "configs" / "fast.yaml")]) == 0
    assert (torus_ws / "mesh" / "clean.ply").stat().st_mtime == mtime
