"""The paper's "CPO" baseline (§6.3): PPO with a Lagrange multiplier on the cost signal.

SPEC.md §8 reads CPO as a Lagrangian-constrained PPO with cost limit d = 0.05 on the
discounted cost J_c = E[sum_t gamma_c^t c_t] (SPEC.md §7: c_t is the weighted sum of boundary
exit, OU collision, building collision and NFZ entry; the env writes it to ``("next", "cost")``).

One ``update(batch)`` on an on-policy batch ``[*B, T]`` (time last) with PPO's keys
(:mod:`uavlae.algos.ppo`) plus ``("next", "cost")``:

1. GAE twice with the current critics: reward (``"advantage"``, ``"value_target"``) and cost
   (``"cost_advantage"``, ``"cost_value_target"``; torchrl's GAE with its reward key set to
   ``"cost"`` and its value key to ``"cost_value"``).
2. The multiplier takes one step on the constraint violation J_c - d (``LagrangeMultiplier``),
   before the policy update, so the policy is trained with the new lambda.
3. ``epochs`` x minibatches of: the clipped surrogate on the Lagrangian advantage

       A_L = (Â_r - lambda * Â_c) / (1 + lambda)
       L_pi = -E[min(rho * A_L, clip(rho, 1 - eps, 1 + eps) * A_L)] - beta_H * H[pi]

   (Ray, Achiam & Amodei 2019, Safety Gym's PPO-Lagrangian), where Â_r is A_r standardised over
   the whole batch and Â_c is A_c centred but not scaled, so that lambda keeps the units of
   reward-advantage per unit of cost; dividing by (1 + lambda) keeps the step size bounded as
   lambda grows. Plus the reward critic loss (``ClipPPOLoss``) and the cost critic loss
   ``E[(V_c(s) - cost_value_target)^2]``.

J_c for step 2 is, in order of preference: the ``episode_cost`` argument (the mean discounted
cost of the episodes finished in this batch, from the training loop's bookkeeping), else the
mean cost lambda-return ``cost_value_target`` over the batch's episode starts (``"is_init"``,
torchrl's InitTracker), else over all its steps (the expected discounted cost-to-go from a
visited state: an upper-biased proxy for episodes whose costly part comes late).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Literal

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
from uavlae.algos.ppo import PPO_TRAIN_KEYS, PPOConfig, _check_on_policy_batch, make_clip_ppo_loss, run_epochs
from uavlae.policies.networks import make_ppo_actor, make_value_critic

CPO_TRAIN_KEYS = (*PPO_TRAIN_KEYS, "cost_advantage", "cost_value_target", "lagrangian_advantage")


class LagrangeConfig(StrictConfig):
    method: Literal["dual_ascent", "pid"] = "dual_ascent"
    init: float = Field(0.0, ge=0)  # lambda_0
    lr: float = Field(0.05, gt=0)  # dual ascent step size
    # PID-Lagrangian (Stooke, Achiam & Abbeel 2020, Alg. 2); used when method == "pid"
    kp: float = Field(0.05, ge=0)
    ki: float = Field(0.01, ge=0)
    kd: float = Field(0.01, ge=0)
    max_value: float | None = Field(None, gt=0)  # optional upper clip of lambda


class LagrangeMultiplier:
    """A non-negative Lagrange multiplier lambda updated on the violation J_c - limit.

    ``dual_ascent``: lambda <- max(0, lambda + lr * (J_c - limit)), projected gradient ascent on
    the dual of max_pi J_r s.t. J_c <= limit.

    ``pid`` (Stooke et al. 2020): with e = J_c - limit,
    I <- max(0, I + e), D = max(0, J_c - J_c,prev) (0 on the first step),
    lambda = max(0, kp * e + ki * I + kd * D). The integral starts at ``init / ki`` so that
    lambda starts near ``init``.
    """

    def __init__(self, cfg: LagrangeConfig | Any = None, limit: float = 0.05):
        self.cfg = parse_config(LagrangeConfig, cfg)
        self.limit = float(limit)
        self._value = float(self.cfg.init)
        self._integral = self.cfg.init / self.cfg.ki if self.cfg.ki > 0 else 0.0
        self._prev_cost: float | None = None
        self.num_updates = 0

    @property
    def value(self) -> float:
        return self._value

    def _clip(self, lam: float) -> float:
        lam = max(0.0, lam)
        return min(lam, self.cfg.max_value) if self.cfg.max_value is not None else lam

    def update(self, cost: float, limit: float | None = None) -> float:
        """One step on the measured constraint value ``cost`` (J_c); returns the new lambda."""
        cost = float(cost)
        if not torch.isfinite(torch.tensor(cost)):
            raise ValueError(f"the measured cost must be finite, got {cost}")
        limit = self.limit if limit is None else float(limit)
        error = cost - limit
        if self.cfg.method == "dual_ascent":
            self._value = self._clip(self._value + self.cfg.lr * error)
        else:
            self._integral = max(0.0, self._integral + error)
            deriv = 0.0 if self._prev_cost is None else max(0.0, cost - self._prev_cost)
            self._value = self._clip(self.cfg.kp * error + self.cfg.ki * self._integral + self.cfg.kd * deriv)
        self._prev_cost = cost
        self.num_updates += 1
        return self._value

    def state_dict(self) -> dict[str, Any]:
        return {
            "value": self._value,
            "integral": self._integral,
            "prev_cost": self._prev_cost,
            "limit": self.limit,
            "num_updates": self.num_updates,
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self._value = float(state["value"])
        self._integral = float(state["integral"])
        self._prev_cost = None if state["prev_cost"] is None else float(state["prev_cost"])
        self.limit = float(state["limit"])
        self.num_updates = int(state["num_updates"])

    def __repr__(self) -> str:
        return f"LagrangeMultiplier(method={self.cfg.method!r}, value={self._value:.4g}, limit={self.limit})"


class CPOConfig(PPOConfig):
    name: Literal["cpo"] = "cpo"  # type: ignore[assignment]
    cost_limit: float = Field(0.05, ge=0)  # SPEC.md §7-§8: d on the discounted cost
    cost_gamma: float = Field(0.99, gt=0, le=1)
    cost_gae_lambda: float = Field(0.95, ge=0, le=1)
    lagrange: LagrangeConfig = LagrangeConfig()


def make_cpo_config(cfg: Any = None, **overrides: Any) -> CPOConfig:
    return parse_config(CPOConfig, cfg, **overrides)


def _standardise(x: torch.Tensor) -> torch.Tensor:
    return (x - x.mean()) / x.std().clamp_min(1e-6) if x.numel() > 1 else x - x.mean()


@dataclass
class PPOLagrangian:
    """PPO-Lagrangian ("CPO" in the paper). Build it with :func:`make_ppo_lagrangian`."""

    cfg: CPOConfig
    actor: ProbabilisticActor
    critic: ValueOperator
    cost_critic: ValueOperator  # "observation" -> "cost_value"
    loss: ClipPPOLoss  # reads the advantage from "lagrangian_advantage"
    gae: GAE
    cost_gae: GAE
    lagrange: LagrangeMultiplier
    optimisers: dict[str, torch.optim.Optimizer]
    num_updates: int = 0

    def _step(self, mb: TensorDictBase) -> dict[str, torch.Tensor]:
        out = self.loss(mb)
        cost_value = self.cost_critic(mb.select("observation").copy())["cost_value"]
        loss_cost_critic = (cost_value - mb["cost_value_target"]).pow(2).mean()
        total = out["loss_objective"] + out["loss_critic"] + out.get("loss_entropy", 0.0) + loss_cost_critic
        norms = optimiser_step(self.optimisers, total, self.cfg.max_grad_norm)
        logs = dict(out.detach().items())
        logs["loss_cost_critic"] = loss_cost_critic.detach()
        logs.update(norms)
        return logs

    def _cost_estimate(self, batch: TensorDictBase) -> float:
        target = batch["cost_value_target"]
        is_init = batch.get("is_init", None)
        if is_init is not None and bool(is_init.any()):
            return float(target[is_init.expand_as(target)].mean())
        return float(target.mean())

    def update(self, batch: TensorDictBase, episode_cost: float | None = None) -> dict[str, float]:
        """One PPO-Lagrangian update on ``[*B, T]`` (module doc: keys, order, exact loss)."""
        _check_on_policy_batch(
            batch, ("observation", "action", "action_log_prob", ("next", "reward"), ("next", "cost"))
        )
        with torch.no_grad():
            batch = self.gae(batch.copy())
            batch = self.cost_gae(batch)
            jc = float(episode_cost) if episode_cost is not None else self._cost_estimate(batch)
            lam = self.lagrange.update(jc, self.cfg.cost_limit)
            adv_r = batch["advantage"]
            adv_r = _standardise(adv_r) if self.cfg.normalize_advantage else adv_r
            adv_c = batch["cost_advantage"] - batch["cost_advantage"].mean()
            batch["lagrangian_advantage"] = (adv_r - lam * adv_c) / (1.0 + lam)
        flat = batch.select(*CPO_TRAIN_KEYS).reshape(-1)
        logs = run_epochs(flat, self.cfg.epochs, self.cfg.minibatch_size, self._step)
        self.num_updates += 1
        cost = batch["next", "cost"]
        logs.update(
            to_floats(
                {
                    "lambda": lam,
                    "cost_estimate": jc,
                    "cost_limit": self.cfg.cost_limit,
                    "cost_violation": jc - self.cfg.cost_limit,
                    "cost_mean_step": cost.mean(),
                    "cost_rate": (cost > 0).float().mean(),
                    "cost_value_target_mean": batch["cost_value_target"].mean(),
                    "cost_advantage_std": batch["cost_advantage"].std(),
                    "reward_mean_step": batch["next", "reward"].mean(),
                    "advantage_mean": batch["advantage"].mean(),
                    "value_target_mean": batch["value_target"].mean(),
                }
            )
        )
        logs["episode_cost_given"] = float(episode_cost is not None)
        logs["num_updates"] = float(self.num_updates)
        return logs

    def _parts(self) -> dict[str, Any]:
        return {"loss": self.loss, "cost_critic": self.cost_critic, "optimisers": self.optimisers, "lagrange": self.lagrange}

    def state_dict(self) -> dict[str, Any]:
        """Actor and reward critic (in ``loss``), cost critic, optimisers, the multiplier."""
        return parts_state_dict(self._parts(), self.num_updates)

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.num_updates = load_parts_state_dict(self._parts(), state)


def make_ppo_lagrangian(cfg: CPOConfig | Any, obs_dim: int, action_spec: TensorSpec) -> PPOLagrangian:
    """Build PPO-Lagrangian for observations ``[obs_dim]`` and the env's ``action_spec``."""
    cfg = make_cpo_config(cfg)
    actor = make_ppo_actor(obs_dim, action_spec, cfg.hidden, cfg.activation)
    critic = make_value_critic(obs_dim, cfg.hidden, "state_value", cfg.activation)
    cost_critic = make_value_critic(obs_dim, cfg.hidden, "cost_value", cfg.activation)
    # Advantages are normalised here over the whole batch (A_r) or centred (A_c), not per minibatch.
    loss = make_clip_ppo_loss(actor, critic, cfg, normalize_advantage=False)
    loss.set_keys(advantage="lagrangian_advantage")
    gae = GAE(gamma=cfg.gamma, lmbda=cfg.gae_lambda, value_network=critic, average_gae=False)
    cost_gae = GAE(gamma=cfg.cost_gamma, lmbda=cfg.cost_gae_lambda, value_network=cost_critic, average_gae=False)
    cost_gae.set_keys(
        reward="cost", value="cost_value", advantage="cost_advantage", value_target="cost_value_target"
    )
    optimisers = {
        "actor": adam(loss.actor_network_params.values(True, True), lr=cfg.actor_lr),
        "critic": adam(
            [*loss.critic_network_params.values(True, True), *cost_critic.parameters()], lr=cfg.critic_lr
        ),
    }
    return PPOLagrangian(
        cfg=cfg,
        actor=actor,
        critic=critic,
        cost_critic=cost_critic,
        loss=loss,
        gae=gae,
        cost_gae=cost_gae,
        lagrange=LagrangeMultiplier(cfg.lagrange, limit=cfg.cost_limit),
        optimisers=optimisers,
    )


make_cpo = make_ppo_lagrangian
