"""SAC-Lagrangian, beyond the paper: SAC (:mod:`uavlae.algos.sac`) under a limit on the cost.

The problem is max_pi J_r(pi) subject to E_s[Q_c(s, pi(s))] <= d, where Q_c is the discounted
cost-to-go sum_k gamma_c^k c_{t+k} of docs/model.md §7's cost and s ranges over the replayed
states. With the default cost and termination on collision, a collision is counted once and ends
the episode, so Q_c is about the discounted chance of a violation ahead (boundary exits, which do
not end it, count each time). The learner follows the off-policy Lagrangian of OmniSafe's
SAC-Lag, with the constraint measured by the cost critic on replayed states rather than by
episode costs, so that the multiplier moves with every gradient step instead of every episode.

One ``update(batch)`` on a replay sample ``[N]`` with SAC's keys plus ``("next", "cost")``:

1. SACLoss's losses through autograd (``loss_impl: torchrl``): twin reward critics, actor,
   log(alpha), and SAC's cloning term when it is on.
2. The cost critic Q_c (one net and a Polyak target with SAC's tau; twin nets guard against
   over-estimating a return to be maximised, and Q_c is not maximised), by TD:

       y = c + gamma_c (1 - terminated) Q_c'(s', a'),  a' ~ pi(.|s')
       L_c = mean_i loss(Q_c(s_i, a_i), y_i)           (SAC's loss_function)

   with no entropy term: the entropy bonus belongs to the reward.
3. The actor's loss becomes the Lagrangian, divided by 1 + lambda as OmniSafe does:

       L_pi = (L_SAC + lambda * mean_i Q_c(s_i, a~_i)) / (1 + lambda),  a~ = rsample of pi(.|s)

   through Q_c with its parameters held fixed (only the actor moves on this term). Dividing makes
   the actor's gradient a convex combination of the reward's and the cost's: its size stays that
   of SAC's whatever lambda, so Adam's moment estimates (which remember ~1000 steps) do not lag
   behind a lambda that grows, the entropy term keeps its weight relative to the whole objective,
   and lambda = 0 is SAC's step exactly. a~ is a fresh sample, not SACLoss's own (which it does
   not expose): an unbiased estimate of the same expectation.
4. Every ``lagrange_every`` steps the multiplier takes one step (``LagrangeMultiplier``:
   lambda <- max(0, lambda + lr (J - d)) for dual ascent) on J, the mean of Q_c(s, a~) over the
   samples of those steps (measured before each step's update, detached). Every measurement of
   the window is used, so a slower multiplier is also a less noisy one.

Logged beside SAC's: ``loss_cost_critic``, ``cost_value`` (this step's measured Q_c(s, a~)),
``loss_actor_lagrangian`` and ``lagrange`` (lambda after this step).
"""

from __future__ import annotations

import copy
from dataclasses import dataclass
from typing import Any, Literal

import torch
from pydantic import Field, model_validator
from tensordict import TensorDict, TensorDictBase
from torch.func import functional_call
from torchrl.data import TensorSpec
from torchrl.modules import ValueOperator
from torchrl.objectives.utils import distance_loss

from uavlae.algos.common import parse_config
from uavlae.algos.ppo_lagrangian import LagrangeConfig, LagrangeMultiplier
from uavlae.algos.sac import SAC, SACConfig, make_sac
from uavlae.policies.networks import action_bounds, make_q_critic


class SACLagConfig(SACConfig):
    name: Literal["sac_lag"] = "sac_lag"  # type: ignore[assignment]
    # The cost critic and the actor's cost term need autograd; the fused path writes out SAC's
    # gradients only (checked below).
    loss_impl: Literal["fused", "torchrl"] = "torchrl"
    # d, in units of Q_c(s, pi(s)) averaged over replayed states: a discounted cost-to-go (cost
    # units of docs/model.md §7, 1 per violating slot at the default weights), so with termination
    # on collision about the discounted chance of a violation ahead. [decision] 0.05, the paper's
    # number for CPO, whose d bounds the same sum from an episode's first state instead.
    cost_limit: float = Field(0.05, ge=0)
    cost_gamma: float | None = Field(None, gt=0, le=1)  # gamma_c of Q_c; null: gamma
    cost_critic_lr: float = Field(3e-4, gt=0)  # [decision] the reward critics' (Table 4)
    # [decision] untuned: a step of 0.05 every 10 gradient steps moves lambda by 0.005 per step
    # per unit of violation, ~5 over 10k steps at a violation of 0.1, where it matters against
    # reward critics of tens
    lagrange: LagrangeConfig = LagrangeConfig()
    lagrange_every: int = Field(10, ge=1)  # gradient steps per multiplier step

    @model_validator(mode="after")
    def _needs_autograd(self) -> SACLagConfig:
        if self.loss_impl != "torchrl":
            raise ValueError(
                f"algo.loss_impl={self.loss_impl!r}: sac_lag trains its cost critic and the actor's cost "
                "term through autograd, which the fused path (SAC's gradients written out) has not; use "
                "algo.loss_impl=torchrl"
            )
        return self

    @property
    def cost_discount(self) -> float:
        """gamma_c: ``cost_gamma``, or ``gamma`` when it is null."""
        return self.gamma if self.cost_gamma is None else self.cost_gamma


def make_sac_lag_config(cfg: Any = None, **overrides: Any) -> SACLagConfig:
    return parse_config(SACLagConfig, cfg, **overrides)


@dataclass(kw_only=True)
class SACLag(SAC):
    """SAC with a cost critic and a Lagrange multiplier. Build it with :func:`make_sac_lag`."""

    cfg: SACLagConfig
    cost_critic: ValueOperator  # ("observation", "action") -> "state_action_value": Q_c
    cost_target: ValueOperator  # its Polyak copy, for the TD target
    lagrange: LagrangeMultiplier
    window_sum: float = 0.0  # the measurements of J since the multiplier's last step: their sum
    window_count: int = 0  # and their count

    _loss_keys = ("loss_actor_lagrangian", "loss_qvalue", "loss_alpha", "loss_clone", "loss_cost_critic")
    _log_keys = (*SAC._log_keys, "loss_actor_lagrangian", "loss_cost_critic", "cost_value")

    def __post_init__(self) -> None:
        super().__post_init__()
        # SAC's soft update then moves the cost target too, with the same tau
        for source, target in zip(self.cost_critic.parameters(), self.cost_target.parameters()):
            self._sources.append(source.data)
            self._targets.append(target.data)

    def _losses(self, batch: TensorDictBase, mask: torch.Tensor | None, relative: bool) -> dict[str, torch.Tensor]:
        out = super()._losses(batch, mask, relative)
        obs, next_obs = batch.get("observation"), batch.get(("next", "observation"))
        n = obs.shape[0]
        # One actor pass for a~ at s (reparameterised, for the actor) and a' at s' (for the target)
        both = TensorDict({"observation": torch.cat([obs, next_obs])}, batch_size=[2 * n])
        sample = self.actor.get_dist(both).rsample()
        a_pi, a_next = sample[:n], sample[n:].detach()
        net = self.cost_critic.module
        with torch.no_grad():
            q_next = self.cost_target.module(next_obs, a_next)
            alive = 1.0 - batch.get(("next", "terminated")).to(q_next.dtype)
            y = batch.get(("next", "cost")).to(q_next.dtype) + self.cfg.cost_discount * alive * q_next
        q = net(obs, batch.get("action"))
        loss_cost_critic = distance_loss(q, y, loss_function=self.cfg.loss_function).mean()
        # Q_c(s, a~) with Q_c's parameters detached: the actor's gradient flows through a~ only
        frozen = {k: v.detach() for k, v in net.named_parameters()}
        cost_value = functional_call(net, frozen, (obs, a_pi)).mean()
        lam = self.lagrange.value
        out["loss_actor_lagrangian"] = (out["loss_actor"] + lam * cost_value) / (1.0 + lam)
        out["loss_cost_critic"] = loss_cost_critic
        out["cost_value"] = cost_value
        return out

    def update(self, batch: TensorDictBase) -> dict[str, float]:
        """One gradient step (module doc), then the multiplier's step when one is due."""
        logs = super().update(batch)
        self.window_sum += logs["cost_value"]
        self.window_count += 1
        if self.num_updates % self.cfg.lagrange_every == 0:
            self.lagrange.update(self.window_sum / self.window_count, self.cfg.cost_limit)
            self.window_sum, self.window_count = 0.0, 0
        logs["lagrange"] = self.lagrange.value
        return logs

    def _parts(self) -> dict[str, Any]:
        return {**super()._parts(), "cost_critic": self.cost_critic, "cost_target": self.cost_target,
                "lagrange": self.lagrange}

    def state_dict(self) -> dict[str, Any]:
        """SAC's, the cost critic and its target (their Adam group is in SAC's optimiser), the
        multiplier and the open measurement window."""
        return {**super().state_dict(), "lagrange_window": {"sum": self.window_sum, "count": self.window_count}}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        super().load_state_dict(state)
        window = state["lagrange_window"]
        self.window_sum, self.window_count = float(window["sum"]), int(window["count"])


def make_sac_lag(cfg: SACLagConfig | Any, obs_dim: int, action_spec: TensorSpec) -> SACLag:
    """Build SAC-Lagrangian for observations ``[obs_dim]`` and the env's bounded ``action_spec``."""
    cfg = make_sac_lag_config(cfg)
    sac = make_sac(cfg, obs_dim, action_spec)  # SAC's parts: actor, SACLoss, its Adam, target updater
    cost_critic = make_q_critic(obs_dim, action_bounds(action_spec).shape[-1], cfg.hidden, cfg.activation, cfg.layer_norm)
    cost_target = copy.deepcopy(cost_critic).requires_grad_(False)
    # A group of SAC's one Adam, as SAC's parts are: the same maths as an Adam of its own, one
    # kernel call less per step
    sac.optimisers["sac"].add_param_group(
        {"name": "cost_critic", "params": list(cost_critic.parameters()), "lr": cfg.cost_critic_lr}
    )
    return SACLag(
        cfg=cfg, actor=sac.actor, loss=sac.loss, optimisers=sac.optimisers, target_updater=sac.target_updater,
        cost_critic=cost_critic, cost_target=cost_target,
        lagrange=LagrangeMultiplier(cfg.lagrange, limit=cfg.cost_limit),
    )
