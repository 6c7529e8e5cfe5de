"""CrossQ (Bhatt et al., ICLR 2024) on torchrl's ``CrossQLoss``: SAC without target networks, with
batch-renormalised critics. Beyond the paper: a stronger off-policy learner than Table 4's SAC,
to tell a learner too small from a task too hard.

What differs from SAC (``uavlae/algos/sac.py``):

- no target Q nets: the TD target ``r + gamma (1 - terminated) (min_k Q_k(s', a') - alpha log pi(a'|s'))``
  comes from the Q nets being trained, without gradient;
- each Q net normalises the input of every linear layer with a batch renormalisation
  (:func:`uavlae.policies.networks.make_batch_renorm_q_critic`), and ``CrossQLoss`` evaluates
  ``(s, a)`` and ``(s', a')`` in one forward, so both are normalised by the same statistics
  (what lets CrossQ drop the target nets); the actor's loss reads the Q nets in eval mode, by
  their running statistics;
- wide Q nets, Adam with beta1 = 0.5, learning rates of 1e-3, and the actor and the temperature
  updated once every ``policy_delay`` = 3 Q steps.

The actor is SAC's plain tanh-Gaussian MLP (the paper's has batch renormalisation too): acting
then never depends on the batch it acts in nor on a module's train/eval mode, and it exports as
SAC's does (``uavlae/export.py``). The Q nets never act, so their mode does not matter for
collection nor evaluation.

``update(batch)`` takes a replay sample ``[N]`` with ``"observation"``, ``"action"``,
``("next", "observation")``, ``("next", "reward")``, ``("next", "done")``,
``("next", "terminated")``; it takes one Adam step on the Q nets and, on every
``policy_delay``-th call, then one on the actor and one on log(alpha), their losses computed
against the Q nets just updated (the order of the CrossQ authors' code).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, ClassVar, Literal

import torch
from pydantic import Field
from tensordict import TensorDictBase
from torchrl.data import TensorSpec
from torchrl.modules import ProbabilisticActor
from torchrl.objectives import CrossQLoss

from uavlae.algos.common import (
    StrictConfig,
    load_parts_state_dict,
    optimiser_step,
    parse_config,
    parts_state_dict,
    to_floats,
)
from uavlae.policies.networks import Activation, action_bounds, make_batch_renorm_q_critic, make_sac_actor


class BatchRenormConfig(StrictConfig):
    """The Q nets' batch renormalisation (Ioffe 2017), CrossQ's settings."""

    momentum: float = Field(0.01, gt=0, le=1)  # running statistics' update rate (Flax's 0.99 = 1 - 0.01)
    eps: float = Field(1e-3, gt=0)  # added to the variance (CrossQ's 0.001)
    warmup_steps: int = Field(100_000, ge=0)  # Q steps of plain batch norm before r and d apply
    max_r: float = Field(3.0, ge=1)  # the std correction r is clamped to [1/max_r, max_r]
    max_d: float = Field(5.0, ge=0)  # the mean correction d to [-max_d, max_d]


class CrossQConfig(StrictConfig):
    name: Literal["crossq"] = "crossq"
    actor_hidden: tuple[int, ...] = Field((256, 256), min_length=1)  # CrossQ's actor
    critic_hidden: tuple[int, ...] = Field((512, 512), min_length=1)  # CrossQ: 2048 (conf/algo/crossq.yaml says why not)
    activation: Activation = "relu"
    batch_renorm: BatchRenormConfig = BatchRenormConfig()
    actor_lr: float = Field(1e-3, gt=0)  # CrossQ
    critic_lr: float = Field(1e-3, gt=0)  # CrossQ
    alpha_lr: float = Field(1e-3, gt=0)  # CrossQ
    adam_beta1: float = Field(0.5, ge=0, lt=1)  # CrossQ, actor and Q nets (the temperature: Adam's 0.9)
    adam_beta2: float = Field(0.999, ge=0, lt=1)
    policy_delay: int = Field(3, ge=1)  # Q steps per actor and temperature step
    gamma: float = Field(0.99, gt=0, le=1)
    alpha_init: float = Field(1.0, gt=0)
    target_entropy: float | Literal["auto"] = "auto"  # auto: -act_dim
    num_qvalue_nets: int = Field(2, ge=1)
    loss_function: Literal["l2", "smooth_l1", "l1"] = "l2"
    max_grad_norm: float | None = Field(None, gt=0)  # None: no clipping
    # Read by the collector / training loop, not by update():
    batch_size: int = Field(256, ge=2)  # the Q nets' batch statistics need rows to vary over
    buffer_size: int = Field(1_000_000, ge=1)
    init_random_frames: int = Field(5_000, ge=0)  # uniform-random actions before learning
    utd_ratio: float = Field(1.0, gt=0)  # gradient steps per collected env frame


def make_crossq_config(cfg: Any = None, **overrides: Any) -> CrossQConfig:
    return parse_config(CrossQConfig, cfg, **overrides)


@dataclass
class CrossQ:
    """The CrossQ learner: loss and three Adams. Build it with :func:`make_crossq`."""

    cfg: CrossQConfig
    actor: ProbabilisticActor  # the acting policy; shares its parameters with ``loss``
    loss: CrossQLoss  # holds the actor's and the Q nets' parameters, the BRN statistics and log_alpha
    optimisers: dict[str, torch.optim.Optimizer]  # {"critic", "actor", "alpha"}
    num_updates: int = 0
    # the latest actor step's scalars, logged with every update until the next one
    actor_logs: dict[str, float] = field(default_factory=dict)
    off_policy: ClassVar[bool] = True

    @property
    def behaviour(self) -> ProbabilisticActor:
        """What acts while collecting: the actor, sampling."""
        return self.actor

    def anneal(self, frames: int) -> None:
        """No schedule follows training progress."""

    def update(self, batch: TensorDictBase) -> dict[str, float]:
        """One Q step, and every ``policy_delay``-th call an actor and a temperature step, on
        ``batch`` (see the module doc for its keys); returns log scalars. The loss copies what it
        is given: the caller's batch is left untouched."""
        critic = {"critic": self.optimisers["critic"]}
        loss_q, meta = self.loss.qvalue_loss(batch)
        norms = optimiser_step(critic, loss_q, self.cfg.max_grad_norm)
        self.num_updates += 1
        actor_step = self.num_updates % self.cfg.policy_delay == 0
        if actor_step:
            # against the Q nets just stepped, in eval mode (CrossQLoss.actor_loss switches them)
            loss_actor, meta_actor = self.loss.actor_loss(batch)
            log_prob = meta_actor["log_prob"]
            loss_alpha = self.loss.alpha_loss(log_prob)  # log_prob is detached: alpha's gradient only
            others = {k: self.optimisers[k] for k in ("actor", "alpha")}
            norms.update(optimiser_step(others, loss_actor + loss_alpha, self.cfg.max_grad_norm))
            self.actor_logs = to_floats(
                {"loss_actor": loss_actor, "loss_alpha": loss_alpha, "entropy": -log_prob.mean()}
            )
        logs = to_floats({"loss_qvalue": loss_q, "td_error": meta["td_error"], **norms})
        logs.update(self.actor_logs)
        logs["alpha"] = self.alpha
        logs["actor_step"] = float(actor_step)
        logs["num_updates"] = float(self.num_updates)
        return logs

    @property
    def alpha(self) -> float:
        return float(self.loss.log_alpha.detach().exp())

    def _parts(self) -> dict[str, Any]:
        return {"loss": self.loss, "optimisers": self.optimisers}

    def state_dict(self) -> dict[str, Any]:
        """Actor, Q nets with their batch statistics, log_alpha (all in ``loss``), optimisers,
        the update counter (the policy delay's phase) and the latest actor step's scalars."""
        return {**parts_state_dict(self._parts(), self.num_updates), "actor_logs": dict(self.actor_logs)}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.num_updates = load_parts_state_dict(self._parts(), state)
        self.actor_logs = dict(state["actor_logs"])


def make_crossq(cfg: CrossQConfig | Any, obs_dim: int, action_spec: TensorSpec) -> CrossQ:
    """Build CrossQ for observations ``[obs_dim]`` and the env's bounded ``action_spec``."""
    cfg = make_crossq_config(cfg)
    act_dim = action_bounds(action_spec).shape[-1]
    actor = make_sac_actor(obs_dim, action_spec, cfg.actor_hidden, cfg.activation)
    brn = cfg.batch_renorm
    qvalue = make_batch_renorm_q_critic(
        obs_dim, act_dim, cfg.critic_hidden, cfg.activation, momentum=brn.momentum, eps=brn.eps,
        warmup_steps=brn.warmup_steps, max_r=brn.max_r, max_d=brn.max_d,
    )
    target_entropy = -float(act_dim) if cfg.target_entropy == "auto" else float(cfg.target_entropy)
    loss = CrossQLoss(
        actor_network=actor,
        qvalue_network=qvalue,
        num_qvalue_nets=cfg.num_qvalue_nets,
        loss_function=cfg.loss_function,
        alpha_init=cfg.alpha_init,
        target_entropy=target_entropy,
    )
    loss.make_value_estimator(gamma=cfg.gamma)
    betas = (cfg.adam_beta1, cfg.adam_beta2)
    # the Q nets' parameters without their batch statistics (buffers, no gradient, one of them an integer)
    critic = [p for p in loss.qvalue_network_params.values(True, True) if p.requires_grad]
    optimisers = {
        "critic": torch.optim.Adam(critic, lr=cfg.critic_lr, betas=betas, fused=True),
        "actor": torch.optim.Adam(list(loss.actor_network_params.values(True, True)), lr=cfg.actor_lr, betas=betas,
                                  fused=True),
        "alpha": torch.optim.Adam([loss.log_alpha], lr=cfg.alpha_lr, fused=True),
    }
    return CrossQ(cfg=cfg, actor=actor, loss=loss, optimisers=optimisers)
