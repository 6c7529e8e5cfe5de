"""The world: batched physics, scenarios, the TorchRL env and its gymnasium adapter."""

from uavlae.envs.config import EnvConfig, make_env_config
from uavlae.envs.uav_env import UAVEnv

__all__ = ["EnvConfig", "UAVEnv", "make_env_config"]
