"""Registry of verification methods: ``ilv``, ``ilv+`` and the baselines share one factory signature.

A module registers a factory with::

    @register("ilv", help="paper-faithful multi-model hypothesize-and-verify")
    def _make(config: VerificationConfig, *, odometry_information: np.ndarray | None) -> Verifier: ...

and callers build any method the same way with :func:`make_verifier`.
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass
from typing import Callable

from lcv_replay.errors import ConfigError
from lcv_replay.verification.base import Verifier
from lcv_replay.verification.config import VerificationConfig

Factory = Callable[..., Verifier]

# Modules imported on first use so that registering methods never slows down ``--help``.
_METHOD_MODULES = ("lcv_replay.verification.ilv", "lcv_replay.verification.baselines")


@dataclass(frozen=True)
class MethodInfo:
    name: str
    help: str
    factory: Factory


_REGISTRY: dict[str, MethodInfo] = {}


def register(name: str, *, help: str) -> Callable[[Factory], Factory]:
    def decorator(factory: Factory) -> Factory:
        _REGISTRY[name] = MethodInfo(name, help, factory)
        return factory

    return decorator


def _load_all() -> None:
    for module in _METHOD_MODULES:
        importlib.import_module(module)


def available_methods() -> dict[str, MethodInfo]:
    """Every registered method by name."""
    _load_all()
    return dict(_REGISTRY)


def make_verifier(method: str, config: VerificationConfig, *, odometry_information=None) -> Verifier:
    """Build verifier ``method`` (e.g. ``"ilv"``, ``"ilv+"``, ``"gnc"``) from ``config``.

    Args:
        odometry_information: ``(3, 3)`` information matrix of one odometry step, if the log
            carries one (g2o logs do, in the ``lcv`` metadata); else the config's default is used.
    """
    methods = available_methods()
    if method not in methods:
        raise ConfigError(
            f"unknown verification method '{method}'",
            fix=f"use one of {', '.join(sorted(methods))}",
        )
    return methods[method].factory(config, odometry_information=odometry_information)
