"""The paper's "CPO" baseline (§6.3): PPO-Lagrangian with a KL trust region.

The paper's CPO (after safety-starter-agents) maximises the return subject to a limit d = 0.05
on the discounted cost J_c = E[sum_t gamma_c^t c_t] of an episode, and keeps each policy update
inside a trust region of mean KL divergence 0.01. docs/model.md §8 reads it as a Lagrangian-constrained
PPO (c_t of docs/model.md §7: the weighted sum of boundary exit, OU collision, building collision and
NFZ entry; the env writes it to ``("next", "cost")``).

One ``update(batch)`` on an on-policy batch ``[*B, T]`` (time last, consecutive batches of the
same collector continuing each row's episodes) with PPO's keys (:mod:`uavlae.algos.ppo`) plus
``("next", "cost")`` and ``("next", "done")``:

1. GAE twice with the current critics: reward (``"advantage"``, ``"value_target"``) and cost
   (``"cost_advantage"``, ``"cost_value_target"``; torchrl's GAE with its reward key set to
   ``"cost"`` and its value key to ``"cost_value"``).
2. J_c is measured on the episodes that end in this batch: ``EpisodeCostTracker`` carries each
   row's running sum_t gamma_c^t c_t across batches (it is part of the checkpoint) and J_c is
   the mean over the episodes finished here. The multiplier takes one step on J_c - d
   (``LagrangeMultiplier``) before the policy update, so the policy is trained with the new
   lambda; a batch in which no episode ends measures nothing and leaves lambda as it is. An
   ``episode_cost`` argument, when given, replaces the measurement.
3. Up to ``epochs`` x minibatches of: the clipped surrogate on the Lagrangian advantage

       A_L = (Â_r - lambda * Â_c) / (1 + lambda)
       L_pi = -E[min(rho * A_L, clip(rho, 1 - eps, 1 + eps) * A_L)] - beta_H * H[pi]

   (Ray, Achiam & Amodei 2019, Safety Gym's PPO-Lagrangian), where Â_r is A_r standardised over
   the whole batch and Â_c is A_c centred but not scaled, so that lambda keeps the units of
   reward-advantage per unit of cost; dividing by (1 + lambda) keeps the step size bounded as
   lambda grows. Plus the reward critic loss (``ClipPPOLoss``) and the cost critic loss
   ``E[(V_c(s) - cost_value_target)^2]``.
4. The trust region, by early stopping: before every minibatch step the mean KL(pi_old || pi)
   over the whole batch is computed exactly (diagonal Gaussians before the tanh, which is a
   bijection and leaves the KL unchanged); once it exceeds ``target_kl`` the update's remaining
   steps and epochs are dropped. Early stopping rather than an adaptive KL penalty because the
   paper states a maximum KL, which a stop enforces up to one minibatch step, while a penalty
   only holds the KL near its target on average (and adds a coefficient with its own schedule);
   it is also what CPO's backtracking line search does: reject the step that leaves the region.
"""

from __future__ import annotations

from collections import defaultdict
from dataclasses import dataclass
from typing import Any, Literal

import torch
from pydantic import Field
from tensordict import TensorDictBase
from torchrl.data import TensorSpec
from torchrl.modules import ProbabilisticActor, ValueOperator
from torchrl.objectives import ClipPPOLoss
from torchrl.objectives.value import GAE

from uavlae.algos.common import StrictConfig, adam, optimiser_step, parse_config, to_floats
from uavlae.algos.ppo import PPO_TRAIN_KEYS, OnPolicy, PPOConfig, _check_on_policy_batch, make_clip_ppo_loss
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
    cost_limit: float = Field(0.05, ge=0)  # docs/model.md §7-§8: d on the discounted cost
    cost_gamma: float = Field(0.99, gt=0, le=1)
    cost_gae_lambda: float = Field(0.95, ge=0, le=1)
    lagrange: LagrangeConfig = LagrangeConfig()
    target_kl: float | None = Field(0.01, gt=0)  # §6.3: the trust region's maximum mean KL; null: off


def make_cpo_config(cfg: Any = None, **overrides: Any) -> CPOConfig:
    return parse_config(CPOConfig, cfg, **overrides)


def _standardise(x: torch.Tensor) -> torch.Tensor:
    return (x - x.mean()) / x.std().clamp_min(1e-6) if x.numel() > 1 else x - x.mean()


def gaussian_kl(loc_p: torch.Tensor, scale_p: torch.Tensor, loc_q: torch.Tensor, scale_q: torch.Tensor) -> torch.Tensor:
    """KL(p || q) of diagonal Gaussians, summed over the last (action) dimension.

    KL = sum_i [ log(s_q / s_p) + (s_p^2 + (m_p - m_q)^2) / (2 s_q^2) - 1/2 ].
    """
    kl = torch.log(scale_q / scale_p) + (scale_p.pow(2) + (loc_p - loc_q).pow(2)) / (2 * scale_q.pow(2)) - 0.5
    return kl.sum(-1)


class EpisodeCostTracker:
    """Each row's discounted episode cost sum_t gamma^t c_t, carried across on-policy batches.

    ``update(cost, done)`` takes one batch ``[*B, T]`` (or ``[*B, T, 1]``) and returns the
    discounted costs of the episodes that ended in it (``done`` at their last step), in no
    particular order. A batch whose row count differs from the previous one starts every row
    afresh (a different collector).
    """

    def __init__(self, gamma: float):
        self.gamma = float(gamma)
        self.acc: torch.Tensor | None = None  # [R] running discounted cost of the open episode
        self.discount: torch.Tensor | None = None  # [R] gamma^t of the row's next step

    def update(self, cost: torch.Tensor, done: torch.Tensor) -> torch.Tensor:
        if cost.shape != done.shape:
            raise ValueError(f"cost {tuple(cost.shape)} and done {tuple(done.shape)} must have one shape")
        if cost.shape[-1] == 1 and cost.dim() >= 2:
            cost, done = cost.squeeze(-1), done.squeeze(-1)
        cost = cost.reshape(-1, cost.shape[-1]).double()
        done = done.reshape(-1, done.shape[-1]).bool()
        rows, steps = cost.shape
        if self.acc is None or self.acc.shape[0] != rows:
            self.acc = torch.zeros(rows, dtype=torch.float64)
            self.discount = torch.ones(rows, dtype=torch.float64)
        acc, discount = self.acc.clone(), self.discount.clone()
        finished = []
        for t in range(steps):
            acc = acc + discount * cost[:, t]
            discount = discount * self.gamma
            ended = done[:, t]
            finished.append(acc[ended])
            acc = torch.where(ended, torch.zeros_like(acc), acc)
            discount = torch.where(ended, torch.ones_like(discount), discount)
        self.acc, self.discount = acc, discount
        return torch.cat(finished)

    def state_dict(self) -> dict[str, Any]:
        return {"gamma": self.gamma, "acc": self.acc, "discount": self.discount}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.gamma = float(state["gamma"])
        self.acc = None if state["acc"] is None else state["acc"].clone()
        self.discount = None if state["discount"] is None else state["discount"].clone()


@dataclass
class PPOLagrangian(OnPolicy):
    """PPO-Lagrangian ("CPO" in the paper). Build it with :func:`make_ppo_lagrangian`. Its
    checkpoint: actor and reward critic (in ``loss``), cost critic, optimisers, the multiplier and
    the open episodes' running costs."""

    cfg: CPOConfig
    actor: ProbabilisticActor
    critic: ValueOperator
    cost_critic: ValueOperator  # "observation" -> "cost_value"
    loss: ClipPPOLoss  # reads the advantage from "lagrangian_advantage"
    gae: GAE
    cost_gae: GAE
    lagrange: LagrangeMultiplier
    episode_costs: EpisodeCostTracker
    optimisers: dict[str, torch.optim.Optimizer]
    num_updates: int = 0
    last_cost: float | None = None  # the latest measured J_c (logged while no episode ends)

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

    def _policy_params(self, obs: TensorDictBase) -> tuple[torch.Tensor, torch.Tensor]:
        dist = self.actor.get_dist(obs.select("observation").copy())
        return dist.loc, dist.scale

    def mean_kl(self, flat: TensorDictBase, old_loc: torch.Tensor, old_scale: torch.Tensor) -> float:
        """Mean over ``flat``'s states of KL(pi_old || pi) for the current actor."""
        with torch.no_grad():
            loc, scale = self._policy_params(flat)
            return float(gaussian_kl(old_loc, old_scale, loc, scale).mean())

    def _epochs_with_kl_stop(self, flat: TensorDictBase) -> dict[str, float]:
        """``epochs`` passes over shuffled minibatches, stopped once the mean KL passes target_kl."""
        with torch.no_grad():
            old_loc, old_scale = self._policy_params(flat)
        n = flat.shape[0]
        sums: dict[str, float] = defaultdict(float)
        steps, stopped, kl = 0, False, 0.0
        for _ in range(self.cfg.epochs):
            for idx in torch.randperm(n).split(self.cfg.minibatch_size):
                if steps > 0 and self.cfg.target_kl is not None:
                    kl = self.mean_kl(flat, old_loc, old_scale)
                    if kl > self.cfg.target_kl:
                        stopped = True
                        break
                for k, v in to_floats(self._step(flat[idx])).items():
                    sums[k] += v
                steps += 1
            if stopped:
                break
        if not stopped:
            kl = self.mean_kl(flat, old_loc, old_scale)
        logs = {k: v / steps for k, v in sums.items()}
        per_epoch = -(-n // self.cfg.minibatch_size)
        logs.update({"kl": kl, "kl_stopped": float(stopped), "gradient_steps": float(steps), "epochs_run": steps / per_epoch})
        return logs

    def update(self, batch: TensorDictBase, episode_cost: float | None = None) -> dict[str, float]:
        """One PPO-Lagrangian update on ``[*B, T]`` (module doc: keys, order, exact loss)."""
        _check_on_policy_batch(
            batch,
            ("observation", "action", "action_log_prob", ("next", "reward"), ("next", "cost"), ("next", "done")),
        )
        with torch.no_grad():
            batch = self.gae(batch.copy())
            batch = self.cost_gae(batch)
            finished = self.episode_costs.update(batch["next", "cost"], batch["next", "done"])
            if episode_cost is not None:
                jc: float | None = float(episode_cost)
            elif finished.numel() > 0:
                jc = float(finished.mean())
            else:
                jc = None
            if jc is not None:
                self.lagrange.update(jc, self.cfg.cost_limit)
                self.last_cost = jc
            lam = self.lagrange.value
            adv_r = batch["advantage"]
            adv_r = _standardise(adv_r) if self.cfg.normalize_advantage else adv_r
            adv_c = batch["cost_advantage"] - batch["cost_advantage"].mean()
            batch["lagrangian_advantage"] = (adv_r - lam * adv_c) / (1.0 + lam)
        flat = batch.select(*CPO_TRAIN_KEYS).reshape(-1)
        logs = self._epochs_with_kl_stop(flat)
        cost = batch["next", "cost"]
        stats = {
            "lambda": lam,
            "episodes_measured": float(finished.numel()) if episode_cost is None else 0.0,
            "cost_limit": self.cfg.cost_limit,
            "cost_mean_step": cost.mean(),
            "cost_rate": (cost > 0).float().mean(),
            "cost_value_target_mean": batch["cost_value_target"].mean(),
            "cost_advantage_std": batch["cost_advantage"].std(),
            "reward_mean_step": batch["next", "reward"].mean(),
            "advantage_mean": batch["advantage"].mean(),
            "value_target_mean": batch["value_target"].mean(),
        }
        if self.last_cost is not None:  # nothing to report before the first episode ends
            stats["episode_cost"] = self.last_cost
            stats["cost_violation"] = self.last_cost - self.cfg.cost_limit
        stats["episode_cost_given"] = float(episode_cost is not None)
        return self._counted(logs, stats)

    def _parts(self) -> dict[str, Any]:
        return {
            "loss": self.loss,
            "cost_critic": self.cost_critic,
            "optimisers": self.optimisers,
            "lagrange": self.lagrange,
            "episode_costs": self.episode_costs,
        }

    def state_dict(self) -> dict[str, Any]:
        return {**super().state_dict(), "last_cost": self.last_cost}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        super().load_state_dict(state)
        self.last_cost = state["last_cost"]


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
        episode_costs=EpisodeCostTracker(cfg.cost_gamma),
        optimisers=optimisers,
    )


make_cpo = make_ppo_lagrangian
