"""uavlae: safe, compliant and economical UAV trajectory planning in low-altitude airspace, on
TorchRL and TensorDict.

Importing the package registers its gymnasium env, so that the id gymnasium documents for a
third-party package works in a fresh interpreter: ``gymnasium.make("uavlae:uavlae/UAV-v0")``
imports ``uavlae`` first, then looks the id up. The entry point is a string: torch and the
physics load on ``make``, not on ``import uavlae``. It also registers the config resolver that
makes default run folders unique.
"""

import os
from importlib.metadata import PackageNotFoundError, version

from omegaconf import OmegaConf

try:
    __version__ = version("uavlae")
except PackageNotFoundError:  # the source folder on sys.path without an install
    __version__ = "0+unknown"

GYM_ID = "uavlae/UAV-v0"
GYM_ENTRY_POINT = "uavlae.envs.gym_adapter:UAVGymEnv"


def register_gym() -> None:
    """Register :class:`uavlae.envs.gym_adapter.UAVGymEnv` with gymnasium as ``"uavlae/UAV-v0"``
    (idempotent; no ``max_episode_steps``: the world truncates itself at ``t_max``)."""
    import gymnasium

    if GYM_ID not in gymnasium.registry:
        gymnasium.register(id=GYM_ID, entry_point=GYM_ENTRY_POINT)


def _unique_token() -> str:
    """Six hex digits drawn once per config (cached): default run folders made in the same
    second still differ."""
    return os.urandom(3).hex()


register_gym()
if not OmegaConf.has_resolver("uavlae.unique"):
    OmegaConf.register_new_resolver("uavlae.unique", _unique_token, use_cache=True)
