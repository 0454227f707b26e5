"""tidee.protocol: the messages, codec, key expressions and clients every tidee process shares.

Importing it registers the Gymnasium environment ``tidee/Tidy-v0`` when gymnasium is
installed (the environment module itself loads only on ``gymnasium.make``).
"""


def _register_gym_env() -> None:
    try:
        import gymnasium
    except ImportError:
        return
    if "tidee/Tidy-v0" not in gymnasium.registry:
        gymnasium.register(id="tidee/Tidy-v0", entry_point="tidee.protocol.gym_env:TidyEnv")


_register_gym_env()
