"""tidee.protocol: the messages, codec, key expressions and clients every tidee process shares.

Importing it (or ``tidee``) registers the Gymnasium environments ``tidee/Tidy-v0`` and
``tidee/Rearrange-v0`` when gymnasium is installed (the environment module itself loads
only on ``gymnasium.make``).
"""

GYM_ENV_ID = "tidee/Tidy-v0"
REARRANGE_ENV_ID = "tidee/Rearrange-v0"


def register_gym_env() -> None:
    """Register ``tidee/Tidy-v0`` and ``tidee/Rearrange-v0`` with Gymnasium (idempotent; a
    no-op without gymnasium)."""
    try:
        import gymnasium
    except ImportError:
        return
    for env_id, cls in ((GYM_ENV_ID, "TidyEnv"), (REARRANGE_ENV_ID, "RearrangeEnv")):
        if env_id not in gymnasium.registry:
            gymnasium.register(id=env_id, entry_point=f"tidee.protocol.gym_env:{cls}")


register_gym_env()
