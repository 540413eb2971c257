"""CLI and config: presets load, --help comes from docstrings, bad input is a one-line error with exit 2."""

import subprocess
import sys

import pytest

from pipeline.cli import main
from pipeline.config import Config, load_config
from tests.conftest import ROOT


@pytest.mark.parametrize("name", ["fast", "default", "balanced", "quality"])
def test_presets_load(name):
    cfg = load_config(ROOT / "configs" / f"{name}.yaml")
    assert isinstance(cfg, Config) and cfg.train.iterations > 0
    assert isinstance(cfg.train.field.plane_res, tuple)


def test_unknown_key(tmp_path):
    p = tmp_path / "bad.yaml"
    p.write_text("train: {iterashuns: 3}\n")
    with pytest.raises(ValueError, match="iterashuns"):
        load_config(p)


def test_help_from_docstrings():
    out = subprocess.run([sys.executable, "-m", "pipeline", "train", "--help"], cwd=ROOT, capture_output=True,
                         text=True, env={"COLUMNS": "200", "PATH": "/usr/bin:/bin"})
    assert out.returncode == 0
    assert "Ray-marching samples between the unit-sphere entry" in out.stdout


def test_missing_workspace_one_line_error(tmp_path, capsys):
    rc = main(["train", str(tmp_path / "nope")])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and len(err.splitlines()) == 1
    assert "images" in err and "run the cameras" in err


def test_bad_config_file_one_line_error(tmp_path, capsys):
    rc = main(["train", str(tmp_path), "--config", str(tmp_path / "missing.yaml")])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and "missing.yaml" in err and len(err.splitlines()) == 1


def test_mesh_without_model(tmp_path, capsys):
    rc = main(["mesh", str(tmp_path)])
    assert rc == 2 and "final.pt" in capsys.readouterr().err
