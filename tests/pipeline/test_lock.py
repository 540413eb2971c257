"""The workspace lock (pipeline/lock.py): a second run stops at once with one line naming the first, a killed run's
lock is taken over, the lock is re-entrant within a run, and a run's SfM child ends with it."""

import json
import os
import signal
import subprocess
import sys
import threading
import time

import pytest

from pipeline.lock import WorkspaceBusy, info_file, read_info, workspace_lock
from pipeline.stages import run_stage
from tests.conftest import ROOT


def test_a_second_run_stops_with_one_line_naming_the_first(tmp_path):
    """`python -m pipeline train WS` while another run holds WS: exit code 2, one line with the holder's PID and
    command and how to wait for it, no traceback, and nothing of the workspace touched."""
    ws = tmp_path / "ws"
    ws.mkdir()
    with workspace_lock(ws, "reconstruct"):
        holder = read_info(ws)
        p = subprocess.run([sys.executable, "-m", "pipeline", "train", str(ws)], cwd=ROOT, capture_output=True,
                           text=True, timeout=300)
        assert read_info(ws) == holder  # the refused run did not overwrite who holds it
    err = p.stderr.strip().splitlines()
    assert p.returncode == 2 and len(err) == 1, p.stderr
    assert f"PID {os.getpid()}" in err[0] and "another run is working in this workspace" in err[0]
    assert f"tail --pid={os.getpid()}" in err[0] and "Traceback" not in p.stderr
    assert not info_file(ws).exists()  # released: the record goes with the lock
    assert sorted(p.name for p in (ws / ".stages").iterdir()) == ["lock"]


def test_the_lock_is_reentrant_in_a_run_and_exclusive_between_threads(tmp_path):
    ws = tmp_path / "ws"
    ws.mkdir()
    refused = []

    def other():
        try:
            with workspace_lock(ws, "another thread"):
                pass
        except WorkspaceBusy as exc:
            refused.append(str(exc))

    with workspace_lock(ws, "reconstruct"):
        with workspace_lock(ws, "the train stage"):  # reconstruct → run_stage: the same run
            assert read_info(ws)["run"] == "reconstruct"
        assert info_file(ws).exists()  # the inner block ends, the outer still holds it
        t = threading.Thread(target=other)
        t.start()
        t.join()
    assert len(refused) == 1 and f"PID {os.getpid()}" in refused[0]
    with workspace_lock(ws, "later"):  # free again
        pass


_HOLD = """
import sys, time
sys.path.insert(0, {root!r})
from pipeline.lock import workspace_lock
with workspace_lock({ws!r}, "reconstruct"):
    print("held", flush=True)
    time.sleep(120)
"""


def test_a_killed_runs_lock_is_taken_over_and_said(tmp_path, capsys):
    """kill -9 leaves the record of the run, not the lock (the kernel releases it): the next run says it takes
    over, and works."""
    ws = tmp_path / "ws"
    ws.mkdir()
    p = subprocess.Popen([sys.executable, "-c", _HOLD.format(root=str(ROOT), ws=str(ws))], stdout=subprocess.PIPE,
                         text=True)
    assert p.stdout.readline().strip() == "held"
    with pytest.raises(WorkspaceBusy, match=f"PID {p.pid}"):
        with workspace_lock(ws, "second"):
            pass
    os.kill(p.pid, signal.SIGKILL)
    p.wait()
    assert json.loads(info_file(ws).read_text())["pid"] == p.pid  # the dead run's record is still there
    capsys.readouterr()
    with workspace_lock(ws, "after the kill"):
        assert read_info(ws)["pid"] == os.getpid()
    err = capsys.readouterr().err
    assert f"PID {p.pid}" in err and "ended without releasing the workspace (killed?); taking it over" in err


def test_a_stage_on_a_busy_workspace_refuses_before_it_changes_anything(tmp_path):
    """run_stage (the API of the CLI, reconstruct and the batch's tasks) takes the lock before it decides anything
    (here: before it finds its inputs missing), and a busy workspace keeps its stamps and markers."""
    ws = tmp_path / "ws"
    (ws / ".stages").mkdir(parents=True)
    (ws / ".stages" / "train.json").write_text("{}")
    p = subprocess.Popen([sys.executable, "-c", _HOLD.format(root=str(ROOT), ws=str(ws))], stdout=subprocess.PIPE,
                         text=True)
    try:
        assert p.stdout.readline().strip() == "held"
        with pytest.raises(WorkspaceBusy, match=f"PID {p.pid}"):
            run_stage("train", ws)
        assert sorted(q.name for q in (ws / ".stages").iterdir()) == ["lock", "lock.info", "train.json"]
    finally:
        p.kill()
        p.wait()


_PARENT = """
import os, subprocess, sys, time
child = subprocess.Popen([sys.executable, "-c", "import sys, time; sys.path.insert(0, {root!r}); "
                          "from pipeline.lock import end_with_parent; end_with_parent(int(sys.argv[1])); "
                          "print('ready', flush=True); time.sleep(120)", str(os.getpid())], stdout=subprocess.PIPE,
                         text=True)
assert child.stdout.readline().strip() == "ready"
print(child.pid, flush=True)
time.sleep(120)
"""


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="the parent-death signal is Linux's")
def test_a_child_of_a_killed_run_ends_with_it(tmp_path):
    """The SfM rung's child process (python -m pipeline.cameras.sfm) would go on writing sfm/ after its run was
    killed, while the next run, holding the lock, rewrites it."""
    p = subprocess.Popen([sys.executable, "-c", _PARENT.format(root=str(ROOT))], stdout=subprocess.PIPE, text=True)
    child = int(p.stdout.readline())  # once the child has made its call
    os.kill(p.pid, signal.SIGKILL)
    p.wait()
    for _ in range(100):
        try:
            os.kill(child, 0)
        except ProcessLookupError:
            break
        time.sleep(0.05)
    else:
        os.kill(child, signal.SIGKILL)
        pytest.fail("the child outlived its killed parent")
    # a run killed while its child was still importing: the child, left to another parent, ends at its call
    late = subprocess.run([sys.executable, "-c", f"import sys; sys.path.insert(0, {str(ROOT)!r}); from pipeline.lock "
                           "import end_with_parent; end_with_parent(1); print('went on')"], capture_output=True,
                          text=True)
    assert late.returncode == 1 and "went on" not in late.stdout


def test_a_second_batch_on_the_same_out_folder_stops_before_it_starts(tmp_path):
    """Two batches writing one OUT (its summary, its captures' workspaces) at once: the second stops with the
    lock's line before it starts its cluster."""
    from pipeline.batch.runner import run_batch

    (tmp_path / "captures" / "vase").mkdir(parents=True)
    out = tmp_path / "out"
    out.mkdir()
    held, release = threading.Event(), threading.Event()

    def first_batch():
        with workspace_lock(out, "batch"):
            held.set()
            release.wait(60)

    t = threading.Thread(target=first_batch)
    t.start()
    try:
        assert held.wait(60)
        with pytest.raises(WorkspaceBusy, match=f"{out}: another run is working in this workspace"):
            run_batch(tmp_path / "captures", out)
    finally:
        release.set()
        t.join()
    assert not (out / "summary.json").exists()
