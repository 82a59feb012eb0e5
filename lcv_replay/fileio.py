"""Atomic output files: write to a temp file in the same folder, then rename on success."""

from __future__ import annotations

import contextlib
import os
import tempfile
from pathlib import Path
from typing import Iterator

from lcv_replay.errors import OutputError


def check_output_path(path: str | Path, *, force: bool = False) -> Path:
    """Validate an output path before any work starts; returns it as a ``Path``.

    Raises :class:`OutputError` when the file exists (and ``force`` is false), when its folder does
    not exist, or when the folder is not writable.
    """
    path = Path(path)
    if path.exists() and not force:
        raise OutputError("output file already exists", path=path, fix="pass --force to overwrite it")
    if path.is_dir():
        raise OutputError("output path is a folder", path=path, fix="name a file")
    folder = path.parent if str(path.parent) else Path(".")
    if not folder.is_dir():
        raise OutputError("output folder does not exist", path=path, fix=f"create {folder} first")
    if not os.access(folder, os.W_OK):
        raise OutputError("output folder is not writable", path=path, fix="choose another output path")
    return path


@contextlib.contextmanager
def atomic_output(path: str | Path, *, force: bool = False) -> Iterator[Path]:
    """Yield a temp path next to ``path``; rename it to ``path`` only if the block succeeds.

    On any exception (KeyboardInterrupt included) the temp file is removed and ``path`` is left as
    it was: an interrupted write never leaves a half-written or clobbered output.
    """
    path = check_output_path(path, force=force)
    fd, tmp_name = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent or ".")
    os.close(fd)
    # mkstemp creates 0600 files; give the output the usual permissions (0666 minus the umask).
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(tmp_name, 0o666 & ~umask)
    tmp = Path(tmp_name)
    try:
        yield tmp
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()
        raise


def write_text_atomic(path: str | Path, text: str, *, force: bool = True) -> Path:
    """Write ``text`` to ``path`` atomically (overwriting by default: summaries, JSON reports)."""
    with atomic_output(path, force=force) as tmp:
        tmp.write_text(text, encoding="utf-8")
    return Path(path)


def user_cache_dir(name: str) -> Path:
    """``$LCV_CACHE_DIR/name``, else ``$XDG_CACHE_HOME/lcv-replay/name`` (``~/.cache/lcv-replay/name``)."""
    if os.environ.get("LCV_CACHE_DIR"):
        return Path(os.environ["LCV_CACHE_DIR"]) / name
    return Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "lcv-replay" / name
