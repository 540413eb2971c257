"""Atomic writes (dvr/atomic.py): a file is whole or absent, a full disk is an OSError naming the file, and the
writers that hide a failed write (OpenCV, torch.save) are caught."""

import errno
import json

import cv2
import numpy as np
import pytest
import torch
import trimesh

from dvr import atomic
from dvr.atomic import (
    DiskFull,
    atomic_path,
    copy_file,
    export_mesh,
    is_disk_full,
    partial_path,
    save_npz,
    save_torch,
    sweep_partials,
    write_image,
    write_json,
)


def test_every_writer_writes_what_reads_back(tmp_path):
    write_json(tmp_path / "a.json", {"x": 1}, indent=1)
    save_npz(tmp_path / "c.npz", a=np.arange(3))
    img = (np.arange(48).reshape(4, 4, 3) * 5).astype(np.uint8)
    write_image(tmp_path / "m.png", img)
    save_torch({"w": torch.ones(2)}, tmp_path / "k.pt")
    export_mesh(tmp_path / "b.ply", trimesh.creation.box())
    copy_file(tmp_path / "a.json", tmp_path / "copy.json")
    assert json.loads((tmp_path / "copy.json").read_text()) == {"x": 1}
    assert np.load(tmp_path / "c.npz")["a"].tolist() == [0, 1, 2]
    assert (cv2.imread(str(tmp_path / "m.png")) == img).all()
    assert torch.load(tmp_path / "k.pt")["w"].tolist() == [1.0, 1.0]
    assert len(trimesh.load(tmp_path / "b.ply").faces) == 12
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.json", "b.ply", "c.npz", "copy.json", "k.pt", "m.png"]


def test_a_write_that_fails_leaves_the_old_file_and_no_temporary(tmp_path):
    """A writer stopped half way (an exception: a kill leaves the temporary file, which the next run sweeps) keeps the
    last whole file; np.savez's own habit of adding .npz to a name is not followed into a second file."""
    target = tmp_path / "cameras.npz"
    save_npz(target, a=np.zeros(2))
    with pytest.raises(RuntimeError), atomic_path(target) as tmp:
        tmp.write_bytes(b"PK half")
        raise RuntimeError("killed")
    assert np.load(target)["a"].tolist() == [0.0, 0.0]
    assert [p.name for p in tmp_path.iterdir()] == ["cameras.npz"]


def test_a_folder_is_replaced_whole(tmp_path):
    model = tmp_path / "best"
    model.mkdir()
    (model / "old.bin").write_text("old")
    with pytest.raises(RuntimeError), atomic_path(model, folder=True) as tmp:
        (tmp / "cameras.bin").write_text("half")
        raise RuntimeError("killed")
    assert [p.name for p in model.iterdir()] == ["old.bin"]
    with atomic_path(model, folder=True) as tmp:
        (tmp / "cameras.bin").write_text("new")
    assert [p.name for p in model.iterdir()] == ["cameras.bin"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["best"]


class _FullDisk:
    """A binary file on a disk that fills after ``room`` bytes."""

    def __init__(self, room):
        self.room = room

    def write(self, b):
        if len(b) > self.room:
            raise OSError(errno.ENOSPC, "No space left on device")
        self.room -= len(b)
        return len(b)

    def flush(self):
        pass


def test_a_full_disk_is_an_oserror_naming_the_file_even_through_torch(tmp_path, monkeypatch):
    """torch.save reports a failed write as a RuntimeError without the errno ("unexpected pos …"): the file it
    writes to records the OSError, which is what save_torch raises."""
    with pytest.raises(RuntimeError, match="unexpected pos|write"):
        torch.save({"w": torch.zeros(100_000)}, _FullDisk(1000))
    monkeypatch.setattr(atomic, "atomic_file", lambda path: _nullctx(_FullDisk(1000)))
    with pytest.raises(OSError) as exc:
        save_torch({"w": torch.zeros(100_000)}, tmp_path / "checkpoint.pt")
    assert exc.value.errno == errno.ENOSPC and is_disk_full(exc.value)


class _nullctx:
    def __init__(self, f):
        self.f = f

    def __enter__(self):
        return self.f

    def __exit__(self, *a):
        return False


def test_a_full_disk_names_the_target_and_its_size(tmp_path, monkeypatch):
    real = atomic.os.replace

    def full(src, dst):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(atomic.os, "replace", full)
    with pytest.raises(DiskFull) as exc:
        atomic.write_bytes(tmp_path / "textured.png", b"x" * 1234)
    monkeypatch.setattr(atomic.os, "replace", real)
    assert exc.value.filename == str(tmp_path / "textured.png") and exc.value.size == 1234
    assert list(tmp_path.iterdir()) == []  # the temporary file went with the failure


def test_opencv_failures_are_raised_not_returned(tmp_path):
    """cv2.imwrite returns False (a full disk, a missing folder) and the caller goes on without the file."""
    img = np.zeros((4, 4), np.uint8)
    assert cv2.imwrite(str(tmp_path / "gone" / "m.png"), img) is False
    with pytest.raises(FileNotFoundError):
        write_image(tmp_path / "gone" / "m.png", img)


def test_disk_full_in_the_words_of_colmap_and_sqlite():
    assert is_disk_full(OSError(errno.ENOSPC, "x"))
    assert is_disk_full(RuntimeError("SQLite error: database or disk is full"))
    try:
        try:
            raise OSError(errno.ENOSPC, "No space left on device")
        except OSError as e:
            raise RuntimeError("write failed") from e
    except RuntimeError as chained:
        assert is_disk_full(chained)
    assert not is_disk_full(OSError(errno.EACCES, "Permission denied"))
    assert not is_disk_full(ValueError("bad"))


def test_sweep_removes_only_what_killed_writers_left(tmp_path):
    (tmp_path / "masks").mkdir()
    keep = [tmp_path / "masks" / "a.png", tmp_path / ".stages.json"]
    for p in keep:
        p.write_text("whole")
    left = partial_path(tmp_path / "masks" / "b.png")
    left.write_text("half")
    folder = partial_path(tmp_path / "best")
    (folder / "sub").mkdir(parents=True)
    assert sweep_partials(tmp_path) == 2
    assert not left.exists() and not folder.exists() and all(p.exists() for p in keep)
