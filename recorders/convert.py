"""Bags replayed directly (``lcv-replay BAG``): convert once, cache by content and options, replay.

``lcv-replay BAG [topic options]`` runs :func:`converted_log` before the replay: it imports the bag
with :func:`recorders.rosbag.record_rosbag` into
``$LCV_CACHE_DIR/converted`` (else ``$XDG_CACHE_HOME/lcv-replay/converted``, i.e.
``~/.cache/lcv-replay/converted``), named after the bag and a key: the BLAKE2b digest of the bag's
bytes, the import options and the lcv-replay version and log format. The same bag with the same
options is converted once; a changed byte or option gives a new key. With ``keep_converted`` the log
goes beside the input instead, as ``NAME.lcv.mcap``, and is reused when its stored key matches.

The conversion is written atomically (temp file and rename), so two replays of the same bag at the
same time cannot leave a half-written cache entry.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

from lcv_replay.errors import RecorderError
from recorders.bags import BagSource, resolve_source
from recorders.common import ProgressCallback
from recorders.rosbag import RosbagOptions, record_rosbag

log = logging.getLogger(__name__)

_DIGEST_BLOCK = 1 << 22
#: The recorder-config entry of a converted log that holds its conversion key.
KEY_ENTRY = "conversion_key"


@dataclass(frozen=True)
class ConvertedLog:
    """A bag's lcv-replay log: where it is, whether it was already there, and its key."""

    path: Path
    reused: bool
    key: str
    source: BagSource


def cache_dir() -> Path:
    """``$LCV_CACHE_DIR/converted``, else ``$XDG_CACHE_HOME/lcv-replay/converted`` (``~/.cache/...``)."""
    if os.environ.get("LCV_CACHE_DIR"):
        return Path(os.environ["LCV_CACHE_DIR"]) / "converted"
    base = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache")
    return base / "lcv-replay" / "converted"


def conversion_key(source: BagSource, options: RosbagOptions) -> str:
    """BLAKE2b (16 bytes) of the bag's data files, the import options, the version and the log format."""
    from lcv_replay import __version__
    from lcv_replay.log.format import FORMAT_VERSION

    digest = hashlib.blake2b(digest_size=16)
    digest.update(json.dumps({"lcv_replay": __version__, "format": FORMAT_VERSION, "options": options.topic_options()},
                             sort_keys=True, default=str).encode())
    for path in source.files:
        try:
            with open(path, "rb") as f:
                digest.update(str(os.fstat(f.fileno()).st_size).encode())
                while block := f.read(_DIGEST_BLOCK):
                    digest.update(block)
        except OSError as exc:
            raise RecorderError(f"cannot read the bag to key its conversion: {exc.strerror}", path=path) from None
    return digest.hexdigest()


def _stored_key(path: Path) -> str | None:
    from lcv_replay.errors import LogFormatError
    from lcv_replay.log.reader import open_log

    try:
        with open_log(path) as reader:
            return reader.info.recorder_config.get(KEY_ENTRY)
    except LogFormatError:
        return None


def converted_log(
    paths: Sequence[str | Path],
    options: RosbagOptions,
    *,
    keep_converted: bool = False,
    progress: ProgressCallback | None = None,
) -> ConvertedLog:
    """The lcv-replay log of a bag: from the cache (or beside the bag), converting it first if needed.

    Raises:
        RecorderError: the bag is unreadable, a topic is missing or ambiguous (the message names
            the option to pass), or ``NAME.lcv.mcap`` beside the bag is some other file.
    """
    source = resolve_source(paths)
    key = conversion_key(source, options)
    if keep_converted:
        target = source.beside / f"{source.name}.lcv.mcap"
        if target.exists():
            stored = _stored_key(target)
            if stored == key:
                return ConvertedLog(target, True, key, source)
            if stored is None:
                raise RecorderError(
                    "exists and is not a conversion of a bag by lcv-replay",
                    path=target, fix="move it away, or drop --keep-converted",
                )
            log.info("%s converts %s with other options or from another version: converting again", target, source.display)
    else:
        folder = cache_dir()
        target = folder / f"{source.name}-{key}.mcap"
        if target.is_file():
            return ConvertedLog(target, True, key, source)
        try:
            folder.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise RecorderError(f"cannot create the conversion cache: {exc.strerror}", path=folder,
                                fix="set LCV_CACHE_DIR to a writable folder, or pass --keep-converted") from None
    record_rosbag(list(source.paths), target, options, force=True, progress=progress, extra_config={KEY_ENTRY: key})
    return ConvertedLog(target, False, key, source)
