"""Atomic file output: write a temporary file beside the target, then rename it over the target.

A reader (or a resumed study) never sees a half-written file: either the old content or the new.

* :func:`atomic_target`: the one temporary-file-and-rename, for any writer that takes a path
  (NumPy, pandas, CasADi); :func:`write_text_atomic`, :func:`write_bytes_atomic`,
  :func:`write_csv_atomic`, :func:`export_mesh_atomic` and :func:`save_figure_atomic` are built on it.
* :func:`staged_directory`: the outputs of one command.  Everything is written into a hidden
  staging directory inside the output directory; only when all of it is written is each file
  renamed into place (``os.replace``, atomic per file).  A failure (an exception, a full disk, an
  interrupt) removes the staging directory and leaves the output directory as it was (and removes
  it if this command created it).  Write errors become one-line :class:`InputError` naming the
  path and the ``--out`` option.
"""

from __future__ import annotations

import contextlib
import os
import shutil
from collections.abc import Iterator
from pathlib import Path

from kneenlp.base.errors import InputError

#: Prefix of temporary files and staging directories; stale staging directories (of a killed
#: process) are removed by the next command writing into the same directory.
TMP_PREFIX = ".kneenlp-tmp-"


def _tmp_name(path: Path) -> Path:
    return path.with_name(f".{path.name}.{os.getpid()}.tmp")


@contextlib.contextmanager
def atomic_target(path: str | Path) -> Iterator[Path]:
    """A temporary path beside ``path`` to write to; renamed over ``path`` when the block ends
    without an error, removed in every case otherwise."""
    path = Path(path)
    tmp = _tmp_name(path)
    try:
        yield tmp
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def write_text_atomic(path: str | Path, text: str) -> Path:
    """Write ``text`` to ``path`` atomically (temporary file in the same directory + rename)."""
    return write_bytes_atomic(path, text.encode())


def write_bytes_atomic(path: str | Path, data: bytes) -> Path:
    """Write ``data`` to ``path`` atomically (temporary file in the same directory + rename)."""
    with atomic_target(path) as tmp, open(tmp, "wb") as fh:
        fh.write(data)
        fh.flush()
        os.fsync(fh.fileno())
    return Path(path)


def write_csv_atomic(table, path: str | Path, **kwargs) -> Path:
    """``table.to_csv(path, **kwargs)`` (a pandas frame) atomically."""
    return write_text_atomic(path, table.to_csv(**kwargs))


def export_mesh_atomic(mesh, path: str | Path) -> Path:
    """``mesh.export(path)`` (a trimesh mesh; format from the suffix of ``path``) atomically."""
    path = Path(path)
    with atomic_target(path) as tmp:
        mesh.export(tmp, file_type=path.suffix.lstrip("."))
    return path


def save_figure_atomic(fig, path: str | Path, **kwargs) -> Path:
    """``fig.savefig(path)`` through a temporary file (format from the suffix of ``path``)."""
    path = Path(path)
    with atomic_target(path) as tmp:
        fig.savefig(tmp, format=path.suffix.lstrip(".") or "png", **kwargs)
    return path


def write_error(exc: OSError, path: str | Path, option: str | None = "--out") -> InputError:
    """An output that cannot be written, as a one-line input error naming the path and option."""
    why = exc.strerror or type(exc).__name__
    where = exc.filename if exc.filename else path
    return InputError(f"cannot write {where} ({why})", source=str(path), field=option)


def remove_stale(directory: Path) -> None:
    """Remove the staging directories in ``directory`` of processes that are gone (killed before
    they could clean up)."""
    for stale in directory.glob(f"{TMP_PREFIX}*"):
        suffix = stale.name.removeprefix(TMP_PREFIX)
        if stale.is_dir() and suffix.isdigit() and not _alive(int(suffix)):
            shutil.rmtree(stale, ignore_errors=True)


def _alive(pid: int) -> bool:
    """Whether process ``pid`` exists (on this machine)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except (PermissionError, OverflowError):
        return True
    return True


class Staging:
    """The staging directory of :func:`staged_directory`: ``path`` to write into, ``final(p)`` the
    place a staged file ends up."""

    def __init__(self, out: Path, path: Path):
        self.out, self.path = out, path

    def final(self, p: str | Path) -> Path:
        p = Path(p)
        try:
            return self.out / p.relative_to(self.path)
        except ValueError:
            return p


@contextlib.contextmanager
def staged_directory(out: str | Path, option: str | None = "--out") -> Iterator[Staging]:
    """Write a command's outputs into ``out`` all at once (see module docstring)."""
    out = Path(out)
    created = [d for d in (out, *out.parents) if not d.exists()]  # removed again on failure
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise write_error(exc, out, option) from None
    if not out.is_dir():
        raise InputError("exists and is not a directory", source=str(out), field=option)
    stage = out / f"{TMP_PREFIX}{os.getpid()}"
    done = False
    try:
        remove_stale(out)
        shutil.rmtree(stage, ignore_errors=True)
        stage.mkdir()
        yield Staging(out, stage)
        files = sorted(p.relative_to(stage) for p in stage.rglob("*") if not p.is_dir())
        for rel in files:  # check every target before moving any: all files or none
            blocking = [out / a for a in rel.parents if a != Path(".") and (out / a).exists()
                        and not (out / a).is_dir()]
            if (out / rel).is_dir() or blocking:
                raise InputError(f"cannot write {out / rel}: {(blocking or [out / rel])[0]} is in the way",
                                 source=str(out), field=option)
        for rel in files:
            (out / rel).parent.mkdir(parents=True, exist_ok=True)
            os.replace(stage / rel, out / rel)
        done = True
    except OSError as exc:
        raise write_error(exc, out, option) from None
    except InputError as exc:  # about a staged file (a written file read back): name where it was to go
        if stage.as_posix() not in f"{exc.source} {exc.message}":
            raise
        raise InputError(exc.message.replace(stage.as_posix(), out.as_posix()),
                         source=exc.source and exc.source.replace(stage.as_posix(), out.as_posix()),
                         field=exc.field) from None
    finally:
        shutil.rmtree(stage, ignore_errors=True)
        for d in created if not done else []:
            with contextlib.suppress(OSError):
                d.rmdir()  # only if empty
