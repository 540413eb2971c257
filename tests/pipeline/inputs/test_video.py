"""A video instead of a photo folder (pipeline/inputs/video.py): frame choice, bad input, and the cameras stage from a
hand-held clip of the scene generator (configs/scenes/e2e_video.yaml: one continuous path around a torus on a
floor, every third frame shaken)."""

import dataclasses
import json
import subprocess
import sys

import cv2
import numpy as np
import pytest

from dvr.cameras import load_cameras
from dvr.data import list_images
from dvr.metrics import pose_errors
from pipeline.config import load_config
from pipeline.errors import StageError
from pipeline.inputs.video import choose_frames, extract_frames, sharpness
from pipeline.report.stage import capture_section
from pipeline.stages import run_stage
from pipeline.workspace import Workspace
from synth import load_scene_file, write_scene
from synth.video import motion_blur, write_video
from tests.conftest import ROOT


def test_choose_frames_takes_the_sharpest_of_each_equal_stretch():
    scores = np.array([1.0, 5.0, 2.0, 9.0, 0.5, 3.0, 3.0, 1.0])
    assert choose_frames(scores, 4) == [1, 3, 5, 6]
    assert choose_frames(scores, 1) == [3]
    assert choose_frames(scores[:3], 10) == [0, 1, 2]  # fewer frames than asked: all of them
    with pytest.raises(ValueError, match="n must be"):
        choose_frames(scores, 0)


def test_motion_blur_lowers_the_sharpness():
    rng = np.random.default_rng(0)
    img = cv2.resize((rng.random((40, 60, 3)) * 255).astype(np.uint8), (240, 160), interpolation=cv2.INTER_NEAREST)
    assert sharpness(motion_blur(img, 9, 30.0)) < 0.5 * sharpness(img)


def _clip(tmp_path, n=12, shake_every=3):
    """A clip of ``n`` frames of random blocks (each its own), every ``shake_every``-th shaken."""
    rng = np.random.default_rng(1)
    folder = tmp_path / "renders"
    folder.mkdir()
    for k in range(n):
        img = (rng.random((30, 40, 3)) * 255).astype(np.uint8)
        cv2.imwrite(str(folder / f"{k:06d}.png"), cv2.resize(img, (160, 120), interpolation=cv2.INTER_NEAREST))
    return write_video(folder, tmp_path / "clip.mp4", shake_every=shake_every)


def test_extract_frames_skips_the_shaken_ones_and_leaves_the_clip(tmp_path):
    clip = _clip(tmp_path)
    before = clip.read_bytes()
    out = tmp_path / "ws" / "frames"
    rec = extract_frames(clip, out, 4, 1600)
    assert json.loads((out / "frames.json").read_text()) == rec
    shaken = set(json.loads(clip.with_suffix(".json").read_text())["shaken"])
    chosen = [c["frame"] for c in rec["chosen"]]
    assert len(chosen) == 4 and not shaken & set(chosen) and rec["frames_in_clip"] == 12
    assert [k // 3 for k in chosen] == [0, 1, 2, 3]  # one from each stretch
    assert sorted(p.name for p in out.glob("*.jpg")) == [f"frame{i:04d}.jpg" for i in range(4)]
    assert cv2.imread(str(out / "frame0000.jpg")).shape == (120, 160, 3)
    assert clip.read_bytes() == before
    extract_frames(clip, out, 4, 80)  # again, smaller: the folder is replaced as a whole
    assert sorted(p.name for p in out.glob("*.jpg")) == [f"frame{i:04d}.jpg" for i in range(4)]
    assert cv2.imread(str(out / "frame0000.jpg")).shape == (60, 80, 3)
    assert not (tmp_path / "ws" / "frames.partial").exists()


@pytest.mark.parametrize(("codec", "name", "rotation"), [("h264", "clip.mp4", 90), ("h264", "clip.MOV", 270),
                                                         ("h264", "clip.mp4", 180), ("hevc", "clip.mov", 90)])
def test_a_phones_clip_comes_out_upright(tmp_path, codec, name, rotation):
    """H.264 and 10-bit HEVC clips filmed with the phone held upright or upside down: the frames are stored turned
    and the container says how to turn them back; the frames taken are the renders, upright."""
    rng = np.random.default_rng(2)
    folder = tmp_path / "renders"
    folder.mkdir()
    for k in range(6):  # portrait renders, each its own blocks
        img = (rng.random((8, 6, 3)) * 255).astype(np.uint8)
        cv2.imwrite(str(folder / f"{k:06d}.png"), cv2.resize(img, (96, 128), interpolation=cv2.INTER_NEAREST))
    clip = write_video(folder, tmp_path / name, codec=codec, rotation=rotation, shake_every=0)
    cap = cv2.VideoCapture(str(clip), cv2.CAP_FFMPEG)
    cap.set(cv2.CAP_PROP_ORIENTATION_AUTO, 0)
    stored = cap.read()[1]
    cap.release()
    assert stored.shape[:2] == ((96, 128) if rotation in (90, 270) else (128, 96))  # as the sensor wrote them
    rec = extract_frames(clip, tmp_path / "frames", 6, 1600)
    assert [c["frame"] for c in rec["chosen"]] == list(range(6))
    for c in rec["chosen"]:
        got = cv2.imread(str(tmp_path / "frames" / c["file"])).astype(float)
        render = cv2.imread(str(folder / f"{c['frame']:06d}.png")).astype(float)
        assert got.shape == render.shape
        err, err_turned = np.abs(got - render).mean(), np.abs(got - render[::-1, ::-1]).mean()
        assert err < 12 and err_turned > 40, (err, err_turned)


def test_write_video_refuses_what_it_cannot_write(tmp_path):
    with pytest.raises(ValueError, match="codec must be"):
        write_video(tmp_path, tmp_path / "clip.mp4", codec="prores")
    with pytest.raises(ValueError, match="rotation must be"):
        write_video(tmp_path, tmp_path / "clip.mp4", codec="mp4v", rotation=90)  # OpenCV's writer cannot tag it
    with pytest.raises(ValueError, match="rotation must be"):
        write_video(tmp_path, tmp_path / "clip.mp4", codec="h264", rotation=45)


def test_a_file_that_is_no_video_is_one_line_naming_it(tmp_path):
    bad = tmp_path / "clip.mp4"
    bad.write_bytes(b"not a video at all" * 100)
    with pytest.raises(StageError, match="clip.mp4: cannot be read as a video"):
        extract_frames(bad, tmp_path / "frames", 8, 1600)
    short = tmp_path / "short"
    short.mkdir()
    write_video(_one_frame(short), tmp_path / "short.mp4", shake_every=0)
    with pytest.raises(StageError, match="short.mp4: 1 frame"):
        extract_frames(tmp_path / "short.mp4", tmp_path / "frames", 8, 1600)
    r = subprocess.run([sys.executable, "-m", "pipeline", "cameras", str(tmp_path / "ws"), "--images", str(bad)],
                       capture_output=True, text=True, cwd=ROOT)
    assert r.returncode != 0 and "Traceback" not in r.stderr and "cannot be read as a video" in r.stderr
    assert bad.read_bytes() == b"not a video at all" * 100


def _one_frame(folder):
    cv2.imwrite(str(folder / "000000.png"), np.full((120, 160, 3), 128, np.uint8))
    return folder


@pytest.mark.slow
@pytest.mark.long
def test_cameras_from_a_hand_held_clip(tmp_path, capsys):
    """A phone's clip of one walk around the torus, held upright (36 frames of 180×240 stored turned in an H.264
    MP4 tagged 90°, every third shaken), through the cameras stage: 18 frames taken (20° apart), upright, none
    shaken, every one registered, poses within 1 % of the orbit of the frames' true cameras, the floor found and
    left out of the masks."""
    scene = load_scene_file(ROOT / "configs" / "scenes" / "e2e_video.yaml")
    scene.cameras = dataclasses.replace(scene.cameras, n_views=36, width=180, height=240)
    syn = tmp_path / "synthetic"
    write_scene(scene, syn)
    clip = write_video(syn / "images", tmp_path / "my clip.mp4", codec="h264", rotation=90)
    cfg = load_config(ROOT / "configs" / "default.yaml")
    cfg.cameras.video_frames = 18
    ws = tmp_path / "ws"
    run_stage("cameras", ws, cfg, images=clip)
    assert "skipping" not in capsys.readouterr().err  # frames/frames.json is the stage's own record, no photo
    chosen = [c["frame"] for c in json.loads((ws / "frames" / "frames.json").read_text())["chosen"]]
    assert not set(chosen) & set(json.loads(clip.with_suffix(".json").read_text())["shaken"])
    names = [p.stem for p in list_images(ws / "images")]
    assert names == [f"frame{i:04d}" for i in range(18)]  # every frame registered
    assert cv2.imread(str(ws / "images" / f"{names[0]}.png")).shape == (240, 180, 3)  # upright
    est, gt = load_cameras(ws / "cameras.npz"), load_cameras(syn / "cameras.npz")

    def centres(c):
        return c.centers @ c.scale_mat[:3, :3].T + c.scale_mat[:3, 3]

    err = pose_errors(centres(est), est.R, centres(gt)[chosen], gt.R[chosen])
    print(json.dumps({"frames": chosen, **err}))
    assert err["center_err_rel_max"] <= 0.01 and err["rot_err_deg_max"] < 1.0, err
    assert "ground_plane" in np.load(ws / "cameras.npz")  # the floor found from a clip as from photos
    stamp = Workspace(ws).stamp("cameras")
    assert stamp["video"] == {"clip": "my clip.mp4", "frames_in_clip": 36, "taken": 18}
    assert "From the video my clip.mp4: 18 of its 36 frames" in capture_section(Workspace(ws), stamp)
    run_stage("masks", ws, cfg)  # and the masks leave it out: the frames' true masks
    ious = []
    for n, k in zip(names, chosen):
        a = cv2.imread(str(ws / "masks" / f"{n}.png"), 0) > 127
        b = cv2.imread(str(syn / "gt" / "masks" / f"{k:06d}.png"), 0) > 127
        ious.append((a & b).sum() / (a | b).sum())
    assert np.mean(ious) >= 0.95, ious
