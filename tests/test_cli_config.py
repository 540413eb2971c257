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


def _options(cls) -> set[str]:
    import tyro

    return {o for a in tyro.extras.get_parser(cls)._actions for o in a.option_strings}


def test_every_option_the_readme_and_makefile_name_parses():
    """Each ``--section.option`` the README or the Makefile names is an option of ``python -m pipeline
    reconstruct`` (the one namespace per stage every stage command shares) or of ``batch``, and each path option
    exists."""
    import re

    from pipeline.cli import COMMAND_CLASSES

    known = _options(COMMAND_CLASSES["reconstruct"]) | _options(COMMAND_CLASSES["batch"])
    text = (ROOT / "README.md").read_text() + (ROOT / "Makefile").read_text()
    named = set(re.findall(r"--[a-z][a-z0-9-]*\.[a-z][a-z0-9-]*[a-z0-9]", text))
    assert len(named) >= 10  # the README documents options; the pattern finds them
    assert sorted(named - known) == []
    assert {"--images", "--masks-dir", "--given-cameras", "--config", "--force"} <= known


def test_stage_table_drives_cli_config_and_make():
    """One stage table: every stage is a CLI command and a make target, every config section belongs to a stage,
    and a stage command offers its own section's options only."""
    from pipeline.cli import COMMAND_CLASSES, COMMANDS
    from pipeline.stages import STAGES

    names = [s.name for s in STAGES]
    assert set(names) <= set(COMMANDS)
    make = subprocess.run(["make", "-s", "print-stages"], cwd=ROOT, capture_output=True, text=True)
    assert make.stdout.split() == names
    import dataclasses

    assert {s.section for s in STAGES if s.section} == {f.name for f in dataclasses.fields(Config)}
    masks = _options(COMMAND_CLASSES["masks"])
    assert "--masks.hull-res" in masks and "--masks-dir" in masks
    assert not any(o.startswith("--train.") for o in masks) and "--images" not in masks


def test_config_from_args_matches_the_preset_plus_options():
    from pipeline.config import config_from_args

    cfg = config_from_args(ROOT / "configs" / "fast.yaml", ["--train.iterations", "7", "--masks.no-stereo"])
    ref = load_config(ROOT / "configs" / "fast.yaml")
    assert cfg.train.iterations == 7 and cfg.masks.stereo is False
    ref.train.iterations, ref.masks.stereo = 7, False
    assert cfg == ref

