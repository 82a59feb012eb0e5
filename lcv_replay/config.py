"""One typed config tree, loaded and validated once, written into every result.

Each stage owns its section as a frozen dataclass whose defaults are the paper's values, with a
comment citing the section (Tanaka, SII 2016). This module composes them into
:class:`ReplayConfig` and converts to and from TOML-like dicts:

* unknown keys are refused by name (``verification.windw_frames``: did you mean ``window_frames``?);
* values are type-checked against the field annotation (int, float, bool, str, Literal, tuples);
* each section validates its ranges in ``__post_init__`` and raises :class:`ConfigError`.
"""

from __future__ import annotations

import dataclasses
import difflib
import tomllib
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal, TypeVar, get_args, get_origin, get_type_hints

from lcv_replay.errors import ConfigError
from lcv_replay.retrieval.config import RetrievalConfig
from lcv_replay.sinks.config import RerunConfig
from lcv_replay.verification.config import VerificationConfig
from lcv_replay.vo.config import VoConfig

T = TypeVar("T")


@dataclass(frozen=True)
class ReplayConfig:
    """The whole configuration of a replay (``lcv-replay LOG.mcap --config FILE.toml``)."""

    retrieval: RetrievalConfig = field(default_factory=RetrievalConfig)
    verification: VerificationConfig = field(default_factory=VerificationConfig)
    rerun: RerunConfig = field(default_factory=RerunConfig)
    vo: VoConfig = field(default_factory=VoConfig)  # stereo VO ('lcv-replay vo', record --vo); not used by the replay


def from_dict(cls: type[T], data: dict[str, Any], *, where: str = "", path: Path | None = None) -> T:
    """Build the dataclass ``cls`` from a (TOML) dict, refusing unknown keys and wrong types."""
    if not isinstance(data, dict):
        raise ConfigError(f"config section '{where or '<root>'}' must be a table", path=path)
    hints = get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls) if f.init}
    kwargs: dict[str, Any] = {}
    for key, value in data.items():
        dotted = f"{where}.{key}" if where else key
        if key not in fields:
            close = difflib.get_close_matches(key, list(fields), n=1)
            hint = f"did you mean '{close[0]}'?" if close else f"known keys: {', '.join(sorted(fields))}"
            raise ConfigError(f"unknown config key '{dotted}'", path=path, fix=hint)
        kwargs[key] = _convert(hints[key], value, dotted, path)
    try:
        return cls(**kwargs)
    except ConfigError as exc:
        if path is not None and exc.path is None:
            raise ConfigError(exc.message, path=path, fix=exc.fix) from None
        raise


def _convert(annotation: Any, value: Any, key: str, path: Path | None) -> Any:
    origin = get_origin(annotation)
    if dataclasses.is_dataclass(annotation):
        return from_dict(annotation, value, where=key, path=path)
    if origin is Literal:
        choices = get_args(annotation)
        if value not in choices:
            raise ConfigError(
                f"config key '{key}' = {value!r} is not allowed",
                path=path,
                fix=f"use one of {', '.join(map(repr, choices))}",
            )
        return value
    if origin in (typing.Union, getattr(__import__("types"), "UnionType", None)):
        options = get_args(annotation)
        if value is None and type(None) in options:
            return None
        errors = []
        for option in options:
            if option is type(None):
                continue
            try:
                return _convert(option, value, key, path)
            except ConfigError as exc:
                errors.append(exc)
        raise errors[0] if errors else ConfigError(f"config key '{key}' has a bad value", path=path)
    if origin is tuple:
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"config key '{key}' = {value!r} must be an array", path=path)
        args = get_args(annotation)
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(_convert(args[0], v, key, path) for v in value)
        if len(args) != len(value):
            raise ConfigError(f"config key '{key}' must have {len(args)} elements", path=path)
        return tuple(_convert(a, v, key, path) for a, v in zip(args, value))
    if annotation is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"config key '{key}' = {value!r} must be a number", path=path)
        return float(value)
    if annotation is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"config key '{key}' = {value!r} must be an integer", path=path)
        return value
    if annotation is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"config key '{key}' = {value!r} must be true or false", path=path)
        return value
    if annotation is str:
        if not isinstance(value, str):
            raise ConfigError(f"config key '{key}' = {value!r} must be a string", path=path)
        return value
    return value


def to_dict(config: Any) -> dict[str, Any]:
    """The config as plain dicts/lists (TOML/JSON-ready), e.g. for the .rrd and summary."""
    def plain(v: Any) -> Any:
        if dataclasses.is_dataclass(v):
            return {f.name: plain(getattr(v, f.name)) for f in dataclasses.fields(v)}
        if isinstance(v, tuple):
            return [plain(x) for x in v]
        return v

    return plain(config)


def load_config(path: str | Path | None) -> ReplayConfig:
    """Load ``path`` (TOML) over the paper defaults; ``None`` gives the defaults."""
    if path is None:
        return ReplayConfig()
    path = Path(path)
    if not path.is_file():
        raise ConfigError("config file not found", path=path, fix="pass an existing TOML file")
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise ConfigError(f"not valid TOML: {exc}", path=path, fix="fix the syntax") from None
    return from_dict(ReplayConfig, data, path=path)


def replace_in(config: T, **overrides: Any) -> T:
    """``dataclasses.replace`` that skips ``None`` overrides (CLI options left unset)."""
    given = {k: v for k, v in overrides.items() if v is not None}
    return dataclasses.replace(config, **given) if given else config
