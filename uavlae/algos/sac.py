"""SAC (Haarnoja et al. 2018) on torchrl's ``SACLoss``: twin Q, Polyak targets, learned alpha.

SPEC.md §8 / paper Table 4: actor lr 1e-4, critic lr 3e-4, batch 256, gamma 0.99, 2x64 hidden.

``update(batch)`` takes a replay sample of shape ``[N]`` with
``"observation"``, ``"action"``, ``("next", "observation")``, ``("next", "reward")``,
``("next", "done")``, ``("next", "terminated")`` and does one gradient step on actor, both Q
nets and log(alpha), then one soft update of the target Q nets.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Literal

import torch
from pydantic import Field
from tensordict import TensorDict, TensorDictBase
from torchrl.data import TensorSpec
from torchrl.modules import ProbabilisticActor
from torchrl.objectives import SACLoss, SoftUpdate

from uavlae.algos.common import (
    StrictConfig,
    adam,
    load_parts_state_dict,
    optimiser_step,
    parse_config,
    parts_state_dict,
    to_floats,
)
from uavlae.policies.networks import Activation, action_bounds, make_q_critic, make_sac_actor


class SACConfig(StrictConfig):
    name: Literal["sac"] = "sac"
    hidden: tuple[int, ...] = Field((64, 64), min_length=1)  # Table 4: 2 hidden layers of 64
    activation: Activation = "relu"
    actor_lr: float = Field(1e-4, gt=0)  # Table 4
    critic_lr: float = Field(3e-4, gt=0)  # Table 4
    alpha_lr: float = Field(3e-4, gt=0)  # [decision] unstated; Haarnoja 2018 uses 3e-4
    gamma: float = Field(0.99, gt=0, le=1)  # Table 4
    tau: float = Field(0.005, gt=0, le=1)  # Polyak factor of the target Q nets
    alpha_init: float = Field(1.0, gt=0)
    target_entropy: float | Literal["auto"] = "auto"  # auto: -act_dim (Haarnoja 2018)
    num_qvalue_nets: int = Field(2, ge=1)
    loss_function: Literal["l2", "smooth_l1", "l1"] = "l2"
    max_grad_norm: float | None = Field(None, gt=0)  # None: no clipping
    compile: bool = False  # torch.compile the loss (benchmarks/sac_update_speed.py)
    # Read by the collector / training loop, not by update():
    batch_size: int = Field(256, ge=1)  # Table 4
    buffer_size: int = Field(1_000_000, ge=1)
    init_random_frames: int = Field(5_000, ge=0)  # uniform-random actions before learning
    utd_ratio: float = Field(1.0, gt=0)  # gradient steps per collected env frame


def make_sac_config(cfg: Any = None, **overrides: Any) -> SACConfig:
    return parse_config(SACConfig, cfg, **overrides)


@dataclass
class SAC:
    """The SAC learner: loss, optimisers, target updater. Build it with :func:`make_sac`."""

    cfg: SACConfig
    actor: ProbabilisticActor  # the acting policy; shares its parameters with ``loss``
    loss: SACLoss
    optimisers: dict[str, torch.optim.Optimizer]
    target_updater: SoftUpdate
    num_updates: int = 0
    _loss_fn: Any = field(default=None, repr=False)
    _in_keys: list = field(default_factory=list, repr=False)

    def __post_init__(self) -> None:
        # Only the loss is compiled: it traces without graph breaks; a first try compiling the
        # optimiser steps and SoftUpdate too ran slower than eager (benchmarks/sac_update_speed.md).
        self._loss_fn = torch.compile(self.loss) if self.cfg.compile else self.loss
        self._in_keys = list(self.loss.in_keys)

    def _step(self, batch: TensorDictBase) -> TensorDict:
        out = self._loss_fn(batch)
        total = out["loss_actor"] + out["loss_qvalue"] + out["loss_alpha"]
        norms = optimiser_step(self.optimisers, total, self.cfg.max_grad_norm)
        self.target_updater.step()
        out = out.select("loss_actor", "loss_qvalue", "loss_alpha", "alpha", "entropy").detach()
        for k, v in norms.items():
            out[k] = v.detach()
        return out

    def update(self, batch: TensorDictBase) -> dict[str, float]:
        """One gradient step on ``batch`` (see the module doc for its keys); returns log scalars."""
        # A fixed set of keys: the loss writes "td_error" into its input, and a compiled loss
        # would recompile on every new key structure. The caller's batch is left untouched.
        out = self._step(batch.select(*self._in_keys))
        self.num_updates += 1
        logs = to_floats(out)
        logs["num_updates"] = float(self.num_updates)
        return logs

    @property
    def alpha(self) -> float:
        return float(self.loss.log_alpha.detach().exp())

    def _parts(self) -> dict[str, Any]:
        return {"loss": self.loss, "optimisers": self.optimisers, "target_updater": self.target_updater}

    def state_dict(self) -> dict[str, Any]:
        """Actor, Q nets, target Q nets, log_alpha (all in ``loss``), optimisers, counters."""
        return parts_state_dict(self._parts(), self.num_updates)

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.num_updates = load_parts_state_dict(self._parts(), state)


def make_sac(cfg: SACConfig | Any, obs_dim: int, action_spec: TensorSpec) -> SAC:
    """Build SAC for observations ``[obs_dim]`` and the env's bounded ``action_spec``."""
    cfg = make_sac_config(cfg)
    act_dim = action_bounds(action_spec).shape[-1]
    actor = make_sac_actor(obs_dim, action_spec, cfg.hidden, cfg.activation)
    qvalue = make_q_critic(obs_dim, act_dim, cfg.hidden, cfg.activation)
    target_entropy = -float(act_dim) if cfg.target_entropy == "auto" else float(cfg.target_entropy)
    loss = SACLoss(
        actor_network=actor,
        qvalue_network=qvalue,
        num_qvalue_nets=cfg.num_qvalue_nets,
        loss_function=cfg.loss_function,
        alpha_init=cfg.alpha_init,
        target_entropy=target_entropy,
        delay_qvalue=True,
    )
    loss.make_value_estimator(gamma=cfg.gamma)
    optimisers = {
        "actor": adam(loss.actor_network_params.values(True, True), lr=cfg.actor_lr),
        "critic": adam(loss.qvalue_network_params.values(True, True), lr=cfg.critic_lr),
        "alpha": adam([loss.log_alpha], lr=cfg.alpha_lr),
    }
    target_updater = SoftUpdate(loss, tau=cfg.tau)
    return SAC(cfg=cfg, actor=actor, loss=loss, optimisers=optimisers, target_updater=target_updater)
