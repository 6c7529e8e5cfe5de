"""SAC-Lagrangian (uavlae.algos.sac_lag): its config, the multiplier's dual ascent on a cost
critic whose value is set by hand, the cost term in the actor's gradient, the cost critic's TD
target, and a short training run."""

from __future__ import annotations

import pytest
import torch
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Bounded

from uavlae.algos import MAKERS, OFF_POLICY, make_learner
from uavlae.algos.sac import make_sac
from uavlae.algos.sac_lag import SACLag, SACLagConfig, make_sac_lag, make_sac_lag_config
from uavlae.factories import CONF_DIR

SPEC = Bounded(-1.0, 1.0, shape=(2,))
OBS = 3


def hand_batch(cost: list[float], terminated: list[bool], seed: int = 0) -> TensorDictBase:
    """A replay sample ``[N]`` with the given per-row cost and termination, random elsewhere."""
    g = torch.Generator().manual_seed(seed)
    n = len(cost)
    term = torch.tensor(terminated).reshape(n, 1)
    return TensorDict(
        {
            "observation": torch.randn(n, OBS, generator=g),
            "action": torch.rand(n, 2, generator=g) * 2 - 1,
            "next": {
                "observation": torch.randn(n, OBS, generator=g),
                "reward": torch.randn(n, 1, generator=g),
                "cost": torch.tensor(cost).reshape(n, 1),
                "done": term.clone(),
                "terminated": term,
            },
        },
        [n],
    )


def set_constant_cost_critic(learner: SACLag, value: float) -> None:
    """Q_c = ``value`` for every input, in the critic and its target: the last layer's weights
    zeroed, its bias set."""
    for net in (learner.cost_critic, learner.cost_target):
        last = [m for m in net.modules() if isinstance(m, torch.nn.Linear)][-1]
        with torch.no_grad():
            last.weight.zero_()
            last.bias.fill_(value)


def lag(**cfg) -> SACLag:
    torch.manual_seed(0)
    return make_sac_lag(cfg, OBS, SPEC)


# ---------------------------------------------------------------- config
def test_composed_yaml_mirrors_the_config():
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        cfg = compose("config", overrides=["+exp=sac_lag"])
    data = OmegaConf.to_container(cfg.algo, resolve=True)
    assert set(data) == set(SACLagConfig.model_fields)
    assert make_sac_lag_config(data) == SACLagConfig()
    assert cfg.name == "sac_lag" and cfg.advisor.kind == "none"
    c = SACLagConfig()
    assert (c.cost_limit, c.cost_discount, c.cost_critic_lr, c.lagrange_every) == (0.05, 0.99, 3e-4, 10)
    assert c.loss_impl == "torchrl" and c.actor_lr == 1e-4 and c.batch_size == 256  # SAC's Table 4 values
    assert make_sac_lag_config({"gamma": 0.9}).cost_discount == 0.9  # null follows gamma
    assert make_sac_lag_config({"cost_gamma": 0.5}).cost_discount == 0.5


@pytest.mark.parametrize(
    "bad, field",
    [
        ({"loss_impl": "fused"}, "algo.loss_impl"),
        ({"cost_limit": -0.1}, "algo.cost_limit"),
        ({"cost_gamma": 1.5}, "algo.cost_gamma"),
        ({"cost_critic_lr": 0.0}, "algo.cost_critic_lr"),
        ({"lagrange_every": 0}, "algo.lagrange_every"),
        ({"lagrange": {"lr": -1.0}}, "algo.lagrange.lr"),
        ({"no_such_key": 1}, "algo.no_such_key"),
    ],
)
def test_bad_config_names_the_key(bad, field):
    with pytest.raises(ValueError, match=field.replace(".", r"\.")):
        make_sac_lag_config(bad)


def test_registered_as_an_off_policy_learner():
    assert "sac_lag" in OFF_POLICY and MAKERS["sac_lag"] is make_sac_lag
    learner = make_learner({"name": "sac_lag"}, OBS, SPEC)
    assert isinstance(learner, SACLag) and learner.off_policy
    groups = [g["name"] for g in learner.optimisers["sac"].param_groups]
    assert groups == ["actor", "critic", "alpha", "cost_critic"]


# ---------------------------------------------------------------- the cost critic's TD target
def test_cost_critic_loss_by_hand():
    # Q_c = 0.5 everywhere (critic and target), gamma_c = 0.5. Rows: cost 1, alive:
    # y = 1 + 0.5 * 0.5 = 1.25, error 0.75; cost 0, terminated: y = 0, error 0.5;
    # cost 0.25, alive: y = 0.25 + 0.25 = 0.5, error 0. Mean squared error (0.5625 + 0.25 + 0) / 3.
    learner = lag(cost_gamma=0.5)
    set_constant_cost_critic(learner, 0.5)
    out = learner._losses(hand_batch([1.0, 0.0, 0.25], [False, True, False]), None, False)
    assert float(out["loss_cost_critic"].detach()) == pytest.approx((0.5625 + 0.25) / 3, rel=1e-6)
    assert float(out["cost_value"].detach()) == 0.5


# ---------------------------------------------------------------- the multiplier
def test_multiplier_dual_ascent_by_hand():
    # Q_c = b exactly at every step: its last layer's weights are 0 and the TD error is 0
    # (cost b (1 - gamma_c) = b / 2 on alive rows, b on terminated ones), so its gradient is 0
    # and Adam leaves it as it is. lambda_k = max(0, lambda_{k-1} + lr (b - d)), lr 1/8, d 1/4:
    # binary fractions, so every value below is exact.
    learner = lag(cost_gamma=0.5, cost_limit=0.25, lagrange_every=1, lagrange={"lr": 0.125, "init": 0.0})

    def step(b: float) -> float:
        set_constant_cost_critic(learner, b)  # in place: the target too (its soft update keeps b)
        logs = learner.update(hand_batch([b / 2, b / 2, b, b / 2], [False, False, True, False]))
        assert logs["cost_value"] == b
        return logs["lagrange"]

    # above the limit: b = 1/2, lr (J - d) = 1/8 * 1/4 = +0.03125 a step
    assert [step(0.5) for _ in range(3)] == [0.03125, 0.0625, 0.09375]
    # below it: b = 1/16, lr (J - d) = 1/8 * -3/16 = -0.0234375 a step, down to 0 and held there
    # (the fifth: max(0, 0 - 0.0234375), projected)
    assert [step(0.0625) for _ in range(5)] == [0.0703125, 0.046875, 0.0234375, 0.0, 0.0]
    assert learner.lagrange.num_updates == 8


def test_multiplier_steps_every_lagrange_every_on_the_window_mean():
    # lagrange_every 3: lambda moves after steps 3 and 6, on the mean of the three measurements.
    # Window 1: (1/2 + 1/2 + 1/8) / 3 = 3/8, lambda = 1/8 (3/8 - 1/4) = 1/64 = 0.015625.
    # Window 2: (1/8 + 1/8 + 1/2) / 3 = 1/4 = d, lambda unchanged.
    learner = lag(cost_gamma=0.5, cost_limit=0.25, lagrange_every=3, lagrange={"lr": 0.125})
    lams = []
    for b in (0.5, 0.5, 0.125, 0.125, 0.125, 0.5):
        set_constant_cost_critic(learner, b)
        lams.append(learner.update(hand_batch([b / 2] * 4, [False] * 4))["lagrange"])
    assert lams == [0.0, 0.0, 0.015625, 0.015625, 0.015625, 0.015625]
    assert learner.lagrange.num_updates == 2 and learner.window_count == 0


# ---------------------------------------------------------------- the actor's gradient
def _grads(learner, batch: TensorDictBase, seed: int = 3) -> dict[str, list[torch.Tensor]]:
    """The gradients of one backward of the summed losses, per parameter group."""
    opt = learner.optimisers["sac"]
    opt.zero_grad(set_to_none=True)
    torch.manual_seed(seed)
    out = learner._losses(batch, None, False)
    sum(out[k] for k in learner._loss_keys).backward()
    grads = {g["name"]: [p.grad.clone() for p in g["params"]] for g in opt.param_groups}
    opt.zero_grad(set_to_none=True)
    return grads


def test_actor_gradient_gains_the_cost_term():
    batch = hand_batch([0.0, 1.0, 0.0, 1.0], [False, True, False, False])
    torch.manual_seed(0)
    sac = make_sac({"loss_impl": "torchrl"}, OBS, SPEC)  # the same first draws: the same actor and critics
    learner = lag()
    for a, b in zip(sac.actor.parameters(), learner.actor.parameters()):
        assert torch.equal(a, b)
    g_sac = _grads(sac, batch)
    g = {lam: _grads(lag(lagrange={"init": lam}), batch) for lam in (0.0, 1.0, 2.0)}
    # lambda = 0: SAC's actor and critic gradients, bit for bit
    for name in ("actor", "critic", "alpha"):
        for x, y in zip(g[0.0][name], g_sac[name]):
            assert torch.equal(x, y), name
    # lambda > 0 moves the actor's gradient, and only the actor's
    assert any(not torch.equal(x, y) for x, y in zip(g[2.0]["actor"], g_sac["actor"]))
    for name in ("critic", "alpha", "cost_critic"):
        for x, y in zip(g[2.0][name], g[0.0][name]):
            assert torch.equal(x, y), name
    # (1 + lambda) g(lambda) = g_SAC + lambda g_c: the cost term's gradient g_c is the same at
    # lambda 1 and 2, so 3 g(2) - g(0) = 2 (2 g(1) - g(0))
    for g0, g1, g2 in zip(g[0.0]["actor"], g[1.0]["actor"], g[2.0]["actor"]):
        torch.testing.assert_close(3 * g2 - g0, 2 * (2 * g1 - g0), rtol=1e-4, atol=1e-6)


def test_cost_term_pushes_the_actor_away_from_costly_actions():
    # Q_c(s, a) = relu(a_0) + 0 * ...: the first hidden unit reads a_0, the others are off, so
    # raising a_0 raises the cost; with lambda large the actor's mean a_0 falls below SAC's.
    batch = hand_batch([0.0] * 16, [False] * 16)

    def mean_a0_after(lam: float) -> float:
        learner = lag(lagrange={"init": lam}, lagrange_every=10_000, cost_critic_lr=1e-12, actor_lr=1e-2)
        for net in (learner.cost_critic, learner.cost_target):
            first, *_, last = [m for m in net.modules() if isinstance(m, torch.nn.Linear)]
            mid = [m for m in net.modules() if isinstance(m, torch.nn.Linear)][1:-1]
            with torch.no_grad():
                for m in (first, *mid, last):
                    m.weight.zero_()
                    m.bias.zero_()
                first.weight[0, OBS] = 1.0  # unit 0 = a_0 (the input is [observation, action])
                for m in mid:
                    m.weight[0, 0] = 1.0
                last.weight[0, 0] = 10.0
        for _ in range(30):
            learner.update(batch)
        with torch.no_grad():
            loc = learner.actor.get_dist_params(batch.select("observation")).get("loc")
        return float(loc[:, 0].mean())

    assert mean_a0_after(100.0) < mean_a0_after(0.0) - 0.01


# ---------------------------------------------------------------- training
def test_sac_lag_trains_end_to_end(tmp_path):
    from tests.test_train import _check_run_outputs, _csv_steps, _run

    final = _run("sac_lag", tmp_path / "sac_lag")
    _check_run_outputs(tmp_path / "sac_lag", final)
    assert final["updates"] > 0
    for metric in ("lagrange", "cost_value", "loss_cost_critic", "alpha"):
        assert _csv_steps(tmp_path / "sac_lag", f"train/{metric}"), metric
