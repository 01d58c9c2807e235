"""C3 strategy registry: config ``matcher.strategy`` name -> factory (the composition root's only way
to build a matcher).

Built-in: ``classical``, ``disk_lightglue``, ``aliked_lightglue``, ``xfeat``, ``xfeat_mnn`` and
``orientation_corr``; others
join through ``register_strategy``. ``create_matcher`` passes each factory only the dependencies its signature
names, so the composition root can hand every strategy the same superset of shared helpers.
"""

from __future__ import annotations

import inspect
from collections.abc import Callable
from typing import Any

import structlog

from gps_denied_onboard.components.c3_matcher import (
    aliked_lightglue,
    classical,
    disk_lightglue,
    orientation_corr,
    xfeat,
    xfeat_mnn,
)
from gps_denied_onboard.components.c3_matcher.errors import StrategyNotLinkedError
from gps_denied_onboard.components.c3_matcher.protocol import CrossDomainMatcher
from gps_denied_onboard.constants import LogEvent

_LOG = structlog.get_logger(__name__)

MatcherFactory = Callable[..., CrossDomainMatcher]

_STRATEGY_REGISTRY: dict[str, MatcherFactory] = {
    classical.LABEL: classical.create,
    disk_lightglue.LABEL: disk_lightglue.create,
    xfeat.LABEL: xfeat.create,
    aliked_lightglue.LABEL: aliked_lightglue.create,
    xfeat_mnn.LABEL: xfeat_mnn.create,
    orientation_corr.LABEL: orientation_corr.create,
}


def register_strategy(name: str, factory: MatcherFactory) -> None:
    """Add a strategy. Re-registering a name with a different factory is an error (two modules would
    silently fight over one config value)."""
    if not name or not isinstance(name, str):
        raise ValueError(f"strategy name must be a non-empty string, got {name!r}")
    existing = _STRATEGY_REGISTRY.get(name)
    if existing is not None and existing is not factory:
        raise ValueError(f"C3 strategy {name!r} is already registered to {existing!r}")
    _STRATEGY_REGISTRY[name] = factory


def available_strategies() -> tuple[str, ...]:
    return tuple(sorted(_STRATEGY_REGISTRY))


def _factory(name: str) -> MatcherFactory:
    factory = _STRATEGY_REGISTRY.get(name)
    if factory is None:
        raise StrategyNotLinkedError(
            f"C3 matcher strategy {name!r} is not linked; available: {', '.join(available_strategies())}"
        )
    return factory


def takes(name: str, dependency: str) -> bool:
    """Whether strategy ``name``'s factory takes ``dependency`` (e.g. ``lightglue_runtime``), so the
    composition root builds only what the chosen strategy uses. StrategyNotLinkedError for an unknown
    name."""
    factory = _factory(name)
    return dependency in inspect.signature(factory).parameters


def create_matcher(name: str, **deps: Any) -> CrossDomainMatcher:
    """Build the strategy ``name`` from ``deps`` (``config`` = the ``MatcherConfig``, shared helpers).

    Raises ``StrategyNotLinkedError`` (listing the valid names) for an unknown name and ``TypeError``
    when a dependency the factory requires is missing. Logs ``c3.matcher.ready`` once built.
    """
    factory = _factory(name)
    params = inspect.signature(factory).parameters
    if any(p.kind is inspect.Parameter.VAR_KEYWORD for p in params.values()):
        accepted = deps
    else:
        accepted = {k: v for k, v in deps.items() if k in params}
    missing = [
        p.name
        for p in params.values()
        if p.default is inspect.Parameter.empty
        and p.kind in (inspect.Parameter.POSITIONAL_OR_KEYWORD, inspect.Parameter.KEYWORD_ONLY)
        and p.name not in accepted
    ]
    if missing:
        raise TypeError(f"C3 strategy {name!r} needs {missing}; given {sorted(deps)}")
    matcher = factory(**accepted)
    if not isinstance(matcher, CrossDomainMatcher):
        raise TypeError(
            f"factory for C3 strategy {name!r} returned {type(matcher).__name__}, not a CrossDomainMatcher"
        )
    config = deps.get("config")
    _LOG.info(
        LogEvent.C3_READY,
        strategy=name,
        min_inliers_threshold=getattr(config, "min_inliers_threshold", None),
        residual_warn_threshold_px=getattr(config, "residual_warn_threshold_px", None),
        # "lightglue" (a matcher model) or "mutual_nn" (no matcher model given): what matches the features
        # (None: the strategy takes no LightGlue helper and matches by its own rule).
        pair_matcher=getattr(accepted.get("lightglue_runtime"), "mode", None),
    )
    return matcher
