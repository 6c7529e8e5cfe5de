"""PPO (Schulman et al. 2017) on torchrl's ``ClipPPOLoss`` and ``GAE``.

docs/model.md §8: same network sizes as SAC (2x64), clip 0.2; learning rates as SAC's Table 4.

``update(batch)`` is one full PPO update on an on-policy batch of shape ``[*B, T]`` (time last,
as the collector returns it) with ``"observation"``, ``"action"``, ``"action_log_prob"`` (written
by :func:`uavlae.policies.networks.make_ppo_actor` while collecting), ``("next", "observation")``,
``("next", "reward")``, ``("next", "done")``, ``("next", "terminated")``: GAE once with the
current critic, then ``epochs`` passes over shuffled minibatches of ``minibatch_size`` steps.
"""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, ClassVar, Literal

import torch
from pydantic import Field
from tensordict import TensorDictBase
from torchrl.data import TensorSpec
from torchrl.modules import ProbabilisticActor, ValueOperator
from torchrl.objectives import ClipPPOLoss
from torchrl.objectives.value import GAE

from uavlae.algos.common import (
    StrictConfig,
    adam,
    load_parts_state_dict,
    optimiser_step,
    parse_config,
    parts_state_dict,
    to_floats,
)
from uavlae.policies.networks import Activation, make_ppo_actor, make_value_critic

# What a PPO minibatch needs once GAE has run; the rest of the rollout is dropped before shuffling.
PPO_TRAIN_KEYS = ("observation", "action", "action_log_prob", "advantage", "value_target", "state_value")


class PPOConfig(StrictConfig):
    name: Literal["ppo"] = "ppo"
    hidden: tuple[int, ...] = Field((64, 64), min_length=1)
    activation: Activation = "tanh"
    actor_lr: float = Field(1e-4, gt=0)
    critic_lr: float = Field(3e-4, gt=0)
    gamma: float = Field(0.99, gt=0, le=1)
    gae_lambda: float = Field(0.95, ge=0, le=1)
    clip_epsilon: float = Field(0.2, gt=0, lt=1)  # docs/model.md §8
    epochs: int = Field(10, ge=1)
    minibatch_size: int = Field(256, ge=1)
    entropy_coeff: float = Field(0.0, ge=0)
    normalize_advantage: bool = True  # per minibatch, mean 0 / std 1
    loss_critic_type: Literal["l2", "smooth_l1", "l1"] = "l2"
    max_grad_norm: float | None = Field(0.5, gt=0)
    # Read by the collector / training loop, not by update():
    frames_per_batch: int = Field(2048, ge=1)


def make_ppo_config(cfg: Any = None, **overrides: Any) -> PPOConfig:
    return parse_config(PPOConfig, cfg, **overrides)


def ppo_minibatch_step(
    loss: ClipPPOLoss,
    optimisers: dict[str, torch.optim.Optimizer],
    max_grad_norm: float | None,
    mb: TensorDictBase,
    extra_losses: Callable[[TensorDictBase], dict[str, torch.Tensor]] | None = None,
) -> dict[str, torch.Tensor]:
    """One gradient step of a clipped-PPO loss on a minibatch: objective + critic + entropy, plus
    every term ``extra_losses(mb)`` returns (a learner's own regulariser; logged by its name)."""
    out = loss(mb)
    total = out["loss_objective"] + out["loss_critic"] + out.get("loss_entropy", 0.0)
    extra = extra_losses(mb) if extra_losses is not None else {}
    for term in extra.values():
        total = total + term
    norms = optimiser_step(optimisers, total, max_grad_norm)
    logs = dict(out.detach().items())
    logs.update({k: v.detach() for k, v in extra.items()})
    logs.update(norms)
    return logs


def run_epochs(
    flat: TensorDictBase,
    epochs: int,
    minibatch_size: int,
    step: Callable[[TensorDictBase], dict[str, torch.Tensor]],
) -> dict[str, float]:
    """``epochs`` passes of ``step`` over shuffled minibatches of ``flat`` ``[N]``; mean logs."""
    n = flat.shape[0]
    sums: dict[str, float] = defaultdict(float)
    count = 0
    for _ in range(epochs):
        for idx in torch.randperm(n).split(minibatch_size):
            for k, v in to_floats(step(flat[idx])).items():
                sums[k] += v
            count += 1
    return {k: v / count for k, v in sums.items()}


def _check_on_policy_batch(batch: TensorDictBase, keys: tuple[str, ...]) -> None:
    if batch.batch_dims < 1:
        raise ValueError("the PPO batch needs a time dimension: shape [*B, T], got a scalar batch")
    missing = [k for k in keys if k not in batch.keys(True)]
    if missing:
        raise KeyError(f"the on-policy batch lacks {missing}; collect it with make_ppo_actor's policy")


class OnPolicy:
    """What every on-policy learner (ppo, cpo, wang, theile) shares, on top of its ``cfg``,
    ``actor``, ``loss``, ``optimisers`` and ``num_updates``: it learns from the rollout its own
    sampling actor collects, no schedule follows training progress, a minibatch is one clipped-PPO
    step, and the checkpoint holds its parts (:meth:`_parts`) and its update count."""

    off_policy: ClassVar[bool] = False
    cfg: Any
    actor: ProbabilisticActor
    loss: ClipPPOLoss
    optimisers: dict[str, torch.optim.Optimizer]
    num_updates: int

    @property
    def behaviour(self) -> ProbabilisticActor:
        """What acts while collecting: the actor, sampling (it writes the log-probabilities)."""
        return self.actor

    def anneal(self, frames: int) -> None:
        """Schedules that follow training progress: none."""

    def _step(self, mb: TensorDictBase) -> dict[str, torch.Tensor]:
        return ppo_minibatch_step(self.loss, self.optimisers, self.cfg.max_grad_norm, mb)

    def _counted(self, logs: dict[str, float], batch_stats: dict[str, Any]) -> dict[str, float]:
        """``logs`` of one update, with the batch's statistics and the update counted."""
        self.num_updates += 1
        logs.update(to_floats(batch_stats))
        logs["num_updates"] = float(self.num_updates)
        return logs

    def _parts(self) -> dict[str, Any]:
        """What the checkpoint holds (its state_dict each)."""
        return {"loss": self.loss, "optimisers": self.optimisers}

    def state_dict(self) -> dict[str, Any]:
        return parts_state_dict(self._parts(), self.num_updates)

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.num_updates = load_parts_state_dict(self._parts(), state)


@dataclass
class PPO(OnPolicy):
    """The PPO learner. Build it with :func:`make_ppo`. Its checkpoint: actor and critic (in
    ``loss``), optimisers, counters; PPO has no target nets."""

    cfg: PPOConfig
    actor: ProbabilisticActor  # the acting policy (writes "action_log_prob")
    critic: ValueOperator
    loss: ClipPPOLoss
    gae: GAE
    optimisers: dict[str, torch.optim.Optimizer]
    num_updates: int = 0

    def update(self, batch: TensorDictBase) -> dict[str, float]:
        """One PPO update on an on-policy batch ``[*B, T]`` (module doc lists its keys)."""
        _check_on_policy_batch(batch, ("observation", "action", "action_log_prob", ("next", "reward")))
        with torch.no_grad():
            batch = self.gae(batch.copy())
        flat = batch.select(*PPO_TRAIN_KEYS).reshape(-1)
        logs = run_epochs(flat, self.cfg.epochs, self.cfg.minibatch_size, self._step)
        return self._counted(logs, {
            "reward_mean_step": batch["next", "reward"].mean(),
            "advantage_mean": batch["advantage"].mean(),
            "advantage_std": batch["advantage"].std(),
            "value_target_mean": batch["value_target"].mean(),
        })


def make_clip_ppo_loss(
    actor: ProbabilisticActor, critic: ValueOperator, cfg: PPOConfig, *, normalize_advantage: bool
) -> ClipPPOLoss:
    return ClipPPOLoss(
        actor,
        critic,
        clip_epsilon=cfg.clip_epsilon,
        entropy_bonus=cfg.entropy_coeff > 0,
        entropy_coeff=cfg.entropy_coeff,
        critic_coeff=1.0,  # Adam on separate parameter sets: a critic coefficient would be a no-op
        loss_critic_type=cfg.loss_critic_type,
        normalize_advantage=normalize_advantage,
    )


def make_ppo(cfg: PPOConfig | Any, obs_dim: int, action_spec: TensorSpec) -> PPO:
    """Build PPO for observations ``[obs_dim]`` and the env's bounded ``action_spec``."""
    cfg = make_ppo_config(cfg)
    actor = make_ppo_actor(obs_dim, action_spec, cfg.hidden, cfg.activation)
    critic = make_value_critic(obs_dim, cfg.hidden, "state_value", cfg.activation)
    loss = make_clip_ppo_loss(actor, critic, cfg, normalize_advantage=cfg.normalize_advantage)
    gae = GAE(gamma=cfg.gamma, lmbda=cfg.gae_lambda, value_network=critic, average_gae=False)
    optimisers = {
        "actor": adam(loss.actor_network_params.values(True, True), lr=cfg.actor_lr),
        "critic": adam(loss.critic_network_params.values(True, True), lr=cfg.critic_lr),
    }
    return PPO(cfg=cfg, actor=actor, critic=critic, loss=loss, gae=gae, optimisers=optimisers)
