"""Where the commands write: every output path checked before any work, every file written
whole or not at all.

A command that computes for minutes and then finds it cannot write its result has lost the
work, so :func:`check_output` is called on each output path as soon as the arguments are read:
the path must be of the kind expected (a file where a file is expected, a directory where a
directory is), and its directory (or the nearest one that exists, for a path whose parents
the command will make) must accept a new file, found by making and removing one there, which
also catches a read-only mount where permission bits say nothing (as for root).

:func:`write_text` and :func:`save_figure` write through a temporary file in the same
directory and rename it into place, so an error or Ctrl-C part-way leaves the old file or the
new one, never half of either.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import tempfile
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

FILE, DIRECTORY = "file", "directory"


class OutputPathError(ValueError):
    """An output path the command could not write; the message names the option and path."""


def _accepts_files(directory: Path) -> bool:
    try:
        fd, probe = tempfile.mkstemp(prefix=".bayesrob-probe-", dir=directory)
    except OSError:
        return False
    os.close(fd)
    os.unlink(probe)
    return True


def check_output(path: str | Path, kind: str, option: str) -> None:
    """Raise :class:`OutputPathError` unless ``path`` can be written as a ``kind`` (FILE or
    DIRECTORY); ``option`` names it in the message (e.g. ``--json``)."""
    p = Path(path)
    where = f"{option} {path}"
    if kind == FILE and p.is_dir():
        raise OutputPathError(f"{where}: is a directory; give a file name")
    if kind == DIRECTORY and p.exists() and not p.is_dir():
        raise OutputPathError(f"{where}: exists and is not a directory")
    base = p if kind == DIRECTORY and p.is_dir() else p.parent
    existing = next((d for d in (base, *base.parents) if d.exists()), Path.cwd())
    if not existing.is_dir():
        raise OutputPathError(f"{where}: {existing} is a file, so it cannot hold the output")
    if not _accepts_files(existing):
        raise OutputPathError(f"{where}: cannot write in {existing} (read-only or no "
                              "permission)")


def _atomic(path: Path, write: Callable[[Path], Any]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=path.suffix, dir=path.parent)
    os.close(fd)
    try:
        write(Path(tmp))
        os.chmod(tmp, 0o644)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def write_text(path: str | Path, text: str) -> None:
    """Write ``text`` to ``path`` whole: a temporary file in its directory, renamed."""
    _atomic(Path(path), lambda tmp: tmp.write_text(text, encoding="utf-8"))


def save_figure(fig: Any, path: str | Path, **kwargs: Any) -> None:
    """``fig.savefig(path, **kwargs)`` whole; the format is taken from ``path``'s suffix."""
    fmt = kwargs.pop("format", None) or Path(path).suffix.lstrip(".") or None
    _atomic(Path(path), lambda tmp: fig.savefig(tmp, format=fmt, **kwargs))


@contextlib.contextmanager
def staged_directory(directory: str | Path) -> Iterator[Path]:
    """A scratch directory inside ``directory`` to write a command's outputs into; when the
    block ends without an error they are moved into ``directory`` (each a rename, replacing
    what had those names), otherwise the scratch goes and ``directory`` is as it was. So a
    run that fails or is interrupted part-way never leaves its outputs mixed with an earlier
    run's."""
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    scratch = Path(tempfile.mkdtemp(prefix=".bayesrob-staged-", dir=directory))
    try:
        yield scratch
        for item in sorted(scratch.iterdir()):
            target = directory / item.name
            if target.is_dir() and not target.is_symlink():
                old = Path(tempfile.mkdtemp(prefix=".bayesrob-old-", dir=directory))
                os.replace(target, old / item.name)
                os.replace(item, target)
                shutil.rmtree(old, ignore_errors=True)
            else:
                os.replace(item, target)
    finally:
        shutil.rmtree(scratch, ignore_errors=True)
