"""Atomic output files: write to a temp file in the same folder, then rename on success.

A write that fails for want of space or permission (a full disk, a read-only or unwritable folder)
becomes one :class:`OutputError` that names the output path and the free space
(:func:`write_error`), and leaves no temp file behind.
"""

from __future__ import annotations

import contextlib
import errno
import os
import shutil
import tempfile
from pathlib import Path
from typing import Iterator

from lcv_replay.errors import OutputError

#: errno values that mean "this output cannot be written here" (not a bug, not bad input).
WRITE_FAILURES = frozenset({errno.ENOSPC, errno.EDQUOT, errno.EFBIG, errno.EROFS, errno.EACCES, errno.EPERM})


def is_write_failure(exc: BaseException) -> bool:
    """True for an ``OSError`` of :data:`WRITE_FAILURES` (full disk, quota, read-only, permission)."""
    return isinstance(exc, OSError) and exc.errno in WRITE_FAILURES


def format_size(size_bytes: int) -> str:
    """``1234567 -> '1.2 MB'`` (decimal units, as ``ros2 bag info``)."""
    size = float(size_bytes)
    for unit in ("B", "kB", "MB", "GB"):
        if size < 1000.0 or unit == "GB":
            return f"{size:.0f} {unit}" if unit == "B" else f"{size:.1f} {unit}"
        size /= 1000.0
    raise AssertionError("unreachable")


def free_space_text(path: str | Path) -> str:
    """``'0 B free of 2.1 MB on /mnt/out'``: the free space of the file system holding ``path``."""
    folder = Path(path)
    while not folder.exists() and folder != folder.parent:
        folder = folder.parent
    try:
        usage = shutil.disk_usage(folder)
    except OSError:
        return "free space unknown"
    return f"{format_size(usage.free)} free of {format_size(usage.total)} on {folder}"


def _nearly_full(folder: Path, slack_bytes: int = 1 << 20) -> bool:
    try:
        return shutil.disk_usage(folder).free < slack_bytes
    except OSError:
        return False


def write_error(path: str | Path, exc: BaseException | None = None, *, what: str = "the file") -> OutputError:
    """The one error for an output that could not be written: the path, the cause and the free space.

    Compute it before removing any temp file, so that the free space is what the write saw.
    """
    path = Path(path)
    folder = path.parent if str(path.parent) else Path(".")
    free = free_space_text(folder)
    code = getattr(exc, "errno", None)
    if code is None and _nearly_full(folder):  # a writer that reports no errno (Rerun's file writer)
        code = errno.ENOSPC
    if code in (errno.ENOSPC, errno.EDQUOT, errno.EFBIG):
        problem, fix = "the disk is full", "free some space there, or write to another folder"
    elif code == errno.EROFS:
        problem, fix = "the file system is read-only", "write to another folder"
    elif code in (errno.EACCES, errno.EPERM):
        problem, fix = "permission denied", "write to a folder you can write to"
    else:
        problem, fix = "the write failed", "check the disk, free some space, or write to another folder"
        cause = getattr(exc, "strerror", None) or (str(exc) if exc is not None else "")
        problem = f"{problem} ({cause})" if cause else problem
    return OutputError(f"cannot write {what}: {problem}, {free}", path=path, fix=fix)


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
        raise OutputError(
            f"output folder is not writable ({free_space_text(folder)})", path=path, fix="choose another output path"
        )
    try:  # os.access trusts the mode bits: /proc or a read-only mount passes it for root
        with tempfile.TemporaryFile(dir=folder):
            pass
    except OSError as exc:
        raise write_error(path, exc) from None
    return path


def make_folder(path: str | Path, *, what: str = "the work folder") -> Path:
    """Create folder ``path`` (and its parents) if needed; returns it as a ``Path``.

    Raises :class:`OutputError` naming the folder when it cannot be created: a write failure
    (:func:`write_error`: full disk, read-only, permission) or a path that cannot hold a folder
    (a parent that is a file, or that cannot be created)."""
    path = Path(path)
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        if is_write_failure(exc):
            raise write_error(path, exc, what=what) from None
        reason = exc.strerror or str(exc)
        raise OutputError(f"cannot create {what} ({reason})", path=path, fix="pass a folder that can be created") from None
    return path


@contextlib.contextmanager
def atomic_output(path: str | Path, *, force: bool = False) -> Iterator[Path]:
    """Yield a temp path next to ``path``; rename it to ``path`` only if the block succeeds.

    On any exception (KeyboardInterrupt included) the temp file is removed and ``path`` is left as
    it was: an interrupted write never leaves a half-written or clobbered output. A write failure
    (:func:`is_write_failure`: a full disk, a read-only folder) is raised as :func:`write_error`.
    """
    path = check_output_path(path, force=force)
    try:
        fd, tmp_name = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent or ".")
    except OSError as exc:  # no file can be created next to the output: it cannot be written
        raise write_error(path, exc) from None
    os.close(fd)
    # mkstemp creates 0600 files; give the output the usual permissions (0666 minus the umask).
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(tmp_name, 0o666 & ~umask)
    tmp = Path(tmp_name)
    try:
        yield tmp
        os.replace(tmp, path)
    except OSError as exc:
        error = write_error(path, exc) if is_write_failure(exc) else None  # the free space before the clean-up
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()
        if error is None:
            raise
        raise error from None
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
