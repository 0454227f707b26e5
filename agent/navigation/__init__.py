"""Navigation: fast-marching geodesic planning (``fmm``) and exploration goals (``explore``)."""

from tidee.agent.navigation.explore import (
    FrontierCluster,
    FrontierExplorer,
    sample_reachable_goal,
    sample_unexplored_goal,
    unexplored_fraction,
)
from tidee.agent.navigation.fmm import FMMPlanner, NavStatus

__all__ = [
    "FMMPlanner",
    "NavStatus",
    "FrontierCluster",
    "FrontierExplorer",
    "sample_reachable_goal",
    "sample_unexplored_goal",
    "unexplored_fraction",
]
