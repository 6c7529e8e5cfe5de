"""DDPG (Lillicrap et al. 2016) on torchrl's ``DDPGLoss``: deterministic actor, Polyak targets.

docs/model.md §8: same network sizes as SAC (2x64); learning rates as SAC's Table 4.

``update(batch)`` takes a replay sample ``[N]`` with ``"observation"``, ``"action"``,
``("next", "observation")``, ``("next", "reward")``, ``("next", "done")``,
``("next", "terminated")`` and does one gradient step on actor and critic, then one soft update
of both target networks. The behaviour policy is ``exploration_policy`` (actor + annealed
noise), its noise annealed by ``anneal(frames)``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, ClassVar, Literal

import torch
from pydantic import Field, model_validator
from tensordict import TensorDictBase
from tensordict.nn import TensorDictSequential
from torch import nn
from torchrl.data import TensorSpec
from torchrl.objectives import DDPGLoss, SoftUpdate

from uavlae.algos.common import (
    StrictConfig,
    adam,
    load_parts_state_dict,
    optimiser_step,
    parse_config,
    parts_state_dict,
    to_floats,
)
from uavlae.policies.networks import Activation, action_bounds, make_ddpg_actor, make_ddpg_exploration, make_q_critic


class DDPGNoiseConfig(StrictConfig):
    kind: Literal["gaussian", "ou"] = "gaussian"  # ou needs an "is_init" entry (InitTracker)
    sigma_init: float = Field(0.3, ge=0)  # in action units (the box is [-1, 1])
    sigma_end: float = Field(0.05, ge=0)
    annealing_num_steps: int = Field(100_000, ge=1)  # frames from sigma_init to sigma_end
    ou_theta: float = Field(0.15, gt=0)
    ou_dt: float = Field(1.0, gt=0)

    @model_validator(mode="after")
    def _anneals_down(self) -> "DDPGNoiseConfig":
        if self.sigma_end > self.sigma_init:
            raise ValueError(f"noise.sigma_end={self.sigma_end} must be <= noise.sigma_init={self.sigma_init}")
        return self


class DDPGConfig(StrictConfig):
    name: Literal["ddpg"] = "ddpg"
    hidden: tuple[int, ...] = Field((64, 64), min_length=1)
    activation: Activation = "relu"
    actor_lr: float = Field(1e-4, gt=0)
    critic_lr: float = Field(3e-4, gt=0)
    gamma: float = Field(0.99, gt=0, le=1)
    tau: float = Field(0.005, gt=0, le=1)
    loss_function: Literal["l2", "smooth_l1", "l1"] = "l2"
    max_grad_norm: float | None = Field(None, gt=0)
    noise: DDPGNoiseConfig = DDPGNoiseConfig()
    # Read by the collector / training loop, not by update():
    batch_size: int = Field(256, ge=1)
    buffer_size: int = Field(1_000_000, ge=1)
    init_random_frames: int = Field(5_000, ge=0)
    utd_ratio: float = Field(1.0, gt=0)


def make_ddpg_config(cfg: Any = None, **overrides: Any) -> DDPGConfig:
    return parse_config(DDPGConfig, cfg, **overrides)


@dataclass
class DDPG:
    """The DDPG learner. Build it with :func:`make_ddpg`."""

    cfg: DDPGConfig
    actor: TensorDictSequential  # deterministic; evaluation policy
    exploration_policy: TensorDictSequential  # actor + noise; collection policy
    noise: nn.Module  # annealed by anneal(frames)
    loss: DDPGLoss
    optimisers: dict[str, torch.optim.Optimizer]
    target_updater: SoftUpdate
    num_updates: int = 0
    noise_frames: int | None = 0  # the frames the noise has been annealed over (None: not known)
    off_policy: ClassVar[bool] = True

    @property
    def behaviour(self) -> TensorDictSequential:
        """What acts while collecting: the actor with its exploration noise."""
        return self.exploration_policy

    def anneal(self, frames: int) -> None:
        """The exploration noise, annealed over the frames collected so far."""
        if self.noise_frames is not None and frames > self.noise_frames:
            self.noise.step(frames - self.noise_frames)
        self.noise_frames = frames

    def update(self, batch: TensorDictBase) -> dict[str, float]:
        """One gradient step on ``batch`` (see the module doc for its keys); returns log scalars."""
        out = self.loss(batch)
        norms = optimiser_step(self.optimisers, out["loss_actor"] + out["loss_value"], self.cfg.max_grad_norm)
        self.target_updater.step()
        self.num_updates += 1
        logs = to_floats(out, ["loss_actor", "loss_value", "pred_value", "target_value"])
        logs.update(to_floats(norms))
        sigma = getattr(self.noise, "sigma", None) if self.cfg.noise.kind == "gaussian" else None
        logs["noise_scale"] = float(sigma if sigma is not None else self.noise.eps * self.cfg.noise.sigma_init)
        logs["num_updates"] = float(self.num_updates)
        return logs

    def _parts(self) -> dict[str, Any]:
        return {"loss": self.loss, "optimisers": self.optimisers, "target_updater": self.target_updater, "noise": self.noise}

    def state_dict(self) -> dict[str, Any]:
        """Actor, critic, both targets (in ``loss``), optimisers, the annealed noise, counters."""
        return {**parts_state_dict(self._parts(), self.num_updates), "noise_frames": self.noise_frames}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.num_updates = load_parts_state_dict(self._parts(), state)
        # a checkpoint from before the noise counted its frames: the next anneal only takes note
        self.noise_frames = state.get("noise_frames")


def make_ddpg(cfg: DDPGConfig | Any, obs_dim: int, action_spec: TensorSpec) -> DDPG:
    """Build DDPG for observations ``[obs_dim]`` and the env's bounded ``action_spec``."""
    cfg = make_ddpg_config(cfg)
    act_dim = action_bounds(action_spec).shape[-1]
    actor = make_ddpg_actor(obs_dim, action_spec, cfg.hidden, cfg.activation)
    critic = make_q_critic(obs_dim, act_dim, cfg.hidden, cfg.activation)
    n = cfg.noise
    policy, noise = make_ddpg_exploration(
        actor,
        action_spec,
        kind=n.kind,
        sigma_init=n.sigma_init,
        sigma_end=n.sigma_end,
        annealing_num_steps=n.annealing_num_steps,
        ou_theta=n.ou_theta,
        ou_dt=n.ou_dt,
    )
    loss = DDPGLoss(actor, critic, loss_function=cfg.loss_function, delay_actor=True, delay_value=True)
    loss.make_value_estimator(gamma=cfg.gamma)
    optimisers = {
        "actor": adam(loss.actor_network_params.values(True, True), lr=cfg.actor_lr),
        "critic": adam(loss.value_network_params.values(True, True), lr=cfg.critic_lr),
    }
    target_updater = SoftUpdate(loss, tau=cfg.tau)
    return DDPG(
        cfg=cfg,
        actor=actor,
        exploration_policy=policy,
        noise=noise,
        loss=loss,
        optimisers=optimisers,
        target_updater=target_updater,
    )
