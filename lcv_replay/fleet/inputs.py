"""A batch's inputs: LOGS (MCAP files, folders, glob patterns) to logs with unique names.

Pure file-system code, no Ray and no replay. The log hash of resume is the descriptor cache's
content key (:func:`lcv_replay.retrieval.cache.log_cache_key`, BLAKE2b of the file's bytes), so
one digest serves both.
"""

from __future__ import annotations

import glob
import hashlib
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable, Sequence

from lcv_replay.errors import FleetError

LOG_SUFFIX = ".mcap"
_GLOB_CHARS = frozenset("*?[")


@dataclass(frozen=True)
class FleetLog:
    """One log of a batch.

    Attributes:
        path: the log, absolute (tasks on other nodes get this path: it must be on shared storage).
        name: its folder under ``RUN_DIR/logs/``: the file stem, with a short hash of the path when
            two logs share a stem.
    """

    path: Path
    name: str


@dataclass(frozen=True)
class FileStat:
    """Size and modification time of a file: the cheap check before re-hashing it on resume."""

    size_bytes: int
    mtime_ns: int

    @classmethod
    def of(cls, path: Path) -> "FileStat":
        st = path.stat()
        return cls(st.st_size, st.st_mtime_ns)


def is_glob(pattern: str) -> bool:
    return any(ch in _GLOB_CHARS for ch in pattern)


def _folder_logs(folder: Path, exclude: Path | None) -> list[Path]:
    """``*.mcap`` under ``folder`` (recursively, sorted), skipping hidden files and ``exclude``."""
    found = []
    for path in sorted(folder.rglob(f"*{LOG_SUFFIX}")):
        if path.name.startswith(".") or not path.is_file():
            continue
        if exclude is not None and path.resolve().is_relative_to(exclude):
            continue
        found.append(path)
    return found


def expand_inputs(patterns: Sequence[str | os.PathLike], *, exclude: Path | None = None) -> list[Path]:
    """MCAP files, folders (searched recursively for ``*.mcap``) and glob patterns (``**`` allowed)
    to absolute paths, in the order given, each once.

    Args:
        exclude: a folder whose files are never inputs (the batch's own output folder).

    Raises:
        FleetError: a path that is neither a glob nor an existing file or folder; nothing matched.
    """
    exclude = None if exclude is None else exclude.resolve()
    seen: set[Path] = set()
    out: list[Path] = []

    def add(paths: Iterable[Path]) -> None:
        for path in paths:
            resolved = path.resolve()
            if resolved not in seen:
                seen.add(resolved)
                out.append(resolved)

    for raw in patterns:
        text = os.fspath(raw)
        if is_glob(text) and not Path(text).exists():
            for match in sorted(glob.glob(text, recursive=True)):
                path = Path(match)
                add(_folder_logs(path, exclude) if path.is_dir() else [path] if path.is_file() else [])
            continue
        path = Path(text)
        if path.is_dir():
            add(_folder_logs(path, exclude))
        elif path.is_file():
            add([path])
        else:
            raise FleetError("no such file or folder", path=path, fix="pass MCAP files, folders holding *.mcap, or quoted glob patterns")
    if not out:
        shown = ", ".join(repr(os.fspath(p)) for p in patterns[:5]) + (", ..." if len(patterns) > 5 else "")
        raise FleetError(
            f"no logs matched {shown}",
            fix="pass MCAP files, folders holding *.mcap (searched recursively), or glob patterns such as 'logs/**/*.mcap'",
        )
    return out


def _safe(stem: str) -> str:
    return "".join(ch if ch.isalnum() or ch in "-_.+" else "_" for ch in stem) or "log"


def name_logs(paths: Sequence[Path]) -> tuple[FleetLog, ...]:
    """Give each log a unique folder name: its stem, plus ``-<8 hex of the path's hash>`` when stems
    collide (stable whatever else is in the batch, so a resumed run finds the same folders)."""
    stems = [_safe(Path(p).stem) for p in paths]
    counts: dict[str, int] = {}
    for stem in stems:
        counts[stem.lower()] = counts.get(stem.lower(), 0) + 1
    logs = []
    for path, stem in zip(paths, stems):
        if counts[stem.lower()] > 1:
            stem = f"{stem}-{hashlib.sha1(str(path).encode()).hexdigest()[:8]}"
        logs.append(FleetLog(Path(path), stem))
    return tuple(logs)


def discover_logs(patterns: Sequence[str | os.PathLike], *, exclude: Path | None = None) -> tuple[FleetLog, ...]:
    """:func:`expand_inputs` then :func:`name_logs`."""
    return name_logs(expand_inputs(patterns, exclude=exclude))

