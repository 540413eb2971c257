"""bench/gpu.py's train step: the train stage and its stamp on a machine without pycolmap (the GPU machine's image)."""

import json
import shutil
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]

TRAIN = """
import json, sys
from pathlib import Path
sys.modules["pycolmap"] = None  # as on the GPU machine: importing it fails
sys.path.insert(0, sys.argv[1])
from bench.gpu import train_stage
from tests.dvr.test_hard_cases import tiny_cfg
train_stage(Path(sys.argv[2]), tiny_cfg(iterations=4, checkpoint_every=2))
"""


def test_the_train_stage_runs_and_stamps_without_pycolmap(small_ws, tmp_path):
    """``train_stage`` trains the workspace and writes the stamp the mesh stage requires (steps, rays, device), where
    pycolmap cannot be imported; ``run_folder`` names a run's workspace."""
    from bench.gpu import run_folder

    ws = tmp_path / "ws"
    shutil.copytree(small_ws, ws)
    done = subprocess.run([sys.executable, "-c", TRAIN, str(ROOT), str(ws)], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr[-2000:]
    stamp = json.loads((ws / ".stages" / "train.json").read_text())
    assert (stamp["steps"], stamp["batch_rays"], stamp["device"]) == (4, 256, "cpu") and stamp["seconds"] > 0
    assert (ws / "model" / "final.pt").exists()
    assert run_folder("cow:default:scale1") == "cow_default_scale1"
