"""Learners on torchrl.objectives, one module each; ``make_learner`` dispatches on ``cfg.name``.

Every learner follows :class:`Learner`: ``actor`` (evaluated and deployed, deterministically),
``behaviour`` (what acts while collecting), ``off_policy``, ``anneal(frames)`` (the schedules
that follow training progress), ``update(batch) -> dict[str, float]``, ``state_dict()`` /
``load_state_dict()``. Off-policy (sac, sac_lag, ddpg, crossq): ``batch`` is a replay sample ``[N]``; on-policy
(ppo, cpo, wang, theile): a collector batch ``[*B, T]``, time last.
"""

from __future__ import annotations

from typing import Any, Protocol

from tensordict import TensorDictBase
from torchrl.data import TensorSpec

from uavlae.algos.crossq import CrossQ, CrossQConfig, make_crossq, make_crossq_config
from uavlae.algos.ddpg import DDPG, DDPGConfig, make_ddpg, make_ddpg_config
from uavlae.algos.ppo import PPO, PPOConfig, make_ppo, make_ppo_config
from uavlae.algos.ppo_lagrangian import (
    CPOConfig, LagrangeMultiplier, PPOLagrangian, make_cpo_config, make_ppo_lagrangian,
)
from uavlae.algos.sac import SAC, SACConfig, make_sac, make_sac_config
from uavlae.algos.sac_lag import SACLag, SACLagConfig, make_sac_lag, make_sac_lag_config
from uavlae.algos.theile import Theile, TheileConfig, make_theile, make_theile_config
from uavlae.algos.wang import Wang, WangConfig, make_wang, make_wang_config

MAKERS = {"sac": make_sac, "sac_lag": make_sac_lag, "ddpg": make_ddpg, "ppo": make_ppo, "cpo": make_ppo_lagrangian,
          "wang": make_wang, "theile": make_theile, "crossq": make_crossq}
# each learner's config alone (validated before anything is built)
CONFIG_MAKERS = {"sac": make_sac_config, "sac_lag": make_sac_lag_config, "ddpg": make_ddpg_config,
                 "ppo": make_ppo_config, "cpo": make_cpo_config, "wang": make_wang_config,
                 "theile": make_theile_config, "crossq": make_crossq_config}
# cut the observation into entities (wang) or find its maps (theile): need the env's ObservationLayout
NEEDS_LAYOUT = frozenset({"wang", "theile"})
OFF_POLICY = frozenset({"sac", "sac_lag", "ddpg", "crossq"})


class Learner(Protocol):
    """What the training loop, the evaluator and the checkpoints need of a learner."""

    off_policy: bool  # True: update() takes replay samples, the loop keeps a replay buffer
    actor: Any  # the policy evaluated and deployed (deterministic under ExplorationType.DETERMINISTIC)

    @property
    def behaviour(self) -> Any:
        """The policy that acts while collecting (DDPG: the actor with its exploration noise)."""

    def anneal(self, frames: int) -> None:
        """Told the frames collected so far before its updates (noise, cloning weight)."""

    def update(self, batch: TensorDictBase) -> dict[str, float]: ...

    def state_dict(self) -> dict[str, Any]: ...

    def load_state_dict(self, state: dict[str, Any]) -> None: ...


def make_learner(cfg: Any, obs_dim: int, action_spec: TensorSpec, layout: Any = None) -> Learner:
    """Build the learner named by ``cfg["name"]`` (a conf/algo/*.yaml node or a mapping);
    ``layout``: the env's ``ObservationLayout``, read by the learners in ``NEEDS_LAYOUT``."""
    name = cfg.name if hasattr(cfg, "name") else cfg["name"]
    if name not in MAKERS:
        raise ValueError(f"algo.name must be one of {sorted(MAKERS)}, got {name!r}")
    if name in NEEDS_LAYOUT:
        return MAKERS[name](cfg, obs_dim, action_spec, layout)
    return MAKERS[name](cfg, obs_dim, action_spec)


__all__ = [
    "CONFIG_MAKERS",
    "CPOConfig",
    "CrossQ",
    "CrossQConfig",
    "DDPG",
    "DDPGConfig",
    "LagrangeMultiplier",
    "Learner",
    "MAKERS",
    "OFF_POLICY",
    "PPO",
    "PPOConfig",
    "PPOLagrangian",
    "SAC",
    "SACConfig",
    "SACLag",
    "SACLagConfig",
    "Theile",
    "TheileConfig",
    "Wang",
    "WangConfig",
    "make_learner",
]
