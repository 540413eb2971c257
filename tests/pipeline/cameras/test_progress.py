"""Progress lines of an SfM child process read from COLMAP's log, and its time budget."""

import subprocess
import sys
import time

from pipeline.cameras.progress import LogProgress, wait_with_progress
from pipeline.messages import heartbeat, minutes

LOG = """I20261128 17:16:46.863876 1 feature_extraction.cc:270] Processed file [1/16]
I20261128 17:16:47.061204 1 feature_extraction.cc:270] Processed file [2/16]
I20261128 17:16:51.234950 1 pairing.cc:214] Processing block [2/3, 3/3]
Matching 589 pairs of similar photos (15 per photo)
I20261129 03:55:23.529173 1 pairing.cc:938] Processing block [2/12]
I20261128 17:16:56.337419 1 incremental_pipeline.cc:620] Registering image #26 (num_reg_frames=12)
I20261128 17:16:56.337468 1 incremental_pipeline.cc:623] => Image sees 115 / 533 points
I20261128 17:16:57.000000 1 global_mapper.cc:80] Running rotation averaging...
"""


def test_log_progress_follows_the_log_as_it_grows(tmp_path):
    log = tmp_path / "rung.log"
    watch = LogProgress(log)
    assert watch.update() == "starting"  # no log yet
    steps = []
    for line in LOG.splitlines(keepends=True):
        with open(log, "a") as f:
            f.write(line[:20])  # a line written in two pieces is read once whole
        steps.append(watch.update())
        with open(log, "a") as f:
            f.write(line[20:])
        steps.append(watch.update())
    assert steps[1] == "features of 1/16 photos" and steps[3] == "features of 2/16 photos"
    assert steps[5] == "matching, block 6/9"  # block (2, 3) of 3 × 3
    assert steps[7] == "matching 589 pairs of similar photos" and steps[9] == "matching, block 2/12"
    assert steps[11] == steps[13] == "mapping, 12 photos registered"  # a line of no step keeps the last one
    assert steps[15] == "mapping: rotation averaging"
    assert minutes(42.4) == "42 s" and minutes(185) == "3 min 05 s"


GLOBAL_LOG = """I20261129 02:50:35.323441 1 database_cache.cc:144] Loading matches...
I20261129 02:50:35.813884 1 global_pipeline.cc:319] === Reconstructing component 1 / 2 with 62 images ===
I20261129 02:50:35.887626 1 global_mapper.cc:565] === Running track establishment ===
I20261129 02:50:56.416378 1 global_mapper.cc:391] Global bundle adjustment iteration 2 / 3, fixed-rotation stage
"""


def test_the_global_mappers_steps_are_said(tmp_path):
    """COLMAP's global mapper logs its own steps: each says what it does, not "starting"."""
    log = tmp_path / "rung.log"
    watch, steps = LogProgress(log), []
    for line in GLOBAL_LOG.splitlines(keepends=True):
        with open(log, "a") as f:
            f.write(line)
        steps.append(watch.update())
    assert steps == ["mapping: loading the matches", "global mapping: part 1/2, 62 photos",
                     "global mapping: track establishment", "global mapping: bundle adjustment, pass 2/3"]


def _child(tmp_path, seconds: float):
    log = tmp_path / "child.log"
    code = ("import sys, time; print('x feature_extraction.cc:270] Processed file [3/10]', flush=True); "
            f"time.sleep({seconds})")
    f = open(log, "w")
    return subprocess.Popen([sys.executable, "-c", code], stdout=f, stderr=subprocess.STDOUT), log, f


def test_a_running_rung_says_what_it_does_at_every_interval(tmp_path):
    p, log, f = _child(tmp_path, 1.5)
    said = []
    with f:
        killed = wait_with_progress(p, log, "default", None, said.append, every=0.3)
    assert not killed and p.returncode == 0
    assert len(said) >= 3 and all(s.startswith("cameras: rung default: ") for s in said)
    assert "features of 3/10 photos" in said[-1]


def test_a_rung_past_its_time_is_stopped(tmp_path):
    p, log, f = _child(tmp_path, 60)
    t0 = time.time()
    with f:
        killed = wait_with_progress(p, log, "guided", t0 + 1.0, [].append, every=0.3)
    assert killed and p.returncode != 0 and time.time() - t0 < 10


def test_a_step_that_says_nothing_itself_gets_a_heartbeat():
    said = []
    with heartbeat("cameras: final adjustment", every=0.2, say=said.append):
        time.sleep(0.9)
    n = len(said)
    time.sleep(0.5)
    assert n >= 3 and len(said) == n  # lines while it runs, none after
    assert said[0].startswith("cameras: final adjustment (")
