"""SAC (Haarnoja et al. 2018) on torchrl's ``SACLoss``: twin Q, Polyak targets, learned alpha.

docs/model.md §8 / paper Table 4: actor lr 1e-4, critic lr 3e-4, batch 256, gamma 0.99, 2x64 hidden.

``update(batch)`` takes a replay sample of shape ``[N]`` with
``"observation"``, ``"action"``, ``("next", "observation")``, ``("next", "reward")``,
``("next", "done")``, ``("next", "terminated")`` and does one gradient step on actor, both Q
nets and log(alpha) (one fused Adam, a parameter group each), then one soft update of the target
Q nets (a ``lerp_`` per parameter).

The gradients come from ``SACLoss`` itself (``loss_impl: torchrl``: its forward, then autograd)
or, by default, from :class:`uavlae.algos.sac_fused.FusedSACGrad` (``loss_impl: fused``): the
same losses and gradients of the same parameters, written out as plain tensor ops (its speed:
docs/performance.md).

Beyond the paper, off by default (``clone_weight: 0``): a cloning term toward the executed
advice, so an advisor's skill reaches the actor and not only the critic. On the replayed rows
whose ``action_source`` is an advisor's own answer (LLM, heuristic, student or scripted:
``uavlae.policies.override.ADVICE_SOURCES``; never the actor's own rows nor a failed advisor's
fallback), the actor's deterministic action ``tanh(loc)`` is pulled toward the replayed action
by a squared error, averaged over the whole sample (rows without advice add 0). With teacher
labels (``advisor.label_all``: the replayed rows carry ``"advice"``, the advisor's answer on every
row, the actor's own included) the pull is toward the label on every labelled row (DAgger)::

    L_clone = w_t * mean_i m_i * ||tanh(loc_i) - a_i||^2

A squared error on the mean stays finite at |a| = 1, where the override clamps and the
heuristic often acts (a log-likelihood of a tanh-Gaussian would diverge there). ``w_t`` is
``clone_weight``, decayed linearly to 0 over ``clone_decay_frames`` (null: constant) and, with
``clone_scale: actor_loss``, multiplied by ``max(|loss_actor|, 1)`` of the same sample
(detached): TD3+BC's normalisation (Fujimoto & Gu 2021) by the size of the Q term, so one weight
means the same in worlds whose returns differ by orders of magnitude.

Also beyond the paper, off by default (``layer_norm: false``): a LayerNorm after each hidden
linear layer of the actor and both Q nets, before the activation; with wider layers
(``conf/algo/sac_ln.yaml``: 2x256) it asks whether Table 4's 2x64 networks limit SAC here.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, ClassVar, Literal

import torch
from pydantic import Field, model_validator
from tensordict import TensorDictBase
from torchrl.data import Bounded, TensorSpec
from torchrl.modules import ProbabilisticActor
from torchrl.objectives import SACLoss, SoftUpdate

from uavlae.algos.common import (
    StrictConfig,
    apply_gradients,
    load_parts_state_dict,
    optimiser_step,
    parse_config,
    parts_state_dict,
    to_floats,
)
from uavlae.algos.sac_fused import FusedSACGrad
from uavlae.policies.networks import Activation, action_bounds, make_q_critic, make_sac_actor
from uavlae.policies.override import ADVICE_SOURCES


class SACConfig(StrictConfig):
    name: Literal["sac"] = "sac"
    hidden: tuple[int, ...] = Field((64, 64), min_length=1)  # Table 4: 2 hidden layers of 64
    activation: Activation = "relu"
    # Beyond the paper: a LayerNorm after each hidden layer of the actor and both Q nets (the
    # OmniDrones-style SAC of conf/algo/sac_ln.yaml); needs loss_impl torchrl.
    layer_norm: bool = False
    actor_lr: float = Field(1e-4, gt=0)  # Table 4
    critic_lr: float = Field(3e-4, gt=0)  # Table 4
    alpha_lr: float = Field(3e-4, gt=0)  # [decision] unstated; Haarnoja 2018 uses 3e-4
    gamma: float = Field(0.99, gt=0, le=1)  # Table 4
    tau: float = Field(0.005, gt=0, le=1)  # Polyak factor of the target Q nets
    alpha_init: float = Field(1.0, gt=0)
    target_entropy: float | Literal["auto"] = "auto"  # auto: -act_dim (Haarnoja 2018), in any action_scale
    # Beyond the paper: the actor's action box is this many times the env's. The env clips each
    # coordinate to [-1, 1] and the speed to v_max (docs/model.md §2), so with 2 full speed lies at
    # |tanh| >= 0.5, inside tanh's linear range: SAC's entropy term, which prices saturating the
    # tanh, no longer prices flying at v_max. 1: the paper's actor.
    action_scale: float = Field(1.0, ge=1.0)
    num_qvalue_nets: int = Field(2, ge=1)
    loss_function: Literal["l2", "smooth_l1", "l1"] = "l2"
    max_grad_norm: float | None = Field(None, gt=0)  # None: no clipping
    # fused: SACLoss's gradients written out by hand (sac_fused.py; same maths, tested against
    # autograd through SACLoss); torchrl: SACLoss's forward and autograd (the reference).
    loss_impl: Literal["fused", "torchrl"] = "fused"
    # torch.compile SACLoss (loss_impl torchrl only), after a one-off compile; the eager fused
    # update stays faster (docs/performance.md).
    compile: bool = False
    compile_simdlen: int | None = Field(128, gt=0)  # inductor CPU vector bits; see compile_loss
    # Beyond the paper (module doc): a cloning term toward the executed advice; 0: off.
    clone_weight: float = Field(0.0, ge=0)
    clone_decay_frames: int | None = Field(None, ge=1)  # linear decay of the weight to 0 (null: constant)
    clone_scale: Literal["actor_loss", "none"] = "actor_loss"  # the weight times max(|loss_actor|, 1), or as is
    # Read by the collector / training loop, not by update():
    batch_size: int = Field(256, ge=1)  # Table 4
    buffer_size: int = Field(1_000_000, ge=1)
    init_random_frames: int = Field(5_000, ge=0)  # uniform-random actions before learning
    utd_ratio: float = Field(1.0, gt=0)  # gradient steps per collected env frame

    @model_validator(mode="after")
    def _compile_needs_torchrl(self) -> SACConfig:
        if self.compile and self.loss_impl != "torchrl":
            raise ValueError(
                "algo.compile compiles torchrl's SACLoss and needs algo.loss_impl=torchrl; the default "
                "fused update is faster uncompiled (docs/performance.md)"
            )
        if self.layer_norm and self.loss_impl != "torchrl":
            raise ValueError(
                "algo.layer_norm needs algo.loss_impl=torchrl: the fused gradients (sac_fused.py) are written "
                "for plain MLPs, without LayerNorm"
            )
        return self


def make_sac_config(cfg: Any = None, **overrides: Any) -> SACConfig:
    return parse_config(SACConfig, cfg, **overrides)


_LOG_KEYS = ("loss_actor", "loss_qvalue", "loss_alpha", "alpha", "entropy", "loss_clone")
_GROUPS = ("actor", "critic", "alpha")  # the Adam parameter groups, in this order


def compile_loss(loss: SACLoss, simdlen: int | None) -> Any:
    """``torch.compile`` of the loss forward (and with it its backward).

    ``simdlen``: inductor's CPU vector width in bits (a public ``torch.compile`` option). The
    backward keeps each ReLU's mask as a bool tensor, which inductor's 256-bit kernels store
    slowly on some CPUs; 128 avoids that (docs/performance.md). None: inductor's choice."""
    options = None if simdlen is None else {"cpp.simdlen": simdlen}
    return torch.compile(loss, options=options)


@dataclass
class SAC:
    """The SAC learner: loss, optimiser, target updater. Build it with :func:`make_sac`."""

    cfg: SACConfig
    actor: ProbabilisticActor  # the acting policy; shares its parameters with ``loss``
    loss: SACLoss
    optimisers: dict[str, torch.optim.Optimizer]  # {"sac": Adam with groups actor/critic/alpha}
    target_updater: SoftUpdate  # owns the source/target pairing and tau
    num_updates: int = 0
    clone_now: float = 0.0  # the cloning weight at the current frame (anneal), before clone_scale
    off_policy: ClassVar[bool] = True
    # What _losses returns that the torchrl path sums into one backward, and what a step logs; a
    # learner built on SAC's losses adds its own terms to both.
    _loss_keys: ClassVar[tuple[str, ...]] = ("loss_actor", "loss_qvalue", "loss_alpha", "loss_clone")
    _log_keys: ClassVar[tuple[str, ...]] = _LOG_KEYS
    _loss_fn: Any = field(default=None, repr=False)
    _in_keys: list = field(default_factory=list, repr=False)
    _sources: list = field(default_factory=list, repr=False)
    _targets: list = field(default_factory=list, repr=False)
    _tau: float = field(default=0.0, repr=False)
    _fused: FusedSACGrad | None = field(default=None, repr=False)

    def __post_init__(self) -> None:
        # Only the loss is compiled: the fused Adam is already one kernel per group, and more
        # graphs mean more guard checks.
        self._loss_fn = compile_loss(self.loss, self.cfg.compile_simdlen) if self.cfg.compile else self.loss
        self._in_keys = list(self.loss.in_keys)
        # SoftUpdate(SACLoss) pairs the Q nets' parameters with their targets, leaf by leaf; the
        # loss exposes both as public TensorDictParams with the same keys.
        target = self.loss.target_qvalue_network_params
        for key, source in self.loss.qvalue_network_params.items(True, True):
            self._sources.append(source.data)
            self._targets.append(target.get(key).data)
        self._tau = 1.0 - self.target_updater.eps  # SoftUpdate's own weight, bit for bit
        if self.cfg.loss_impl == "fused":
            box = self.actor.spec["action"].space
            self._fused = FusedSACGrad(self.loss, self.cfg.activation, box.low, box.high)
            groups = self.optimisers["sac"].param_groups
            if sorted(map(id, self._fused.params)) != sorted(id(p) for g in groups for p in g["params"]):
                raise RuntimeError("the optimiser's parameters are not the loss's")  # make_sac bug
        self.anneal(0)

    @property
    def behaviour(self) -> ProbabilisticActor:
        """What acts while collecting: the actor, sampling."""
        return self.actor

    def anneal(self, frames: int) -> None:
        """The schedules that follow training progress: the cloning weight at ``frames``."""
        w, decay = self.cfg.clone_weight, self.cfg.clone_decay_frames
        self.clone_now = w if decay is None else w * max(0.0, 1.0 - frames / decay)

    def _clone_mask(self, batch: TensorDictBase) -> torch.Tensor | None:
        """Bool ``[N]``: the replayed rows an advisor acted on, or with teacher labels the rows it
        labelled (None: cloning off now)."""
        if self.clone_now <= 0:
            return None
        if "advice_ok" in batch.keys():
            return batch.get("advice_ok").reshape(-1)
        source = batch.get("action_source", None)
        if source is None:
            raise KeyError("algo.clone_weight > 0 needs 'action_source' in the replayed batch")
        return torch.isin(source.reshape(-1), torch.tensor(ADVICE_SOURCES, device=source.device))

    def _step(self, batch: TensorDictBase, mask: torch.Tensor | None) -> dict[str, torch.Tensor]:
        relative = self.cfg.clone_scale == "actor_loss"
        if self._fused is not None:
            out, grads = self._fused.grads(batch, self.clone_now, mask, relative, clone_target(batch))
            for p, g in zip(self._fused.params, grads):
                p.grad = g
            norms = apply_gradients(self.optimisers, self.cfg.max_grad_norm)
        else:
            out = self._losses(batch, mask, relative)
            total = sum(out[k] for k in self._loss_keys)
            norms = optimiser_step(self.optimisers, total, self.cfg.max_grad_norm)
        with torch.no_grad():
            # SoftUpdate: target <- target + tau (source - target)
            for target, source in zip(self._targets, self._sources):
                target.lerp_(source, self._tau)
        logs = {k: out[k].detach() for k in self._log_keys}
        logs.update((k, v.detach()) for k, v in norms.items())
        return logs

    def _losses(self, batch: TensorDictBase, mask: torch.Tensor | None, relative: bool) -> dict[str, torch.Tensor]:
        """SACLoss's losses through autograd (``loss_impl: torchrl``) and the cloning term."""
        out = dict(self._loss_fn(batch.select(*self._in_keys)).items())
        loss_clone = torch.zeros(())
        if mask is not None:
            w = self.clone_now * (max(abs(float(out["loss_actor"].detach())), 1.0) if relative else 1.0)
            loss_clone = clone_loss(self.actor, batch.get("observation"), clone_target(batch), mask, w)
        out["loss_clone"] = loss_clone
        return out

    def update(self, batch: TensorDictBase) -> dict[str, float]:
        """One gradient step on ``batch`` (see the module doc for its keys); returns log scalars."""
        # A fixed set of keys for SACLoss (_step): the loss writes "td_error" into its input, and
        # a compiled loss would recompile on every new key structure. The caller's batch is left
        # untouched.
        out = self._step(batch, self._clone_mask(batch))
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
        """Actor, Q nets, target Q nets, log_alpha (all in ``loss``), optimiser, counters."""
        return parts_state_dict(self._parts(), self.num_updates)

    def load_state_dict(self, state: dict[str, Any]) -> None:
        if set(state["optimisers"]) == set(_GROUPS):  # written before the optimisers were merged
            state = {**state, "optimisers": {"sac": _merge_adam_states(state["optimisers"])}}
        self.num_updates = load_parts_state_dict(self._parts(), state)


def clone_target(batch: TensorDictBase) -> torch.Tensor:
    """What the cloning term pulls the actor toward: the teacher's labels (``"advice"``, written
    with ``advisor.label_all``) where the batch has them, else the replayed action."""
    return batch.get("advice") if "advice" in batch.keys() else batch.get("action")


def clone_loss(actor: ProbabilisticActor, obs: torch.Tensor, action: torch.Tensor, mask: torch.Tensor,
               weight: float) -> torch.Tensor:
    """``weight * mean_i mask_i ||det_i - action_i||^2`` through autograd, ``det`` the actor's
    deterministic action (``tanh(loc)`` mapped onto its action box): the module doc's cloning
    term, and the reference for the fused gradient."""
    from tensordict import TensorDict

    loc = actor.get_dist_params(TensorDict({"observation": obs}, batch_size=obs.shape[:1])).get("loc")
    box = actor.spec["action"].space
    det = loc.tanh() * (box.high - box.low) / 2 + (box.high + box.low) / 2  # the deterministic action
    diff = (det - action) * mask.reshape(-1, 1).to(loc.dtype)
    return weight * diff.square().sum(-1).mean()


def _merge_adam_states(states: dict[str, Any]) -> dict[str, Any]:
    """One Adam state dict, a named group per old optimiser, from the three separate ones."""
    merged: dict[str, Any] = {"state": {}, "param_groups": []}
    offset = 0
    for name in _GROUPS:
        old = states[name]
        for group in old["param_groups"]:
            merged["param_groups"].append({**group, "name": name, "params": [i + offset for i in group["params"]]})
        merged["state"].update({i + offset: s for i, s in old["state"].items()})
        offset += sum(len(g["params"]) for g in old["param_groups"])
    return merged


def scaled_action_box(action_spec: TensorSpec, scale: float) -> Bounded:
    """The actor's box: the env's per-sample box (:func:`action_bounds`) scaled by ``scale`` about its centre."""
    box = action_bounds(action_spec)
    if scale == 1.0:
        return box
    low, high = box.space.low, box.space.high
    mid, half = (high + low) / 2, (high - low) / 2 * scale
    return Bounded(mid - half, mid + half, shape=box.shape, dtype=box.dtype, device=box.device)


def make_sac(cfg: SACConfig | Any, obs_dim: int, action_spec: TensorSpec) -> SAC:
    """Build SAC for observations ``[obs_dim]`` and the env's bounded ``action_spec``."""
    cfg = make_sac_config(cfg)
    box = scaled_action_box(action_spec, cfg.action_scale)
    act_dim = box.shape[-1]
    actor = make_sac_actor(obs_dim, box, cfg.hidden, cfg.activation, cfg.layer_norm)
    qvalue = make_q_critic(obs_dim, act_dim, cfg.hidden, cfg.activation, cfg.layer_norm)
    # auto: -act_dim whatever the box: the entropy is measured in the action's own units, which
    # are the env's (velocity / v_max) in a wider box too, so the draws spread as far in velocity
    # as the paper's actor's (the wider box's extra room is what the tanh gives up at its edge)
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
    # One Adam, a group per part: Adam is per-parameter, so this is the maths of three Adams
    # at a third of the optimiser calls. Fused: one kernel per group instead of a Python loop.
    groups = [
        {"name": "actor", "params": list(loss.actor_network_params.values(True, True)), "lr": cfg.actor_lr},
        {"name": "critic", "params": list(loss.qvalue_network_params.values(True, True)), "lr": cfg.critic_lr},
        {"name": "alpha", "params": [loss.log_alpha], "lr": cfg.alpha_lr},
    ]
    optimisers = {"sac": torch.optim.Adam(groups, fused=True)}
    target_updater = SoftUpdate(loss, tau=cfg.tau)
    return SAC(cfg=cfg, actor=actor, loss=loss, optimisers=optimisers, target_updater=target_updater)
