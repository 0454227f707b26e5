"""Navigation: fast-marching geodesic planning (``fmm``) and exploration goals (``explore``)."""

from tidee.agent.navigation.explore import (
    FrontierCluster,
    FrontierExplorer,
    sample_reachable_goal,
    sample_unexplored_goal,
    unexplored_fraction,
)
from tidee.agent.navigation.fmm import FMMPlanner, Grid2D, GridLike, NavStatus

__all__ = [
    "FMMPlanner",
    "Grid2D",
    "GridLike",
    "NavStatus",
    "FrontierCluster",
    "FrontierExplorer",
    "sample_reachable_goal",
    "sample_unexplored_goal",
    "unexplored_fraction",
]
