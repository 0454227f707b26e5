"""tidee.protocol: the messages, codec, key expressions and clients every tidee process shares.

Importing it (or ``tidee``) registers the Gymnasium environment ``tidee/Tidy-v0`` when
gymnasium is installed (the environment module itself loads only on ``gymnasium.make``).
"""

GYM_ENV_ID = "tidee/Tidy-v0"


def register_gym_env() -> None:
    """Register ``tidee/Tidy-v0`` with Gymnasium (idempotent; a no-op without gymnasium)."""
    try:
        import gymnasium
    except ImportError:
        return
    if GYM_ENV_ID not in gymnasium.registry:
        gymnasium.register(id=GYM_ENV_ID, entry_point="tidee.protocol.gym_env:TidyEnv")


register_gym_env()
