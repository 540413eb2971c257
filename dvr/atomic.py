"""Atomic writes: a file (or folder) the pipeline writes is whole or absent, never half written.

Every writer puts its content under a temporary name beside the target (``.<name>.<pid>.partial``: hidden, in the
same folder so the rename stays on one file system, and with no extension a reader globs for), then renames it over
the target with :func:`os.replace`. A process killed while writing (``kill -9``, the out-of-memory killer, a closed
terminal) leaves at most that temporary file, which nothing reads and the next run that takes the workspace sweeps
away (:func:`sweep_partials`); the file of the last finished write stays as it was. (Nothing is synced to the disk:
a power cut is another matter.)

A full disk (``ENOSPC``) or quota (``EDQUOT``) stops a write with an :class:`OSError` carrying that errno and the
target's path (:class:`DiskFull`, with the size when the content was in memory), its temporary file removed: the
caller says it in one line (:func:`pipeline.stages.run_stage`). Writers that hide the error are checked: OpenCV's
``imwrite`` returns False (images are encoded in memory here and written by Python), ``torch.save`` turns it into a
RuntimeError without the errno (the Python file it writes to records it), and COLMAP's model writer leaves its
files cut short without a word (:func:`check_room` after it).

    from dvr.atomic import write_json, write_image, save_torch, atomic_path

    write_json(ws / "stage.json", {"seconds": 3})
    write_image(ws / "masks" / "a.png", mask)                  # cv2.imencode, then one write
    save_torch(checkpoint, ws / "model" / "checkpoint.pt")
    with atomic_path(ws / "sfm" / "best", folder=True) as tmp:  # a writer that takes a path
        rec.write(tmp)
"""

from __future__ import annotations

import contextlib
import errno
import json
import os
import shutil
from collections.abc import Iterator
from pathlib import Path

PARTIAL = ".partial"
"""The suffix of a temporary name (:func:`partial_path`)."""

DISK_FULL_ERRNOS = frozenset(e for e in (errno.ENOSPC, getattr(errno, "EDQUOT", None)) if e is not None)
"""The errnos of a full disk or quota."""

DISK_FULL_WORDS = ("No space left on device", "Disk quota exceeded", "database or disk is full")
"""How a full disk reads in the messages of writers that lose the errno (COLMAP's log, SQLite)."""


class DiskFull(OSError):
    """A write stopped by a full disk or quota: ``filename`` is the file it was writing, ``size`` its size in bytes
    when known (None otherwise)."""

    def __init__(self, code: int, path: Path | str, size: int | None = None):
        super().__init__(code, os.strerror(code), str(path))
        self.size = size


def is_disk_full(exc: BaseException) -> bool:
    """Whether ``exc`` (or an exception it was raised from) is a full disk or quota: its errno, or the words COLMAP
    and SQLite say it with."""
    seen = set()
    while exc is not None and id(exc) not in seen:
        seen.add(id(exc))
        if isinstance(exc, OSError) and exc.errno in DISK_FULL_ERRNOS:
            return True
        if any(w in str(exc) for w in DISK_FULL_WORDS):
            return True
        exc = exc.__cause__ or exc.__context__
    return False


def partial_path(path: Path) -> Path:
    """The temporary name beside ``path`` that this process writes it under."""
    path = Path(path)
    return path.with_name(f".{path.name}.{os.getpid()}{PARTIAL}")


def _remove(p: Path) -> None:
    if p.is_dir() and not p.is_symlink():
        shutil.rmtree(p, ignore_errors=True)
    else:
        with contextlib.suppress(OSError):
            p.unlink()


def _full(exc: OSError, path: Path, size: int | None) -> OSError:
    """``exc`` as a :class:`DiskFull` naming ``path`` (and ``size``, when known) when it is a full disk, else
    itself."""
    if isinstance(exc, DiskFull):
        exc.size = exc.size if exc.size is not None else size
        return exc
    if exc.errno not in DISK_FULL_ERRNOS:
        return exc
    return DiskFull(exc.errno, path, size)


def _reraise(exc: OSError, path: Path, size: int | None):
    full = _full(exc, path, size)
    if full is exc:
        raise exc
    raise full from exc


def replace_folder(src: Path, dst: Path) -> None:
    """Move the finished folder ``src`` to ``dst`` (a folder already there is replaced: moved aside under a temporary
    name first, then removed; a kill between the two renames leaves ``dst`` absent, never half of it)."""
    src, dst = Path(src), Path(dst)
    old = None
    if dst.is_dir() and not dst.is_symlink():
        old = dst.with_name(f".{dst.name}.{os.getpid()}.old{PARTIAL}")
        _remove(old)
        os.replace(dst, old)
    elif dst.exists() or dst.is_symlink():
        dst.unlink()
    os.replace(src, dst)
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)


@contextlib.contextmanager
def atomic_path(path: Path, folder: bool = False) -> Iterator[Path]:
    """A temporary path beside ``path`` for a writer that takes a path (a file, or with ``folder`` a folder the
    writer fills, created empty here), moved over ``path`` when the block ends without an exception and removed
    when it raises. The temporary name has no extension: a writer that infers the format from it needs the format
    given."""
    path = Path(path)
    tmp = partial_path(path)
    _remove(tmp)
    if folder:
        tmp.mkdir(parents=True)
    try:
        yield tmp
        if folder:
            replace_folder(tmp, path)
        else:
            os.replace(tmp, path)
    except OSError as exc:
        _remove(tmp)
        _reraise(exc, path, None)
    except BaseException:
        _remove(tmp)
        raise


@contextlib.contextmanager
def atomic_file(path: Path, mode: str = "wb", **open_kw) -> Iterator:
    """An open file (``mode``: "wb" or "w") whose content becomes ``path`` when the block ends without an exception
    (:func:`atomic_path`)."""
    with atomic_path(path) as tmp, open(tmp, mode, **open_kw) as f:
        yield f


def write_bytes(path: Path, data: bytes) -> None:
    """``data`` to ``path``, atomically; a full disk raises :class:`DiskFull` with the size."""
    try:
        with atomic_file(path) as f:
            f.write(data)
    except OSError as exc:
        _reraise(exc, Path(path), len(data))


def write_text(path: Path, text: str) -> None:
    """``text`` (UTF-8) to ``path``, atomically."""
    write_bytes(path, text.encode("utf-8"))


def write_json(path: Path, obj, **dumps_kw) -> None:
    """``obj`` as JSON to ``path``, atomically (``dumps_kw``: :func:`json.dumps`'s, e.g. ``indent=1``)."""
    write_text(path, json.dumps(obj, **dumps_kw))


def save_npz(path: Path, **arrays) -> None:
    """``np.savez`` of ``arrays`` to ``path`` (exactly that name), atomically."""
    import numpy as np

    with atomic_file(path) as f:
        np.savez(f, **arrays)


def write_image(path: Path, img, params: list[int] | tuple = ()) -> None:
    """``img`` encoded by OpenCV in the format of ``path``'s extension (``params``: ``cv2.imwrite``'s) and written
    atomically. ``cv2.imwrite`` itself reports a full disk only by returning False."""
    import cv2

    ok, buf = cv2.imencode(Path(path).suffix, img, list(params))
    if not ok:
        raise ValueError(f"{path}: OpenCV cannot encode this image as {Path(path).suffix}")
    write_bytes(path, buf.tobytes())


def export_mesh(path: Path, mesh, file_type: str | None = None, **export_kw) -> None:
    """A trimesh mesh or scene exported to ``path`` (``file_type``: the format, else ``path``'s extension;
    ``export_kw``: trimesh's ``export`` options), encoded in memory and written atomically."""
    data = mesh.export(file_type=file_type or Path(path).suffix.lstrip("."), **export_kw)
    write_bytes(path, data.encode("utf-8") if isinstance(data, str) else data)


class _Recording:
    """A binary file for ``torch.save`` that keeps the OSError its writes raised (torch reports a failed write
    as a RuntimeError without the errno)."""

    def __init__(self, f):
        self.f, self.error = f, None

    def write(self, b) -> int:
        try:
            return self.f.write(b)
        except OSError as exc:
            self.error = exc
            raise

    def flush(self) -> None:
        self.f.flush()


def save_torch(obj, path: Path) -> None:
    """``torch.save`` of ``obj`` to ``path``, atomically; a full disk raises :class:`DiskFull`."""
    import torch

    with atomic_file(path) as f:
        out = _Recording(f)
        try:
            torch.save(obj, out)
        except RuntimeError as exc:
            if out.error is not None:
                raise out.error from exc
            raise


def copy_file(src: Path, dst: Path) -> None:
    """A copy of the file ``src`` at ``dst``, atomically (its content; not its times or mode)."""
    with atomic_path(dst) as tmp:
        shutil.copyfile(src, tmp)


FULL_BELOW = 1 << 20
"""Bytes left on a disk below which a writer that reports nothing (COLMAP's) is taken to have filled it."""


def short_write(path: Path) -> OSError:
    """The error for a file or folder a writer that reports nothing left incomplete: :class:`DiskFull` when the
    disk holding it has (almost) no space left (:data:`FULL_BELOW`), else an ``EIO`` OSError naming it."""
    path = Path(path)
    try:
        free = shutil.disk_usage(path if path.exists() else path.parent).free
    except OSError:
        free = None
    if free is not None and free < FULL_BELOW:
        return DiskFull(errno.ENOSPC, path)
    return OSError(errno.EIO, "written incompletely (it does not read back)", str(path))


def check_room(path: Path) -> None:
    """After a writer that says nothing when the disk fills (COLMAP's model and image writers leave their files cut
    short): :class:`DiskFull` naming ``path`` when its disk has (almost) no space left. Reading such a file back is
    no check: a count read from the cut leaves COLMAP's reader allocating gigabytes."""
    err = short_write(path)
    if isinstance(err, DiskFull):
        raise err


def sweep_partials(root: Path) -> int:
    """Remove the temporary files and folders that killed writers left under ``root`` (names from
    :func:`partial_path`); only while no other process writes there (the workspace lock). Returns how many."""
    root = Path(root)
    if not root.is_dir():
        return 0
    found = [p for p in root.rglob(f".*{PARTIAL}") if p.name.startswith(".")]
    for p in sorted(found, key=lambda q: len(q.parts)):  # a folder before what is inside it
        if p.exists() or p.is_symlink():
            _remove(p)
    return len(found)
