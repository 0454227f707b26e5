"""tidee: an embodied agent that tidies messy rooms (TIDEE, ECCV 2022) on PyBullet + Zenoh.

``import tidee`` registers the Gymnasium environment ``tidee/Tidy-v0``, so
``gymnasium.make("tidee/Tidy-v0", transport="inproc")`` works right after it. The import
is cheap: neither torch nor pybullet loads until an environment or agent is built.
"""

from tidee.protocol import GYM_ENV_ID, register_gym_env

register_gym_env()  # tidee.protocol registers on import too; calling it here says why we import it

__all__ = ["GYM_ENV_ID", "register_gym_env"]
