"""The ``wang`` baseline: PPO on an entity transformer with random network distillation.

After Wang et al. 2023 (BIT-MCS DRL-UCS-AoI-Threshold: GTrXL with RND), reduced to our single
DCU. The actor and the critic are each an :class:`uavlae.policies.entity_transformer.EntityHead`
(one token per GE, zone, visible OU and the DCU, a type embedding, a masked transformer encoder;
that module's doc writes the adaptation down: attention over entities in one slot, where GTrXL
is memory over time). PPO as :mod:`uavlae.algos.ppo` (torchrl's ``ClipPPOLoss`` and ``GAE``).

Random network distillation (Burda et al. 2019): a fixed, randomly initialised network f and a
predictor f_hat trained to match it on the visited next observations; the intrinsic reward of a
transition is e = ||f(o') - f_hat(o')||^2 / d, standardised with the running mean and standard
deviation of e (Welford over every batch so far), and PPO's GAE sees r + ``rnd.weight`` * r_int.
The predictor takes ``rnd.epochs`` passes over the batch after the policy update.
Departures from Burda et al.: they divide by the std of the intrinsic *returns* and keep the
mean; a positive bonus on every slot would pay the DCU for staying airborne instead of landing
(an episode ends on landing), so here the bonus is centred and rewards only novelty relative to
the average. One value head on the summed reward (they use two); the observation is the env's
normalised one, not whitened again.

``update(batch)`` takes an on-policy batch ``[*B, T]`` with PPO's keys; the batch is not
modified (the intrinsic reward goes into a copy).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Literal

import torch
from pydantic import Field
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModule
from torch import nn
from torchrl.data import TensorSpec
from torchrl.modules import NormalParamExtractor, ProbabilisticActor, TanhNormal, ValueOperator
from torchrl.objectives import ClipPPOLoss
from torchrl.objectives.value import GAE

from uavlae.algos.common import StrictConfig, adam, parse_config
from uavlae.algos.ppo import PPO_TRAIN_KEYS, OnPolicy, PPOConfig, _check_on_policy_batch, make_clip_ppo_loss, run_epochs
from uavlae.envs.world import ObservationLayout
from uavlae.policies.entity_transformer import EntityHead
from uavlae.policies.networks import SCALE_AT_ZERO, SCALE_LB, SCALE_MIN, action_bounds


class TransformerConfig(StrictConfig):
    d_model: int = Field(64, ge=1)  # Table 4's width of 64
    n_heads: int = Field(4, ge=1)
    n_layers: int = Field(2, ge=1)  # Table 4's two layers
    ff: int = Field(128, ge=1)  # feed-forward width inside each encoder layer
    head_hidden: tuple[int, ...] = (64,)  # the MLP from the DCU token's output to the outputs


class RNDConfig(StrictConfig):
    weight: float = Field(0.05, ge=0)  # r + weight * r_int / std(r_int); 0: no intrinsic reward
    hidden: tuple[int, ...] = Field((64, 64), min_length=1)
    out_features: int = Field(64, ge=1)
    lr: float = Field(3e-4, gt=0)
    epochs: int = Field(1, ge=0)
    minibatch_size: int = Field(256, ge=1)


class WangConfig(PPOConfig):
    name: Literal["wang"] = "wang"  # type: ignore[assignment]
    transformer: TransformerConfig = TransformerConfig()
    rnd: RNDConfig = RNDConfig()


def make_wang_config(cfg: Any = None, **overrides: Any) -> WangConfig:
    return parse_config(WangConfig, cfg, **overrides)


def _mlp(n_in: int, n_out: int, hidden: tuple[int, ...]) -> nn.Sequential:
    layers: list[nn.Module] = []
    for h in hidden:
        layers += [nn.Linear(n_in, h), nn.ReLU()]
        n_in = h
    layers.append(nn.Linear(n_in, n_out))
    return nn.Sequential(*layers)


@dataclass
class RunningStd:
    """Welford's running mean and variance of a scalar stream."""

    count: float = 0.0
    mean: float = 0.0
    m2: float = 0.0

    def update(self, x: torch.Tensor) -> None:
        x = x.detach().double().flatten()
        n = float(x.numel())
        if n == 0:
            return
        b_mean = float(x.mean())
        b_m2 = float(((x - b_mean) ** 2).sum())
        total = self.count + n
        delta = b_mean - self.mean
        self.mean += delta * n / total
        self.m2 += b_m2 + delta**2 * self.count * n / total
        self.count = total

    @property
    def var(self) -> float:
        return self.m2 / self.count if self.count > 0 else 1.0

    @property
    def std(self) -> float:
        return math.sqrt(self.var)

    def state_dict(self) -> dict[str, float]:
        return {"count": self.count, "mean": self.mean, "m2": self.m2}

    def load_state_dict(self, state: dict[str, float]) -> None:
        self.count, self.mean, self.m2 = float(state["count"]), float(state["mean"]), float(state["m2"])


class RND(nn.Module):
    """A fixed random target network and its trained predictor on observations ``[..., D]``."""

    def __init__(self, obs_dim: int, cfg: RNDConfig):
        super().__init__()
        self.target = _mlp(obs_dim, cfg.out_features, cfg.hidden)
        self.predictor = _mlp(obs_dim, cfg.out_features, cfg.hidden)
        for p in self.target.parameters():
            p.requires_grad_(False)

    def error(self, obs: torch.Tensor) -> torch.Tensor:
        """Per-observation prediction error ``[..., 1]``: the mean square over the output features."""
        return (self.predictor(obs) - self.target(obs)).pow(2).mean(-1, keepdim=True)


@dataclass
class Wang(OnPolicy):
    """The ``wang`` learner. Build it with :func:`make_wang`. Its checkpoint: actor and critic (in
    ``loss``), RND target and predictor, optimisers, the running std."""

    cfg: WangConfig
    actor: ProbabilisticActor
    critic: ValueOperator
    loss: ClipPPOLoss
    gae: GAE
    rnd: RND
    optimisers: dict[str, torch.optim.Optimizer]
    rnd_optimiser: torch.optim.Optimizer
    intrinsic_std: RunningStd = field(default_factory=RunningStd)
    num_updates: int = 0

    def intrinsic_reward(self, next_obs: torch.Tensor, update_stats: bool = True) -> torch.Tensor:
        """(e - running mean(e)) / running std(e), ``[..., 1]`` (the stats first take in this batch)."""
        with torch.no_grad():
            err = self.rnd.error(next_obs)
        if update_stats:
            self.intrinsic_std.update(err)
        return (err - self.intrinsic_std.mean) / max(self.intrinsic_std.std, 1e-8)

    def _train_rnd(self, next_obs: torch.Tensor) -> float:
        flat = next_obs.reshape(-1, next_obs.shape[-1])
        losses = []
        for _ in range(self.cfg.rnd.epochs):
            for idx in torch.randperm(flat.shape[0]).split(self.cfg.rnd.minibatch_size):
                loss = self.rnd.error(flat[idx]).mean()
                self.rnd_optimiser.zero_grad(set_to_none=True)
                loss.backward()
                self.rnd_optimiser.step()
                losses.append(float(loss.detach()))
        return sum(losses) / len(losses) if losses else float("nan")

    def update(self, batch: TensorDictBase) -> dict[str, float]:
        """One PPO update with the RND bonus on ``[*B, T]`` (module doc)."""
        _check_on_policy_batch(batch, ("observation", "action", "action_log_prob", ("next", "reward"), ("next", "observation")))
        next_obs = batch["next", "observation"]
        r_int = self.intrinsic_reward(next_obs)
        with torch.no_grad():
            work = batch.clone(False)
            work["next"] = batch["next"].clone(False)
            work["next", "reward"] = batch["next", "reward"] + self.cfg.rnd.weight * r_int
            work = self.gae(work)
        flat = work.select(*PPO_TRAIN_KEYS).reshape(-1)
        logs = run_epochs(flat, self.cfg.epochs, self.cfg.minibatch_size, self._step)
        logs["loss_rnd"] = self._train_rnd(next_obs)
        return self._counted(logs, {
            "reward_mean_step": batch["next", "reward"].mean(),
            "intrinsic_reward_mean": r_int.mean(),
            "intrinsic_std": self.intrinsic_std.std,
            "advantage_mean": work["advantage"].mean(),
            "value_target_mean": work["value_target"].mean(),
        })

    def _parts(self) -> dict[str, Any]:
        return {"loss": self.loss, "rnd": self.rnd, "optimisers": {**self.optimisers, "rnd": self.rnd_optimiser},
                "intrinsic_std": self.intrinsic_std}


def make_wang(cfg: WangConfig | Any, obs_dim: int, action_spec: TensorSpec, layout: ObservationLayout | None = None) -> Wang:
    """Build ``wang`` for the env's observation ``layout`` (its columns are cut into tokens)."""
    cfg = make_wang_config(cfg)
    if layout is None:
        raise ValueError("algo wang needs the env's ObservationLayout (env.layout) to cut the observation into entities")
    if layout.size != obs_dim:
        raise ValueError(f"the observation has {obs_dim} columns but the layout {layout.size}")
    t = cfg.transformer
    if t.d_model % t.n_heads:
        raise ValueError(f"algo.transformer.d_model={t.d_model} must be a multiple of n_heads={t.n_heads}")
    sizes = dict(d_model=t.d_model, n_heads=t.n_heads, n_layers=t.n_layers, ff=t.ff, head_hidden=t.head_hidden)
    box = action_bounds(action_spec)
    act_dim = box.shape[-1]
    extractor = NormalParamExtractor(scale_mapping=f"biased_softplus_{SCALE_AT_ZERO}_{SCALE_MIN}", scale_lb=SCALE_LB)
    params = TensorDictModule(
        nn.Sequential(EntityHead(layout, 2 * act_dim, **sizes), extractor), in_keys=["observation"], out_keys=["loc", "scale"]
    )
    actor = ProbabilisticActor(
        params, in_keys=["loc", "scale"], spec=box, distribution_class=TanhNormal,
        distribution_kwargs={"low": box.space.low, "high": box.space.high}, return_log_prob=True,
    )
    critic = ValueOperator(EntityHead(layout, 1, **sizes), in_keys=["observation"], out_keys=["state_value"])
    loss = make_clip_ppo_loss(actor, critic, cfg, normalize_advantage=cfg.normalize_advantage)
    # deactivate_vmap: torch has no vmap rule for CPU attention, so the stacked call would fall back slowly
    gae = GAE(gamma=cfg.gamma, lmbda=cfg.gae_lambda, value_network=critic, average_gae=False, deactivate_vmap=True)
    optimisers = {
        "actor": adam(loss.actor_network_params.values(True, True), lr=cfg.actor_lr),
        "critic": adam(loss.critic_network_params.values(True, True), lr=cfg.critic_lr),
    }
    rnd = RND(obs_dim, cfg.rnd)
    return Wang(
        cfg=cfg, actor=actor, critic=critic, loss=loss, gae=gae, rnd=rnd, optimisers=optimisers,
        rnd_optimiser=adam(rnd.predictor.parameters(), lr=cfg.rnd.lr),
    )
