"""CLI and config: presets load, --help comes from docstrings, bad input is a one-line error with exit 2."""

import subprocess
import sys

import pytest

from pipeline.cli import main
from pipeline.config import Config, load_config
from tests.conftest import ROOT, cli_options

PRESETS = sorted(p.stem for p in (ROOT / "configs").glob("*.yaml"))


def test_the_presets_are_found():
    assert {"preview", "fast", "default", "balanced", "quality"} <= set(PRESETS)


@pytest.mark.parametrize("name", PRESETS)
def test_presets_load(name):
    cfg = load_config(ROOT / "configs" / f"{name}.yaml")
    assert isinstance(cfg, Config) and cfg.train.iterations > 0
    assert isinstance(cfg.train.field.plane_res, tuple)


def test_unknown_key(tmp_path):
    p = tmp_path / "bad.yaml"
    p.write_text("train: {iterashuns: 3}\n")
    with pytest.raises(ValueError, match="iterashuns"):
        load_config(p)


def _help(*args):
    out = subprocess.run([sys.executable, "-m", "pipeline", *args], cwd=ROOT, capture_output=True, text=True,
                         env={"COLUMNS": "200", "PATH": "/usr/bin:/bin"})
    assert out.returncode == 0, out.stderr
    return out.stdout


def test_help_from_docstrings():
    """--help-all lists every option with its docstring; --help the few a user needs, one line each, with the
    preset's values."""
    from pipeline.cli_help import USER_OPTIONS, field_doc
    from pipeline.config import TrainConfig

    assert field_doc(TrainConfig, "n_steps") in " ".join(_help("train", "--help-all").split())
    short = _help("reconstruct", "--help", "--config", str(ROOT / "configs" / "fast.yaml"))
    assert len(short.splitlines()) <= 150 and "--help-all" in short
    for name in [n for n in USER_OPTIONS if not n.startswith("batch.")]:
        section, leaf = name.split(".")
        assert f"--{section}." in short and leaf.replace("_", "-") in short, name
    assert "--train.iterations INT" in short and "(now: 500)" in short  # the fast preset's value
    assert "--images PATH" in short and "--mesh.frame {sfm,normalized}" in short
    assert "--masks.hull-res" not in short and "--masks.hull-res" in _help("reconstruct", "--help-all")
    assert "--batch.address" in _help("batch", "--help")


def test_missing_workspace_one_line_error(tmp_path, capsys):
    rc = main(["train", str(tmp_path / "nope")])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and len(err.splitlines()) == 1
    assert "images" in err and "run the cameras" in err


def test_bad_config_file_one_line_error(tmp_path, capsys):
    rc = main(["train", str(tmp_path), "--config", str(tmp_path / "missing.yaml")])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and "missing.yaml" in err and len(err.splitlines()) == 1


def test_broken_yaml_is_one_line_naming_where(tmp_path, capsys):
    """PyYAML's message spans five lines (the problem, a context, a caret drawing); the user gets one."""
    preset = tmp_path / "bad.yaml"
    preset.write_text("train:\n  iterations: [1\n")
    rc = main(["train", str(tmp_path), "--config", str(preset)])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and len(err.splitlines()) == 1, err
    assert "bad.yaml: not valid YAML (line 3, column 1:" in err and "configs/default.yaml" in err


def test_a_file_as_workspace_is_one_line(tmp_path, capsys):
    """A workspace path that is a file is one line, not NotADirectoryError's traceback (from the stamp of the first
    stage)."""
    photos = tmp_path / "photos"
    photos.mkdir()
    for i in range(3):
        (photos / f"{i}.png").write_bytes(b"not looked at before the workspace is")
    taken = tmp_path / "taken.txt"
    taken.write_text("a user's file")
    for command in (["reconstruct", str(taken), "--images", str(photos)], ["cameras", str(taken), "--images",
                                                                         str(photos)]):
        rc = main(command)
        err = capsys.readouterr().err.strip()
        assert rc == 2 and err == f"error: {taken}: a file, not a workspace folder; give a new or existing folder"
    assert taken.read_text() == "a user's file"


@pytest.mark.parametrize("yaml_text, named", [
    ("texture: {size: -5}\n", "--texture.size = -5: must be a whole number ≥ 1"),
    ("mesh: {max_faces: 0}\n", "--mesh.max-faces = 0: must be a whole number ≥ 1"),
    ("train: {iterations: many}\n", "--train.iterations = 'many': must be a whole number"),
    ("train: {weights: {rgb: -1.0}}\n", "--train.weights.rgb = -1.0: must be a finite number ≥ 0"),
    ("train: {field: {plane_res: [64, 0]}}\n", "--train.field.plane-res = (64, 0): must be a list of whole numbers"),
    ("texture: {angle_power: .nan}\n", "--texture.angle-power = nan: must be a finite number ≥ 0"),
    ("mesh: {frame: world}\n", "--mesh.frame = 'world': must be one of sfm, normalized"),
    ("texture: {view_selection: 2}\n", "--texture.view-selection = 2: must be true or false"),
])
def test_out_of_range_option_in_a_preset_is_one_line(tmp_path, capsys, yaml_text, named):
    """A YAML preset can hold any value: a wrong type, a negative size or a NaN is named with its option before
    any stage runs (without the check, ``texture: {size: -5}`` reached the user after training as numpy's "negative
    dimensions are not allowed")."""
    preset = tmp_path / "bad.yaml"
    preset.write_text(yaml_text)
    ws = tmp_path / "ws"
    rc = main(["reconstruct", str(ws), "--images", str(tmp_path), "--config", str(preset)])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and len(err.splitlines()) == 1 and "bad.yaml" in err and named in err
    assert not ws.exists()


@pytest.mark.parametrize("argv, named", [
    (["--texture.size", "0"], "--texture.size = 0"),
    (["--texture.texel-density", "-1.5"], "--texture.texel-density = -1.5"),
    (["--texture.angle-power", "inf"], "--texture.angle-power = inf: must be"),
    (["--texture.device", "tpu"], "--texture.device: device 'tpu' is not a torch device"),
])
def test_out_of_range_option_on_the_command_line_is_one_line(tmp_path, capsys, argv, named):
    rc = main(["texture", str(tmp_path / "ws"), *argv])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and len(err.splitlines()) == 1 and err.startswith(f"error: {named}")
    assert not (tmp_path / "ws").exists()


def test_a_device_this_machine_lacks_is_named_before_any_stage(tmp_path, capsys):
    """``reconstruct --texture.device cuda`` on a laptop stops before the first stage, naming the option, not in the
    texture stage after minutes of training: a device the machine lacks is checked first. Reading a preset does not
    check it (a batch's head node may lack the GPU its workers have)."""
    preset = tmp_path / "gpu.yaml"
    preset.write_text("train: {device: cuda}\ntexture: {device: tpu}\n")
    assert load_config(preset).texture.device == "tpu"
    ws = tmp_path / "ws"
    rc = main(["reconstruct", str(ws), "--images", str(tmp_path), "--texture.device", "tpu"])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and err == "error: --texture.device: device 'tpu' is not a torch device; use device: auto, cpu " \
                              "or cuda"
    assert not ws.exists()


def test_reconstruct_checks_every_stage_before_the_first():
    """The API too: a bad texture option stops reconstruct before the cameras stage, not after minutes of
    training; every preset and the defaults pass."""
    import dataclasses

    from pipeline.config import check_config
    from pipeline.stages import reconstruct

    cfg = Config()
    cfg = dataclasses.replace(cfg, texture=dataclasses.replace(cfg.texture, size=-1))
    with pytest.raises(ValueError, match="texture.size"):
        reconstruct(None, ROOT / "nowhere-this-is-never-created", cfg)
    assert not (ROOT / "nowhere-this-is-never-created").exists()
    for name in PRESETS:
        check_config(load_config(ROOT / "configs" / f"{name}.yaml"))


def _numbers(cfg, where=""):
    """(section config, field name, dotted name, declared positive) of every numeric option of ``cfg``."""
    import dataclasses
    import typing

    from dvr.options import is_positive

    hints = typing.get_type_hints(type(cfg), include_extras=True)
    for f in dataclasses.fields(cfg):
        value = getattr(cfg, f.name)
        if dataclasses.is_dataclass(value):
            yield from _numbers(value, f"{where}{f.name}.")
        elif isinstance(value, (int, float)) and not isinstance(value, bool):
            yield cfg, f.name, where + f.name, is_positive(hints[f.name])


def test_range_rules_are_declared_on_the_fields():
    """An option declared positive on its field (``PositiveInt``, ``PositiveFloat``) refuses 0 with a line naming
    it; every other number takes 0 (it switches a term or a step off) and refuses a negative value or NaN."""
    from pipeline.config import check_config

    cfg = Config()
    options = list(_numbers(cfg))
    assert sum(positive for *_, positive in options) >= 30  # sizes, counts, resolutions, scales
    for section, leaf, name, positive in options:
        before = getattr(section, leaf)
        for bad in ([0] if positive else []) + [-1, float("nan")]:
            if isinstance(before, int) and isinstance(bad, float):
                continue
            setattr(section, leaf, type(before)(bad) if not isinstance(bad, float) else bad)
            with pytest.raises(ValueError, match=f"--{name.replace('_', '-')} = "):
                check_config(cfg)
        if not positive:
            setattr(section, leaf, type(before)(0))
            check_config(cfg)
        setattr(section, leaf, before)


def test_a_fraction_is_refused_outside_zero_to_one():
    from pipeline.config import check_config

    cfg = Config()
    for good in (0.0, 0.5, 1.0):
        cfg.masks.carve_fraction = good
        check_config(cfg)
    for bad in (1.5, -0.1, float("nan")):
        cfg.masks.carve_fraction = bad
        with pytest.raises(ValueError, match="--masks.carve-fraction = .*: must be a number from 0 to 1"):
            check_config(cfg)


def test_mesh_without_model(tmp_path, capsys):
    rc = main(["mesh", str(tmp_path)])
    assert rc == 2 and "final.pt" in capsys.readouterr().err


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
    assert {f.name: f.default_factory for f in dataclasses.fields(Config)} == {
        s.section: s.options for s in STAGES if s.section}  # Config is declared to match the table
    masks = cli_options(COMMAND_CLASSES["masks"])
    assert "--masks.hull-res" in masks and "--masks-dir" in masks
    assert not any(o.startswith("--train.") for o in masks) and "--images" not in masks


def test_config_from_args_matches_the_preset_plus_options():
    from pipeline.config import config_from_args

    cfg = config_from_args(ROOT / "configs" / "fast.yaml", ["--train.iterations", "7", "--masks.no-stereo"])
    ref = load_config(ROOT / "configs" / "fast.yaml")
    assert cfg.train.iterations == 7 and cfg.masks.stereo is False
    ref.train.iterations, ref.masks.stereo = 7, False
    assert cfg == ref



def test_pipeline_synth_hands_over_to_the_generator(tmp_path):
    """``python -m pipeline synth`` runs ``python -m synth`` (the generator sits above the package, which never
    imports it): the generator's one-line error and exit code come through."""
    scene, out_dir = tmp_path / "missing.yaml", tmp_path / "o"
    out = subprocess.run([sys.executable, "-m", "pipeline", "synth", str(scene), str(out_dir)], cwd=ROOT,
                         capture_output=True, text=True)
    assert out.returncode == 2 and "missing.yaml" in out.stderr and len(out.stderr.strip().splitlines()) == 1
    assert not out_dir.exists()


def test_the_preview_preset_keeps_the_default_cameras():
    """A later run with the default preset in the same workspace reuses the preview's cameras stage (its stamp is the
    hash of the stage's own section), as the README says."""
    preview = load_config(ROOT / "configs" / "preview.yaml")
    assert preview.cameras == Config().cameras
    assert preview.train.iterations < Config().train.iterations
