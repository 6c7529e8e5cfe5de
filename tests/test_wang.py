"""The ``wang`` baseline: entity tokens cut from the observation, order and absence invariance of
the entity transformer, RND's running statistics by hand, one update and a checkpoint round trip."""

from __future__ import annotations

import copy
import math

import pytest
import torch
from torchrl.envs.utils import ExplorationType, set_exploration_type

from uavlae.algos import make_learner
from uavlae.algos.wang import RunningStd, make_wang, make_wang_config
from uavlae.envs import UAVEnv
from uavlae.policies.entity_transformer import EntityTransformer

TINY = {"epochs": 1, "minibatch_size": 32, "transformer": {"d_model": 16, "n_heads": 2, "n_layers": 2, "ff": 32}}


@pytest.fixture(scope="module")
def env() -> UAVEnv:
    return UAVEnv(batch_size=[6], seed=4)


@pytest.fixture(scope="module")
def td0(env):
    return env.reset()


def _net(env, seed=0) -> EntityTransformer:
    torch.manual_seed(seed)
    return EntityTransformer(env.layout, d_model=16, n_heads=2, n_layers=2, ff=32).eval()


def test_tokens_are_the_observation_columns_of_each_entity(env, td0):
    s, obs = td0["state"], td0["observation"]
    tok = _net(env).tokens(obs)
    X = env.cfg.area.x_size
    ge, ge_present = tok["ge"]
    assert torch.allclose(ge[..., :2], s["ge_pos"] / X)
    assert torch.allclose(ge[..., 2:4], (s["ge_pos"] - s["position"].unsqueeze(-2)) / X, atol=1e-6)
    assert torch.allclose(ge[..., 4], s["ge_remaining"] / env.cfg.ge.data_max)
    assert torch.equal(ge_present, s["ge_mask"])
    for name in ("nfz", "rz", "bz"):
        feat, present = tok[name]
        r = s[name]
        assert torch.allclose(feat[..., :2], r[..., :2] / X) and torch.allclose(feat[..., 2:4], (r[..., 2:] - r[..., :2]) / X)
        assert torch.equal(present, s[f"{name}_mask"])
    dcu, dcu_present = tok["dcu"]
    assert torch.allclose(dcu[..., 0, :2], s["position"] / X) and dcu_present.all()
    ou, seen = tok["ou"]
    d = torch.linalg.vector_norm(s["ou_pos"] - s["position"].unsqueeze(-2), dim=-1)
    assert torch.equal(seen.sum(-1), ((d <= env.cfg.safety.perception_radius) & s["ou_mask"]).sum(-1))
    # every column is in exactly one token: 6 + 4 (GE) + 5 per zone + 5 per OU, the rest the DCU's
    t = _net(env).tokens
    assert 5 * t.n_ge + 5 * sum(t.n_zone) + 5 * t.n_ou + t.n_dcu == env.layout.size


def test_output_does_not_depend_on_the_order_of_the_tokens(env, td0):
    net = _net(env)
    tokens = net.tokens(td0["observation"])
    ref = net.encode(tokens)
    g = torch.Generator().manual_seed(0)
    shuffled = {}
    for name, (x, present) in tokens.items():
        perm = torch.randperm(x.shape[-2], generator=g)
        shuffled[name] = (x[..., perm, :], present[..., perm])
    assert torch.allclose(net.encode(shuffled), ref, atol=1e-5)
    # the types are told apart: swapping the NFZ and BZ lists' roles changes the output
    assert not torch.allclose(net.encode({**tokens, "nfz": tokens["bz"], "bz": tokens["nfz"]}), ref, atol=1e-4)
    # the same through the flat observation: GE slots permuted column-wise give the same output
    obs = td0["observation"]
    G = net.tokens.n_ge
    perm = torch.randperm(G, generator=g)
    xy = obs[:, : 2 * G].reshape(-1, G, 2)[:, perm].reshape(-1, 2 * G)
    rest = [obs[:, 2 * G + i * G : 2 * G + (i + 1) * G][:, perm] for i in range(3)]
    permuted = torch.cat([xy, *rest, obs[:, 5 * G :]], dim=-1)
    assert not torch.equal(permuted, obs)
    assert torch.allclose(net(permuted), net(obs), atol=1e-5)


def test_absent_entities_change_nothing(env, td0):
    net = _net(env)
    tokens = net.tokens(td0["observation"])
    ref = net.encode(tokens)
    # whatever the padded columns of an absent entity hold
    noisy = {}
    for name, (x, present) in tokens.items():
        junk = torch.randn_like(x) * 10
        noisy[name] = (torch.where(present.unsqueeze(-1), x, junk), present)
    assert torch.allclose(net.encode(noisy), ref, atol=1e-5)
    # dropping them altogether (row by row: rows have different counts)
    for row in range(ref.shape[0]):
        kept = {name: (x[row : row + 1, present[row]], present[row : row + 1, present[row]]) for name, (x, present) in tokens.items()}
        assert torch.allclose(net.encode(kept)[0], ref[row], atol=1e-5)
    # a present entity does change it
    x, present = tokens["ge"]
    moved = {**tokens, "ge": (x + present.unsqueeze(-1) * 0.1, present)}
    assert not torch.allclose(net.encode(moved), ref, atol=1e-4)


def test_running_std_hand_computed():
    rs = RunningStd()
    rs.update(torch.tensor([1.0, 2.0, 3.0]))
    assert rs.mean == pytest.approx(2.0) and rs.var == pytest.approx(2.0 / 3.0)
    rs.update(torch.tensor([4.0]))  # 1..4: mean 2.5, population variance 1.25
    assert rs.mean == pytest.approx(2.5) and rs.var == pytest.approx(1.25) and rs.std == pytest.approx(math.sqrt(1.25))


def test_intrinsic_reward_is_the_standardised_rnd_error(env):
    algo = make_wang(TINY, env.layout.size, env.action_spec, env.layout)
    obs = torch.rand(40, env.layout.size)
    e = algo.rnd.error(obs).detach()
    r = algo.intrinsic_reward(obs)
    # first batch: the running stats are this batch's, so the bonus has mean 0 and population std 1
    assert torch.allclose(r, (e - e.mean()) / e.std(unbiased=False), atol=1e-5)
    assert float(r.mean()) == pytest.approx(0.0, abs=1e-5)


def test_update_trains_actor_critic_and_predictor_only(env):
    algo = make_learner({"name": "wang", **TINY, "rnd": {"weight": 0.5, "epochs": 3, "minibatch_size": 16}},
                        env.layout.size, env.action_spec, layout=env.layout)
    torch.manual_seed(1)
    with torch.no_grad(), set_exploration_type(ExplorationType.RANDOM):
        batch = env.rollout(12, algo.actor, break_when_any_done=False)
    reward = batch["next", "reward"].clone()
    before = {n: [p.detach().clone() for p in m.parameters()] for n, m in
              (("actor", algo.actor), ("critic", algo.critic), ("pred", algo.rnd.predictor), ("target", algo.rnd.target))}
    with torch.no_grad():
        err0 = float(algo.rnd.error(batch["next", "observation"]).mean())
    logs = algo.update(batch)
    assert all(math.isfinite(v) for v in logs.values()) and {"loss_rnd", "intrinsic_reward_mean"} <= set(logs)
    assert torch.equal(batch["next", "reward"], reward)  # the bonus went into a copy
    changed = {n: any(not torch.equal(b, p) for b, p in zip(bs, m.parameters())) for (n, bs), m in
               zip(before.items(), (algo.actor, algo.critic, algo.rnd.predictor, algo.rnd.target))}
    assert changed == {"actor": True, "critic": True, "pred": True, "target": False}
    with torch.no_grad():
        assert float(algo.rnd.error(batch["next", "observation"]).mean()) < err0  # the predictor learns
    with pytest.raises(ValueError, match="ObservationLayout"):
        make_wang(TINY, env.layout.size, env.action_spec)
    with pytest.raises(ValueError, match="multiple of n_heads"):
        make_wang({"transformer": {"d_model": 10, "n_heads": 4}}, env.layout.size, env.action_spec, env.layout)
    with pytest.raises(ValueError, match="algo.rnd.weight"):
        make_wang_config({"rnd": {"weight": -1.0}})


def test_state_dict_round_trip_continues_identically(env):
    def make():
        return make_wang(TINY, env.layout.size, env.action_spec, env.layout)

    torch.manual_seed(0)
    a = make()
    torch.manual_seed(2)
    with torch.no_grad(), set_exploration_type(ExplorationType.RANDOM):
        batch = env.rollout(8, a.actor, break_when_any_done=False)
    a.update(batch.clone())
    state = copy.deepcopy(a.state_dict())
    torch.manual_seed(123)
    b = make()
    b.load_state_dict(state)
    for pa, pb in zip(a.rnd.target.parameters(), b.rnd.target.parameters()):
        assert torch.equal(pa, pb)  # the random target travels with the checkpoint
    torch.manual_seed(7)
    la = a.update(batch.clone())
    torch.manual_seed(7)
    lb = b.update(batch.clone())
    assert la == lb
