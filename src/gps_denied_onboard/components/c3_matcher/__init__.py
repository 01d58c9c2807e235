"""C3 cross-domain matcher: nav frame vs the top-N map chips -> RANSAC-filtered correspondences.

Public surface: the ``CrossDomainMatcher`` protocol, its DTOs and errors, the shared
``RollingHealthWindow``, and the strategy registry (``create_matcher``). Strategies live in their own
modules (``classical``, ``disk_lightglue``) and share one per-candidate loop (``base``).
"""

from gps_denied_onboard.components.c3_matcher.errors import (
    InsufficientInliersError,
    MatcherBackboneError,
    MatcherError,
    StrategyNotLinkedError,
)
from gps_denied_onboard.components.c3_matcher.health import RollingHealthWindow
from gps_denied_onboard.components.c3_matcher.protocol import CrossDomainMatcher
from gps_denied_onboard.components.c3_matcher.registry import (
    _STRATEGY_REGISTRY,
    available_strategies,
    create_matcher,
    register_strategy,
)
from gps_denied_onboard.components.c3_matcher.types import CandidateMatchSet, MatcherHealth, MatchResult

__all__ = [
    "_STRATEGY_REGISTRY",
    "CandidateMatchSet",
    "CrossDomainMatcher",
    "InsufficientInliersError",
    "MatchResult",
    "MatcherBackboneError",
    "MatcherError",
    "MatcherHealth",
    "RollingHealthWindow",
    "StrategyNotLinkedError",
    "available_strategies",
    "create_matcher",
    "register_strategy",
]
