"""Actor and critic factories shared by the learners (docs/model.md §8: 2 hidden layers of 64).

Every factory takes plain sizes and an action spec, so the env, the tests and the learners
build the same modules. Keys follow docs/env_contract.md and torchrl.objectives' defaults:

- stochastic actors (SAC, PPO): ``"observation"`` -> ``"loc"``, ``"scale"`` -> ``"action"``
  (tanh-normal, bounded by the spec), plus ``"action_log_prob"`` when ``return_log_prob``;
- DDPG actor: ``"observation"`` -> ``"param"`` (unbounded) -> ``"action"`` (tanh into bounds);
- Q critic: ``("observation", "action")`` -> ``"state_action_value"``;
- value critic: ``"observation"`` -> ``out_key`` (``"state_value"``, or ``"cost_value"`` for the
  cost critic of the Lagrangian learner).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Literal

import torch
from tensordict.nn import TensorDictModule, TensorDictSequential
from torch import nn
from torchrl.data import Bounded, TensorSpec
from torchrl.modules import (
    MLP,
    AdditiveGaussianModule,
    BatchRenorm1d,
    NormalParamExtractor,
    OrnsteinUhlenbeckProcessModule,
    ProbabilisticActor,
    TanhModule,
    TanhNormal,
    ValueOperator,
)

Activation = Literal["relu", "tanh", "elu", "silu"]
_ACTIVATIONS: dict[str, type[nn.Module]] = {"relu": nn.ReLU, "tanh": nn.Tanh, "elu": nn.ELU, "silu": nn.SiLU}

__all__ = [
    "Activation",
    "CappedBatchRenorm1d",
    "action_bounds",
    "make_batch_renorm_q_critic",
    "make_ddpg_actor",
    "make_ddpg_exploration",
    "make_ppo_actor",
    "make_q_critic",
    "make_sac_actor",
    "make_value_critic",
]


def _activation(name: str) -> type[nn.Module]:
    try:
        return _ACTIVATIONS[name]
    except KeyError:
        raise ValueError(f"activation must be one of {sorted(_ACTIVATIONS)}, got {name!r}") from None


def _mlp(in_features: int, out_features: int, hidden: Sequence[int], activation: str, layer_norm: bool = False) -> MLP:
    """Linear layers of ``hidden`` widths; ``layer_norm``: a LayerNorm after each hidden linear
    layer, before its activation (torchrl's MLP places ``norm_class`` there)."""
    norm = {"norm_class": nn.LayerNorm, "norm_kwargs": [{"normalized_shape": h} for h in hidden]} if layer_norm else {}
    return MLP(
        in_features=in_features,
        out_features=out_features,
        num_cells=list(hidden),
        activation_class=_activation(activation),
        **norm,
    )


def action_bounds(action_spec: TensorSpec) -> Bounded:
    """The per-sample action box ``[act_dim]`` of a (possibly batch-shaped) bounded spec.

    The env declares its action spec with the batch dimension (``[B, 2]``); the networks need
    the box of one sample, which must be the same for every batch row.
    """
    if not isinstance(action_spec, Bounded):
        raise TypeError(f"the action spec must be Bounded, got {type(action_spec).__name__}")
    act_dim = action_spec.shape[-1]
    low = action_spec.space.low.expand(action_spec.shape).reshape(-1, act_dim)
    high = action_spec.space.high.expand(action_spec.shape).reshape(-1, act_dim)
    if not (torch.equal(low, low[:1].expand_as(low)) and torch.equal(high, high[:1].expand_as(high))):
        raise ValueError("the action bounds differ between batch rows; one box per sample is expected")
    return Bounded(low[0].clone(), high[0].clone(), shape=(act_dim,), dtype=action_spec.dtype, device=action_spec.device)


# The scale head: softplus(x + b) + SCALE_MIN with b such that a zero input gives SCALE_AT_ZERO,
# floored at SCALE_LB (tensordict's NormalParamExtractor defaults, spelled out so that the
# hand-written SAC gradients read the same numbers).
SCALE_AT_ZERO = 1.0
SCALE_MIN = 0.01
SCALE_LB = 1e-4


def _tanh_normal_actor(
    obs_dim: int,
    action_spec: TensorSpec,
    hidden: Sequence[int],
    activation: str,
    return_log_prob: bool,
    layer_norm: bool = False,
) -> ProbabilisticActor:
    box = action_bounds(action_spec)
    act_dim = box.shape[-1]
    extractor = NormalParamExtractor(scale_mapping=f"biased_softplus_{SCALE_AT_ZERO}_{SCALE_MIN}", scale_lb=SCALE_LB)
    net = nn.Sequential(_mlp(obs_dim, 2 * act_dim, hidden, activation, layer_norm), extractor)
    params = TensorDictModule(net, in_keys=["observation"], out_keys=["loc", "scale"])
    return ProbabilisticActor(
        params,
        in_keys=["loc", "scale"],
        spec=box,
        distribution_class=TanhNormal,
        distribution_kwargs={"low": box.space.low, "high": box.space.high},
        return_log_prob=return_log_prob,
    )


def make_sac_actor(
    obs_dim: int,
    action_spec: TensorSpec,
    hidden: Sequence[int] = (64, 64),
    activation: Activation = "relu",
    layer_norm: bool = False,
) -> ProbabilisticActor:
    """Tanh-Gaussian actor for SAC: ``"observation"`` -> ``"loc"``, ``"scale"``, ``"action"``.

    SACLoss draws its own reparameterised samples from ``get_dist``; no log-prob is written.
    Under ``ExplorationType.DETERMINISTIC`` the action is the tanh of the mean (evaluation).
    ``layer_norm``: a LayerNorm after each hidden linear layer (it normalises each row alone, so
    acting on one row and learning on a batch see the same network).
    """
    return _tanh_normal_actor(obs_dim, action_spec, hidden, activation, return_log_prob=False, layer_norm=layer_norm)


def make_ppo_actor(
    obs_dim: int,
    action_spec: TensorSpec,
    hidden: Sequence[int] = (64, 64),
    activation: Activation = "tanh",
) -> ProbabilisticActor:
    """Tanh-Gaussian actor for PPO/CPO; also writes ``"action_log_prob"`` for the ratio."""
    return _tanh_normal_actor(obs_dim, action_spec, hidden, activation, return_log_prob=True)


def make_q_critic(
    obs_dim: int,
    act_dim: int,
    hidden: Sequence[int] = (64, 64),
    activation: Activation = "relu",
    layer_norm: bool = False,
) -> ValueOperator:
    """Q(s, a): ``("observation", "action")`` -> ``"state_action_value"`` ``[..., 1]``;
    ``layer_norm`` as :func:`make_sac_actor`."""
    return ValueOperator(
        _mlp(obs_dim + act_dim, 1, hidden, activation, layer_norm),
        in_keys=["observation", "action"],
        out_keys=["state_action_value"],
    )


class CappedBatchRenorm1d(BatchRenorm1d):
    """torchrl's ``BatchRenorm1d`` with its step counter held at ``warmup_steps``.

    Batch renormalisation's correction factors r and d are clamped to [1/max_r, max_r] and
    [-max_d, max_d] and weighted by ``num_batches_tracked // warmup_steps``, which should stop at
    1. torchrl 0.14 writes ``self.num_batches_tracked.clamp_max(...)``, out of place, and drops the
    result: the counter keeps counting, the weight reaches 2 after twice the warm-up and grows from
    there, and r and d leave their clamps. Clamping in place after each training forward keeps the
    weight at 1 (tests/test_algos.py checks that torchrl still needs this)."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        out = super().forward(x)
        if self.training:
            # out of place, then copied: vmap (CrossQLoss runs the Q nets under it) has no rule for clamp_
            self.num_batches_tracked.copy_(self.num_batches_tracked.clamp_max(self.warmup_steps))
        return out


class _ConcatSequential(nn.Sequential):
    """``nn.Sequential`` over the inputs concatenated on their last dimension (as torchrl's MLP)."""

    def forward(self, *inputs: torch.Tensor) -> torch.Tensor:
        return super().forward(torch.cat(inputs, -1))


def make_batch_renorm_q_critic(
    obs_dim: int,
    act_dim: int,
    hidden: Sequence[int],
    activation: Activation = "relu",
    *,
    momentum: float = 0.01,
    eps: float = 1e-3,
    warmup_steps: int = 100_000,
    max_r: float = 3.0,
    max_d: float = 5.0,
) -> ValueOperator:
    """Q(s, a) for CrossQ: ``("observation", "action")`` -> ``"state_action_value"`` ``[..., 1]``,
    with a batch renormalisation before every linear layer, the input's included::

        BRN -> Linear -> act -> BRN -> Linear -> act -> ... -> BRN -> Linear(1)

    (the CrossQ paper's critic, as sb3-contrib builds it). In training mode each BRN normalises
    by the statistics of the batch it is given: CrossQLoss gives it the current and the next
    state-actions together, so both are normalised alike; in eval mode (CrossQLoss's actor loss)
    it uses its running statistics, which are buffers of the module and so of its state dict."""
    act = _activation(activation)
    norm = {"momentum": momentum, "eps": eps, "warmup_steps": warmup_steps, "max_r": max_r, "max_d": max_d}
    layers: list[nn.Module] = []
    width = obs_dim + act_dim
    for h in hidden:
        layers += [CappedBatchRenorm1d(width, **norm), nn.Linear(width, h), act()]
        width = h
    layers += [CappedBatchRenorm1d(width, **norm), nn.Linear(width, 1)]
    return ValueOperator(_ConcatSequential(*layers), in_keys=["observation", "action"], out_keys=["state_action_value"])


def make_value_critic(
    obs_dim: int,
    hidden: Sequence[int] = (64, 64),
    out_key: str = "state_value",
    activation: Activation = "tanh",
) -> ValueOperator:
    """V(s): ``"observation"`` -> ``out_key`` ``[..., 1]``."""
    return ValueOperator(_mlp(obs_dim, 1, hidden, activation), in_keys=["observation"], out_keys=[out_key])


def make_ddpg_actor(
    obs_dim: int,
    action_spec: TensorSpec,
    hidden: Sequence[int] = (64, 64),
    activation: Activation = "relu",
) -> TensorDictSequential:
    """Deterministic actor: ``"observation"`` -> ``"param"`` -> ``"action"`` = tanh into the box."""
    box = action_bounds(action_spec)
    act_dim = box.shape[-1]
    param = TensorDictModule(_mlp(obs_dim, act_dim, hidden, activation), in_keys=["observation"], out_keys=["param"])
    squash = TanhModule(in_keys=["param"], out_keys=["action"], spec=box)
    return TensorDictSequential(param, squash)


def make_ddpg_exploration(
    actor: TensorDictModule,
    action_spec: TensorSpec,
    *,
    kind: Literal["gaussian", "ou"] = "gaussian",
    sigma_init: float = 0.3,
    sigma_end: float = 0.05,
    annealing_num_steps: int = 100_000,
    ou_theta: float = 0.15,
    ou_dt: float = 1.0,
) -> tuple[TensorDictSequential, nn.Module]:
    """The DDPG behaviour policy: ``actor`` followed by annealed noise, projected into the box.

    Returns ``(policy, noise)``; the training loop calls ``noise.step(frames)`` after each
    collected batch to anneal sigma from ``sigma_init`` to ``sigma_end`` over
    ``annealing_num_steps`` frames. Noise is only added under ``ExplorationType.RANDOM`` (the
    collector's default); evaluation under ``DETERMINISTIC`` gets the bare actor.

    ``kind="ou"`` is the Ornstein-Uhlenbeck process of the DDPG paper; it keeps its state per
    batch row and needs an ``"is_init"`` entry (torchrl's ``InitTracker`` transform) to reset it.
    """
    box = action_bounds(action_spec)
    if kind == "gaussian":
        noise: nn.Module = AdditiveGaussianModule(
            spec=box,
            sigma_init=float(sigma_init),
            sigma_end=float(sigma_end),
            annealing_num_steps=annealing_num_steps,
            safe=False,  # _add_noise already projects into the box
        )
    elif kind == "ou":
        noise = OrnsteinUhlenbeckProcessModule(
            spec=box,
            eps_init=1.0,
            eps_end=float(sigma_end / sigma_init) if sigma_init > 0 else 0.0,
            annealing_num_steps=annealing_num_steps,
            theta=ou_theta,
            sigma=sigma_init,
            dt=ou_dt,
            safe=True,
        )
    else:
        raise ValueError(f"exploration kind must be 'gaussian' or 'ou', got {kind!r}")
    return TensorDictSequential(actor, noise), noise
