"""``loss_impl: fused`` (uavlae.algos.sac_fused): SACLoss's losses and gradients, written out.

The reference is torchrl's ``SACLoss`` forward plus autograd, on the same parameter tensors and
the same seeded noise: every loss and every gradient must agree to float32 rounding, for every
activation and critic loss the config offers, on a box that is not [-1, 1], on deeper nets, and
on real env transitions. Plus one case small enough to do by hand, and the config errors.
"""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Bounded

from uavlae.algos.sac import make_sac, make_sac_config
from uavlae.algos.sac_fused import FusedSACGrad
from uavlae.envs import UAVEnv

_KEYS = ("loss_actor", "loss_qvalue", "loss_alpha", "alpha", "entropy")


def random_batch(n: int, obs_dim: int, seed: int = 0) -> TensorDictBase:
    g = torch.Generator().manual_seed(seed)
    term = torch.rand(n, 1, generator=g) < 0.2
    return TensorDict(
        {
            "observation": torch.randn(n, obs_dim, generator=g),
            "action": torch.rand(n, 2, generator=g) * 2 - 1,
            "next": {
                "observation": torch.randn(n, obs_dim, generator=g),
                "reward": torch.randn(n, 1, generator=g),
                "done": term.clone(),
                "terminated": term,
            },
        },
        [n],
    )


def reference(sac, batch: TensorDictBase, seed: int) -> tuple[dict[str, float], list[torch.Tensor]]:
    """SACLoss forward + autograd: the five outputs and the gradient of each fused parameter."""
    fused = sac._fused
    for p in fused.params:
        p.grad = None
    torch.manual_seed(seed)
    out = sac.loss(batch.select(*sac.loss.in_keys).clone())
    (out["loss_actor"] + out["loss_qvalue"] + out["loss_alpha"]).backward()
    grads = [p.grad.clone() for p in fused.params]
    for p in fused.params:
        p.grad = None
    return {k: float(out[k].detach()) for k in _KEYS}, grads


def fused(sac, batch: TensorDictBase, seed: int) -> tuple[dict[str, float], list[torch.Tensor]]:
    torch.manual_seed(seed)
    out, grads = sac._fused.grads(batch)
    return {k: float(out[k]) for k in _KEYS}, grads


def assert_same(sac, batch: TensorDictBase, seed: int = 1) -> None:
    ref_out, ref_grads = reference(sac, batch, seed)
    out, grads = fused(sac, batch, seed)
    for k in _KEYS:
        assert out[k] == pytest.approx(ref_out[k], rel=1e-5, abs=1e-6), k
    assert len(grads) == len(ref_grads) == len(sac._fused.params)
    for p, g, r in zip(sac._fused.params, grads, ref_grads):
        assert g.shape == p.shape
        scale = float(r.abs().max()) + 1e-12
        assert float((g - r).abs().max()) / scale < 1e-5, tuple(p.shape)


def perturb_targets(sac, scale: float = 0.1) -> None:
    """Targets != online Q nets, so a mixed-up parameter set cannot pass."""
    g = torch.Generator().manual_seed(7)
    with torch.no_grad():
        for v in sac.loss.target_qvalue_network_params.values(True, True):
            v.add_(scale * torch.randn(v.shape, generator=g))


@pytest.mark.parametrize("activation", ["relu", "tanh", "elu", "silu"])
@pytest.mark.parametrize("loss_function", ["l2", "l1", "smooth_l1"])
def test_gradients_match_sacloss(activation, loss_function):
    torch.manual_seed(0)
    cfg = {"activation": activation, "loss_function": loss_function, "hidden": (32, 48, 16), "alpha_init": 0.3}
    sac = make_sac(cfg, 17, Bounded(-1.0, 1.0, shape=(2,)))
    perturb_targets(sac)
    assert_same(sac, random_batch(64, 17))


def test_gradients_match_on_an_asymmetric_box_and_three_q_nets():
    torch.manual_seed(0)
    sac = make_sac({"num_qvalue_nets": 3, "alpha_init": 2.0}, 11, Bounded(torch.tensor([-3.0, 0.0]), torch.tensor([1.0, 0.5]), shape=(2,)))
    assert sac._fused.box is not None
    perturb_targets(sac)
    assert_same(sac, random_batch(32, 11, seed=3))


def test_gradients_match_on_env_transitions():
    env = UAVEnv(batch_size=[8], seed=0)
    torch.manual_seed(0)
    batch = env.rollout(16, break_when_any_done=False).reshape(-1)
    sac = make_sac({}, env.observation_spec["observation"].shape[-1], env.action_spec)
    perturb_targets(sac, 0.02)
    assert_same(sac, batch)


def test_small_case_by_hand():
    """All weights and hidden biases zero: every Q is its output bias and the actor's output is
    0, so loc = 0 and scale = softplus(0 + b) + m = 1 (NormalParamExtractor's bias).
    Q biases (0.5, -1.0), reward 2, terminated: target = 2, loss_q = 1.5^2 + 3^2 = 11.25,
    dloss_q/db_j = 2 (b_j - 2) / 1 = (-3, -6); the actor loss gets no Q gradient (dQ/da = 0)."""
    sac = make_sac({}, 3, Bounded(-1.0, 1.0, shape=(2,)))
    with torch.no_grad():
        for p in sac._fused.params:
            p.zero_()
        sac.loss.qvalue_network_params["module", "4", "bias"].copy_(torch.tensor([[0.5], [-1.0]]))
    batch = TensorDict(
        {
            "observation": torch.tensor([[0.3, -0.2, 0.1]]),
            "action": torch.tensor([[0.5, -0.5]]),
            "next": {
                "observation": torch.zeros(1, 3),
                "reward": torch.tensor([[2.0]]),
                "done": torch.ones(1, 1, dtype=torch.bool),
                "terminated": torch.ones(1, 1, dtype=torch.bool),
            },
        },
        [1],
    )
    torch.manual_seed(0)
    out, grads = sac._fused.grads(batch)
    assert float(out["loss_qvalue"]) == pytest.approx(11.25)
    # fused params: actor (w, b) x 3 = 0..5, Q (w, b) x 3 = 6..11, log_alpha = 12
    assert sac._fused.params[11] is sac.loss.qvalue_network_params["module", "4", "bias"]
    q_bias_grad = grads[11]
    assert q_bias_grad.flatten().tolist() == pytest.approx([-3.0, -6.0])
    # alpha = exp(0) = 1; the Q part of the actor loss is -min(0.5, -1.0) = 1
    assert float(out["loss_actor"]) == pytest.approx(-float(out["entropy"]) + 1.0, abs=1e-6)
    # log-prob of a unit Gaussian pushed through tanh: d/dloc logp = 2 tanh(x) at x = eps
    torch.manual_seed(0)
    eps = torch.empty(1, 2).normal_()  # the next-obs draw comes first ...
    eps = torch.empty(1, 2).normal_()  # ... this is the actor's
    loc_grad = grads[5][:2]  # the actor's output bias: (loc, scale) rows
    assert loc_grad.tolist() == pytest.approx((2 * torch.tanh(eps[0])).tolist(), abs=1e-6)
    assert all(float(g.abs().max()) == 0 for g in grads[6:10])  # Q weights and hidden biases


def test_whole_updates_match_torchrl():
    """Five updates (Adam included) from the same seeds give torchrl's parameters, targets and
    Adam moments to float rounding. (Over many updates the two drift apart at rounding level:
    Adam's first steps turn a ~1e-9 gradient into a full lr-sized step of either sign.)"""
    batch = random_batch(128, 23, seed=2)
    states = {}
    for impl in ("torchrl", "fused"):
        torch.manual_seed(0)
        sac = make_sac({"loss_impl": impl}, 23, Bounded(-1.0, 1.0, shape=(2,)))
        for i in range(5):
            torch.manual_seed(100 + i)
            logs = sac.update(batch.clone())
        assert sac.num_updates == 5 and logs["num_updates"] == 5.0
        states[impl] = sac.state_dict()
    a, b = states["torchrl"], states["fused"]
    for key, value in a["loss"].items():
        if value.is_floating_point():
            assert torch.allclose(value, b["loss"][key], rtol=1e-4, atol=1e-6), key
    for idx, st in a["optimisers"]["sac"]["state"].items():
        for name in ("exp_avg", "exp_avg_sq", "step"):
            assert torch.allclose(st[name], b["optimisers"]["sac"]["state"][idx][name], rtol=1e-4, atol=1e-7), (idx, name)


def test_config_and_unsupported_losses_are_errors():
    assert make_sac_config().loss_impl == "fused"
    with pytest.raises(ValueError, match="loss_impl"):
        make_sac_config({"compile": True})
    with pytest.raises(ValueError, match="algo.loss_impl"):
        make_sac_config({"loss_impl": "jax"})
    make_sac_config({"compile": True, "loss_impl": "torchrl"})  # fine
    sac = make_sac({"loss_impl": "torchrl"}, 5, Bounded(-1.0, 1.0, shape=(2,)))
    assert sac._fused is None
    sac.loss.min_log_alpha = -3.0
    with pytest.raises(ValueError, match="min_alpha"):
        FusedSACGrad(sac.loss, "relu")
