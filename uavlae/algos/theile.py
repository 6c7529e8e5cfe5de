"""The ``theile`` baseline: PPO on a D4-averaged CNN over DCU-centred maps, with a regulariser.

After Theile et al. 2024 (equivariant ensembles and regularisation for map-based path
planning), moved from coverage to data collection. The observation is the env's with
``env.maps.enabled`` (uavlae.envs.maps: a local fine and a global coarse map centred on the DCU);
the actor and the critic are each a :class:`uavlae.policies.d4.D4Ensemble`: one shared CNN
evaluated on the 8 images of the observation under the square's symmetry group, its outputs
brought back and averaged, so the policy is equivariant and the value invariant by construction.

The regulariser (weights ``regularizer.actor`` and ``regularizer.critic``) adds
``w · (1/8) Σ_e ||m_e − m̄||²`` to PPO's loss, ``m_e`` a member's back-transformed action mean (or
value) and ``m̄`` their average, pulling the shared network towards being equivariant itself.
PPO as :mod:`uavlae.algos.ppo` (torchrl's ``ClipPPOLoss`` and ``GAE``, :func:`ppo_minibatch_step`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Literal

import torch
from pydantic import Field
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModule
from torch import nn
from torchrl.data import TensorSpec
from torchrl.modules import NormalParamExtractor, ProbabilisticActor, TanhNormal, ValueOperator
from torchrl.objectives.value import GAE

from uavlae.algos.common import StrictConfig, adam, parse_config
from uavlae.algos.ppo import PPO, PPOConfig, make_clip_ppo_loss, ppo_minibatch_step
from uavlae.envs.world import ObservationLayout
from uavlae.policies.d4 import D4Ensemble, member_spread
from uavlae.policies.networks import SCALE_AT_ZERO, SCALE_LB, SCALE_MIN, action_bounds


class CNNConfig(StrictConfig):
    channels: tuple[int, ...] = Field((8, 16), min_length=1)  # one 3x3 convolution per entry, ReLU after each
    stride: int = Field(2, ge=1, le=4)
    head_hidden: tuple[int, ...] = (64, 64)  # Table 4's 2 x 64, after the convolutions


class RegularizerConfig(StrictConfig):
    actor: float = Field(0.1, ge=0)  # weight of the members' spread of the action mean
    critic: float = Field(0.0, ge=0)  # weight of the members' spread of the value


class TheileConfig(PPOConfig):
    name: Literal["theile"] = "theile"  # type: ignore[assignment]
    cnn: CNNConfig = CNNConfig()
    regularizer: RegularizerConfig = RegularizerConfig()


def make_theile_config(cfg: Any = None, **overrides: Any) -> TheileConfig:
    return parse_config(TheileConfig, cfg, **overrides)


@dataclass
class Theile(PPO):
    """The ``theile`` learner: PPO (its update, epochs and state) with the members' spread added
    to every minibatch's loss. Build it with :func:`make_theile`."""

    cfg: TheileConfig
    actor_net: D4Ensemble = field(kw_only=True)
    critic_net: D4Ensemble = field(kw_only=True)

    def regularizer(self, mb: TensorDictBase) -> dict[str, torch.Tensor]:
        """The weighted spreads of the members on a minibatch (the terms PPO's loss gets added)."""
        obs = mb["observation"]
        out: dict[str, torch.Tensor] = {}
        w = self.cfg.regularizer
        if w.actor > 0:
            out["loss_equivariance_actor"] = w.actor * member_spread(self.actor_net.members_of(obs)[..., :2])
        if w.critic > 0:
            out["loss_equivariance_critic"] = w.critic * member_spread(self.critic_net.members_of(obs))
        return out

    def _step(self, mb: TensorDictBase) -> dict[str, torch.Tensor]:
        return ppo_minibatch_step(self.loss, self.optimisers, self.cfg.max_grad_norm, mb, extra_losses=self.regularizer)


def make_theile(cfg: TheileConfig | Any, obs_dim: int, action_spec: TensorSpec, layout: ObservationLayout | None = None) -> Theile:
    """Build ``theile`` for the env's observation ``layout`` (it must carry the maps)."""
    cfg = make_theile_config(cfg)
    if layout is None:
        raise ValueError("algo theile needs the env's ObservationLayout (env.layout) to find the maps")
    if layout.size != obs_dim:
        raise ValueError(f"the observation has {obs_dim} columns but the layout {layout.size}")
    box = action_bounds(action_spec)
    if box.shape[-1] != 2:
        raise ValueError(f"algo theile acts on a 2-D velocity, got an action of {box.shape[-1]} dimensions")
    sizes = dict(channels=cfg.cnn.channels, stride=cfg.cnn.stride, hidden=cfg.cnn.head_hidden)
    actor_net = D4Ensemble(layout, "action", **sizes)
    critic_net = D4Ensemble(layout, "value", **sizes)
    # the regulariser reads the members of the pass ClipPPOLoss has just made on the same minibatch
    actor_net.keep_members = cfg.regularizer.actor > 0
    critic_net.keep_members = cfg.regularizer.critic > 0
    extractor = NormalParamExtractor(scale_mapping=f"biased_softplus_{SCALE_AT_ZERO}_{SCALE_MIN}", scale_lb=SCALE_LB)
    params = TensorDictModule(nn.Sequential(actor_net, extractor), in_keys=["observation"], out_keys=["loc", "scale"])
    actor = ProbabilisticActor(
        params, in_keys=["loc", "scale"], spec=box, distribution_class=TanhNormal,
        distribution_kwargs={"low": box.space.low, "high": box.space.high}, return_log_prob=True,
    )
    critic = ValueOperator(critic_net, in_keys=["observation"], out_keys=["state_value"])
    loss = make_clip_ppo_loss(actor, critic, cfg, normalize_advantage=cfg.normalize_advantage)
    gae = GAE(gamma=cfg.gamma, lmbda=cfg.gae_lambda, value_network=critic, average_gae=False)
    optimisers = {
        "actor": adam(loss.actor_network_params.values(True, True), lr=cfg.actor_lr),
        "critic": adam(loss.critic_network_params.values(True, True), lr=cfg.critic_lr),
    }
    return Theile(cfg=cfg, actor=actor, critic=critic, actor_net=actor_net, critic_net=critic_net, loss=loss, gae=gae,
                  optimisers=optimisers)
