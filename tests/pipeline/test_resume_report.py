"""`make reconstruct` after a kill during training resumes and finishes; the report is self-contained and,
where Chromium is installed, shows the model."""

import os
import shutil
import signal
import subprocess
import sys
import time

import pytest

from tests.conftest import ROOT

pytestmark = pytest.mark.slow

CFG = """
train:
  iterations: 80
  batch_rays: 512
  checkpoint_every: 10
  log_every: 10
  preview_every: 0
  hull_res: 48
  field: {base_res: 48, plane_res: [32, 64]}
mesh: {resolution: 96, max_faces: 5000}
texture: {size: 256}
"""


@pytest.mark.long
def test_kill_during_training_then_reconstruct_resumes(small_ws, tmp_path):
    ws = tmp_path / "ws"
    shutil.copytree(small_ws, ws)
    cfg = tmp_path / "cfg.yaml"
    cfg.write_text(CFG)
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    p = subprocess.Popen([sys.executable, "-m", "pipeline", "train", str(ws), "--config", str(cfg)], cwd=ROOT,
                         env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    ck = ws / "model" / "checkpoint.pt"
    t0 = time.time()
    while not ck.exists() and time.time() - t0 < 120 and p.poll() is None:
        time.sleep(0.05)
    os.killpg(p.pid, signal.SIGKILL)
    p.wait()
    assert ck.exists() and not (ws / "model" / "final.pt").exists()
    out = subprocess.run(["make", "--no-print-directory", "reconstruct", f"OUT={ws}", f"CONFIG={cfg}",
                          f"PY={sys.executable}"], cwd=ROOT, env=env, capture_output=True, text=True)
    assert out.returncode == 0, out.stdout[-2000:] + out.stderr[-2000:]
    assert "resuming at step" in out.stdout
    last = out.stdout.strip().splitlines()[-1]
    assert "textured.glb" in last and "report.html" in last
    for f in ("model/final.pt", "mesh/clean.ply", "mesh/textured.glb", "report.html"):
        assert (ws / f).exists(), f
    html = (ws / "report.html").read_text()
    assert "Stages" in html
    pairs = sorted((ws / "report").glob("render_*.png"))  # photo | render strips, also as files
    assert pairs, "report/render_*.png missing"
    import cv2

    pair = cv2.imread(str(pairs[0]))
    _, tag, view = pairs[0].stem.split("_", 2)
    src = ws / "gt" / "heldout" / "images" if tag == "heldout" else ws / "images"
    photo = cv2.imread(str(next(src.glob(view + ".*"))))
    assert pair.shape == (photo.shape[0], 2 * photo.shape[1], 3)
    assert (pair[:, photo.shape[1]:] != pair[0, -1]).any()  # the render half is not blank
    for ext in ('src="http', "src='http", 'href="http', "href='http"):  # self-contained: nothing fetched
        assert ext not in html, ext
    chromium = shutil.which("chromium") or shutil.which("chromium-browser")
    if not (ROOT / "node_modules" / "@google" / "model-viewer").exists():
        pytest.skip("model-viewer not installed (make setup-web): the interactive viewer is not in the report")
    assert "<model-viewer" in html
    if chromium is None:
        pytest.skip("Chromium not installed: the screenshot check of the report needs it")
    _screenshot_shows_model(chromium, ws / "report.html", tmp_path)


def _screenshot_shows_model(chromium, page, tmp_path):
    import cv2
    import numpy as np

    shot = tmp_path / "shot.png"
    # only the viewer: a page that embeds the report's model-viewer element alone would duplicate the report;
    # the viewer is the first thing after the stage table, so a tall window catches it
    subprocess.run([chromium, "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                    "--disable-background-networking", "--disable-component-update", "--disable-sync",
                    f"--user-data-dir={tmp_path / 'prof'}", "--use-gl=swiftshader", "--enable-unsafe-swiftshader",
                    "--virtual-time-budget=15000", "--window-size=900,1400", f"--screenshot={shot}",
                    page.as_uri()], check=True, capture_output=True, timeout=180)
    img = cv2.imread(str(shot))
    assert img is not None
    # the viewer's box has background #eee; the model adds other pixels inside it
    box = np.all(np.abs(img.astype(int) - 238) <= 2, axis=2)
    ys, xs = np.nonzero(box)
    assert len(ys) > 1000, "viewer not found in the screenshot"
    y0, y1, x0, x1 = ys.min(), ys.max(), xs.min(), xs.max()
    inner = img[y0:y1, x0:x1]
    not_bg = np.any(np.abs(inner.astype(int) - 238) > 10, axis=2).mean()
    assert not_bg > 0.01, f"only {not_bg:.4f} of the viewer is not background"


def test_report_says_where_the_masks_footprint_came_from(tmp_path):
    """The report's sentence for each value of the masks' ``footprint`` stamp: the source in words ("sparse points",
    "masks' hull", and an older workspace's True, from sparse points alone), the fallback for False, nothing
    for None; never the raw value."""
    import json

    import numpy as np

    from pipeline.report.stage import capture_section
    from pipeline.workspace import Workspace

    ws = Workspace(tmp_path)
    np.savez(ws.cameras, ground_plane=np.array([0.0, 0.0, 1.0, 0.5]))
    ws.stages.mkdir(parents=True, exist_ok=True)
    said = {}
    for value in ("sparse points", "masks' hull", "sparse points and masks' hull", True, False, None):
        (ws.stages / "masks.json").write_text(json.dumps({"footprint": value}))
        said[value] = capture_section(ws, {})
    assert "its sparse points on the plane, widened" in said["sparse points"] and said[True] == said["sparse points"]
    assert "the visual hull of the first masks" in said["masks' hull"]
    assert "widened" in said["sparse points and masks' hull"] and "united with the visual hull" in said[
        "sparse points and masks' hull"]
    assert "no footprint of the object could be built" in said[False]
    assert "automatic masks" not in said[None]
    assert not any("(True)" in s or "masks' hull)" in s for s in said.values())


def test_report_says_what_the_salient_object_model_did_to_the_masks():
    """The masks stage's stamp in words: made again with the model's vote (its check's share), checked and kept,
    made with it on request; nothing for masks made without it (the user's, or the check off)."""
    from pipeline.report.stage import saliency_note

    again = saliency_note({"saliency": True, "salient_beyond": 0.129})
    assert len(again) == 1 and "made again with the salient-object model's vote" in again[0] and "12.9 %" in again[0]
    kept = saliency_note({"saliency": False, "salient_beyond": 0.007})
    assert len(kept) == 1 and "checked" in kept[0] and "0.7 %" in kept[0] and "kept" in kept[0]
    asked = saliency_note({"saliency": True, "salient_beyond": None})
    assert len(asked) == 1 and "masks.saliency" in asked[0]
    assert saliency_note({"saliency": False, "salient_beyond": None}) == [] and saliency_note({}) == []


def test_stage_table_reads_as_words_and_keeps_the_raw_record():
    """A stage's row: numbers to four significant digits, nested records in brackets, long lists by their length,
    the text escaped; the full record as JSON in a folded element beside it, unchanged."""
    import json

    from pipeline.report.stage import readable, stage_row

    record = {"mean_reprojection_error": 0.4169242521923031, "rung": "default", "unregistered": [],
              "support": {"normal": [-0.0198, -0.9481, -0.3175], "inliers": 236},
              "floaters": [{"faces": 846}, {"faces": 854}], "note": "<b>"}
    text = readable(record)
    assert text == ("mean_reprojection_error: 0.4169, rung: default, unregistered: none, support: (normal: [-0.0198, "
                    "-0.9481, -0.3175], inliers: 236), floaters: 2 entries, note: <b>")
    row = stage_row("cameras", 17.81, record)
    assert "<td>17.8</td>" in row and "&lt;b&gt;" in row and "<b>" not in row
    raw = row.split("<code>")[1].split("</code>")[0]
    assert json.loads(raw.replace("&quot;", '"').replace("&lt;", "<").replace("&gt;", ">")) == record


def test_unreadable_training_record_starts_afresh(tmp_path):
    """model/config.json says which config a checkpoint belongs to; left empty or damaged (a killed run, a hand),
    it is no record: the checkpoint is discarded and training starts afresh (not json's "Expecting value" as an
    error that only --force would clear)."""
    import json

    from dvr.config import TrainConfig
    from pipeline.train.stage import _fresh_or_resume
    from pipeline.workspace import Job, Workspace

    ws = Workspace(tmp_path / "ws")
    ws.model.mkdir(parents=True)
    (ws.model / "checkpoint.pt").write_bytes(b"a checkpoint of unknown config")
    (ws.model / "config.json").write_text("")
    (tmp_path / "input.png").write_bytes(b"x")
    _fresh_or_resume(Job(ws, TrainConfig(), config_hash="abc", inputs=[tmp_path / "input.png"]))
    assert not (ws.model / "checkpoint.pt").exists()
    assert json.loads((ws.model / "config.json").read_text())["hash"] == "abc"


def test_report_skips_a_damaged_stamp(tmp_path):
    """A stage's stamp left empty (disk full, a hand) counts as not done everywhere else; the report read it with
    json.loads and stopped on json's "Expecting value"."""
    import json

    from pipeline.report.stage import build
    from pipeline.stages import STAGES
    from pipeline.workspace import Workspace

    ws = Workspace(tmp_path)
    ws.stages.mkdir(parents=True)
    (ws.stages / "train.json").write_text("")
    (ws.stages / "cameras.json").write_text(json.dumps({"seconds": 3.0}))
    page = build(ws, tuple(st.name for st in STAGES))
    assert "<h1>Reconstruction report" in page and "Stages" in page


def test_report_curves_skip_a_log_line_cut_short(tmp_path):
    """log.jsonl is appended to: a kill in the middle of a line leaves it cut short (until the training resumes and
    trims it), and the report read every line with json.loads."""
    import json

    from pipeline.report.stage import curves

    log = tmp_path / "log.jsonl"
    log.write_text("".join(json.dumps({"step": s, "loss": 0.5 / s, "psnr": 10.0 + s}) + "\n" for s in (1, 2)) +
                   '{"step": 3, "loss": 0.1')
    assert curves(log, tmp_path / "curves.png") is not None and (tmp_path / "curves.png").exists()


def test_report_renders_beside_masks_of_another_size(small_ws, tmp_path):
    """images/ redone at another size (cameras --force --cameras.max-side …) leaves masks/ of the old size until
    the masks stage runs again; the report's renders then score over the mesh's own pixels (not numpy's "operands
    could not be broadcast together")."""
    import cv2
    import numpy as np
    import trimesh

    from pipeline.report.stage import renders
    from pipeline.texture.export import export_textured
    from pipeline.workspace import Workspace

    root = tmp_path / "ws"
    shutil.copytree(small_ws, root)
    ws = Workspace(root)
    for folder in (root / "masks", root / "gt" / "heldout" / "masks"):
        for m in folder.glob("*.png"):
            cv2.imwrite(str(m), np.full((7, 9), 255, np.uint8))
    box = trimesh.creation.box(extents=(0.5, 0.5, 0.5))
    uvs = np.random.default_rng(0).uniform(0.1, 0.9, (len(box.vertices), 2))
    ws.mesh.mkdir(exist_ok=True)
    export_textured(ws.mesh, box.vertices, box.faces, uvs, np.full((16, 16, 3), 0.5, np.float32), np.eye(4))
    out = renders(ws)
    assert out and all(np.isfinite(psnr) for _, _, psnr in out)
