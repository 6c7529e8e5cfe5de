"""Learners (uavlae.algos) and their networks: Lagrange maths by hand, one update on real env
data for every learner, checkpoint round trips, and a small SAC learning check."""

from __future__ import annotations

import copy
import math

import pytest
import torch
import yaml
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Bounded
from torchrl.envs.utils import ExplorationType, set_exploration_type

from uavlae.algos.crossq import CrossQConfig, make_crossq, make_crossq_config
from uavlae.algos.ddpg import DDPGConfig, make_ddpg, make_ddpg_config
from uavlae.algos.ppo import PPOConfig, make_ppo, make_ppo_config
from uavlae.algos.ppo_lagrangian import (
    CPOConfig,
    LagrangeMultiplier,
    gaussian_kl,
    make_cpo_config,
    make_ppo_lagrangian,
)
from uavlae.algos.sac import SACConfig, make_sac, make_sac_config
from uavlae.algos.sac_lag import make_sac_lag
from uavlae.factories import CONF_DIR
from uavlae.envs import UAVEnv
from uavlae.policies.networks import CappedBatchRenorm1d, action_bounds, make_sac_actor

CONF = CONF_DIR / "algo"


# ---------------------------------------------------------------- Lagrange multiplier
def test_dual_ascent_hand_computed():
    lam = LagrangeMultiplier({"method": "dual_ascent", "lr": 0.1, "init": 0.0}, limit=0.05)
    # lambda <- max(0, lambda + 0.1 * (0.5 - 0.05))
    assert lam.update(0.5) == pytest.approx(0.045, abs=1e-12)
    assert lam.update(0.5) == pytest.approx(0.09, abs=1e-12)
    # below the limit: -0.1 * 0.05 = -0.005 a step, so 0.09 reaches 0 after 18 steps
    values = [lam.update(0.0) for _ in range(25)]
    assert values[0] == pytest.approx(0.085, abs=1e-12)
    assert all(b <= a for a, b in zip(values, values[1:]))
    assert min(values) >= 0.0
    assert values[-1] == 0.0 and lam.value == 0.0  # exactly zero, clipped, never negative
    assert lam.update(0.5) == pytest.approx(0.045, abs=1e-12)  # rises again from zero


def test_dual_ascent_limit_argument_and_cap():
    lam = LagrangeMultiplier({"lr": 1.0, "max_value": 0.3}, limit=0.05)
    assert lam.update(0.15, limit=0.1) == pytest.approx(0.05)  # the call's limit wins
    assert lam.update(10.0) == 0.3  # projected onto [0, max_value]
    with pytest.raises(ValueError, match="finite"):
        lam.update(float("nan"))


def test_pid_lagrangian_hand_computed_and_monotone():
    cfg = {"method": "pid", "kp": 0.05, "ki": 0.01, "kd": 0.01, "init": 0.0}
    lam = LagrangeMultiplier(cfg, limit=0.05)
    # e = 0.45, I = 0.45, D = 0 (first step): 0.05 * 0.45 + 0.01 * 0.45
    assert lam.update(0.5) == pytest.approx(0.027)
    # rising cost: e = 0.55, I = 1.0, D = 0.1
    assert lam.update(0.6) == pytest.approx(0.05 * 0.55 + 0.01 * 1.0 + 0.01 * 0.1)
    up = [lam.update(0.6) for _ in range(20)]
    assert all(b > a for a, b in zip(up, up[1:]))  # integral keeps growing above the limit
    down = [lam.update(0.0) for _ in range(400)]
    assert all(b <= a for a, b in zip(down, down[1:]))
    assert min(down) >= 0.0 and down[-1] == 0.0


def test_lagrange_state_round_trip():
    a = LagrangeMultiplier({"method": "pid"}, limit=0.05)
    for c in (0.3, 0.2, 0.4):
        a.update(c)
    b = LagrangeMultiplier({"method": "pid"}, limit=0.05)
    b.load_state_dict(copy.deepcopy(a.state_dict()))
    assert b.state_dict() == a.state_dict()
    assert b.update(0.1) == a.update(0.1)


# ---------------------------------------------------------------- configs
@pytest.mark.parametrize(
    "name, make, model",
    [
        ("sac", make_sac_config, SACConfig),
        ("ddpg", make_ddpg_config, DDPGConfig),
        ("ppo", make_ppo_config, PPOConfig),
        ("cpo", make_cpo_config, CPOConfig),
        ("crossq", make_crossq_config, CrossQConfig),
    ],
)
def test_yaml_mirrors_config(name, make, model):
    data = yaml.safe_load((CONF / f"{name}.yaml").read_text())
    assert set(data) == set(model.model_fields)
    assert make(data) == model()


def test_sac_ln_yaml_is_sac_with_three_keys_changed():
    data = yaml.safe_load((CONF / "sac_ln.yaml").read_text())
    assert set(data) == set(SACConfig.model_fields)
    assert make_sac_config(data) == SACConfig(hidden=(256, 256), layer_norm=True, loss_impl="torchrl")


@pytest.mark.parametrize("name", ["sac", "ddpg", "ppo", "cpo", "crossq"])
def test_make_learner_dispatches_on_name(name):
    from omegaconf import OmegaConf

    from uavlae.algos import MAKERS, make_learner

    node = OmegaConf.create(yaml.safe_load((CONF / f"{name}.yaml").read_text()))
    learner = make_learner(node, 5, Bounded(-1.0, 1.0, shape=(4, 2)))
    assert learner.cfg.name == name and type(learner).__module__ == MAKERS[name].__module__
    with pytest.raises(ValueError, match="algo.name"):
        make_learner({"name": "trpo"}, 5, Bounded(-1.0, 1.0, shape=(2,)))


def test_config_errors_name_the_field():
    with pytest.raises(ValueError, match="algo.actor_lr"):
        make_sac_config({"actor_lr": -1.0})
    with pytest.raises(ValueError, match="algo.learning_rate"):
        make_ppo_config({"learning_rate": 1e-3})
    with pytest.raises(ValueError, match="sigma_end"):
        make_ddpg_config({"noise": {"sigma_init": 0.1, "sigma_end": 0.2}})
    assert make_sac_config().actor_lr == 1e-4 and make_sac_config().critic_lr == 3e-4
    assert make_ppo_config().clip_epsilon == 0.2 and make_cpo_config().cost_limit == 0.05
    with pytest.raises(ValueError, match="algo.layer_norm needs algo.loss_impl=torchrl"):
        make_sac_config({"layer_norm": True})  # the fused default knows plain MLPs only
    assert make_sac_config({"layer_norm": True, "loss_impl": "torchrl"}).layer_norm
    with pytest.raises(ValueError, match="algo.policy_delay"):
        make_crossq_config({"policy_delay": 0})
    with pytest.raises(ValueError, match="algo.batch_renorm.momentum"):
        make_crossq_config({"batch_renorm": {"momentum": 0.0}})
    with pytest.raises(ValueError, match="algo.adam_beta1"):
        make_crossq_config({"adam_beta1": 1.0})


# ---------------------------------------------------------------- env data
@pytest.fixture(scope="module")
def env() -> UAVEnv:
    return UAVEnv(batch_size=[8], seed=0)


@pytest.fixture(scope="module")
def obs_dim(env) -> int:
    return env.observation_spec["observation"].shape[-1]


@pytest.fixture(scope="module")
def replay_batch(env) -> TensorDictBase:
    """Random-action transitions as a replay buffer would return them: ``[128]``."""
    torch.manual_seed(0)
    return env.rollout(16, break_when_any_done=False).reshape(-1)


def on_policy_batch(env, actor) -> TensorDictBase:
    torch.manual_seed(1)
    with torch.no_grad(), set_exploration_type(ExplorationType.RANDOM):
        return env.rollout(16, actor, break_when_any_done=False)


def params(module: torch.nn.Module) -> list[torch.Tensor]:
    return [p.detach().clone() for p in module.parameters()]


def changed(before: list[torch.Tensor], module: torch.nn.Module) -> bool:
    return any(not torch.equal(b, p) for b, p in zip(before, module.parameters()))


def td_equal(a: TensorDictBase, b: TensorDictBase) -> bool:
    return all(torch.equal(a[k], b[k]) for k in a.keys(True, True))


def td_max_abs_diff(a: TensorDictBase, b: TensorDictBase) -> float:
    return max(float((a[k] - b[k]).abs().max()) for k in a.keys(True, True))


def all_finite(logs: dict[str, float]) -> bool:
    return all(math.isfinite(v) for v in logs.values())


def test_networks_respect_action_box(env, obs_dim):
    box = action_bounds(env.action_spec)
    assert box.shape == (2,)
    actor = make_sac_actor(obs_dim, env.action_spec)
    td = actor(env.reset())
    assert td["action"].shape == (8, 2) and {"loc", "scale"} <= set(td.keys())
    assert td["action"].abs().max() <= 1.0
    with pytest.raises(TypeError):
        action_bounds(env.observation_spec["observation"])


@pytest.mark.parametrize("scale, speed", [(1.0, 5.0), (2.0, 10.0)])
def test_action_scale_puts_full_speed_inside_tanhs_range_by_hand(env, obs_dim, scale, speed):
    """algo.action_scale widens the actor's box about its centre: the mean action for
    loc = (atanh 0.5, 0) is (0.5, 0) in the env's box [-1, 1]^2, 5 m/s east, and (1, 0) in a box
    twice as wide, 10 m/s = v_max. The entropy target auto stays -2: the wider box's actions are
    in the env's units. The exported actor acts in the same box."""
    from uavlae.envs.physics import action_to_velocity
    from uavlae.export import NoisyActor, actor_box

    sac = make_sac({"action_scale": scale}, obs_dim, env.action_spec)
    assert sac.actor.spec["action"].space.high.tolist() == [scale, scale]
    assert float(sac.loss.target_entropy) == -2.0
    assert actor_box(sac, env.action_spec).space.low.tolist() == [-scale, -scale]
    last = [m for m in sac.actor.modules() if isinstance(m, torch.nn.Linear)][-1]
    with torch.no_grad():
        last.weight.zero_()
        last.bias.copy_(torch.tensor([math.atanh(0.5), 0.0, 0.0, 0.0]))
    mean = NoisyActor(sac, env.action_spec)(torch.zeros(1, obs_dim), torch.zeros(1, 2))
    assert mean.tolist()[0] == pytest.approx([0.5 * scale, 0.0], abs=1e-6)
    assert action_to_velocity(mean, 10.0).tolist()[0] == pytest.approx([speed, 0.0], abs=1e-5)


def test_action_scale_below_one_is_refused():
    with pytest.raises(ValueError, match="action_scale"):
        make_sac_config({"action_scale": 0.5})


def test_sac_update(env, obs_dim, replay_batch):
    sac = make_sac({}, obs_dim, env.action_spec)
    loss = sac.loss
    actor_before = params(sac.actor)
    q_before = loss.qvalue_network_params.data.clone()
    target_before = loss.target_qvalue_network_params.data.clone()
    alpha_before = sac.alpha
    logs = sac.update(replay_batch.clone())
    assert all_finite(logs) and {"loss_actor", "loss_qvalue", "loss_alpha", "alpha", "entropy"} <= set(logs)
    assert changed(actor_before, sac.actor)  # the acting actor shares the loss parameters
    assert not td_equal(loss.qvalue_network_params.data, q_before)
    # SoftUpdate: target <- (1 - tau) * target + tau * source, once per update
    tau = sac.cfg.tau
    expected = target_before.apply(lambda t, s: (1 - tau) * t + tau * s, loss.qvalue_network_params.data)
    assert td_max_abs_diff(loss.target_qvalue_network_params.data, expected) < 1e-6
    assert not td_equal(loss.target_qvalue_network_params.data, target_before)
    sac.update(replay_batch.clone())
    assert sac.alpha != alpha_before  # automatic entropy tuning moves alpha


def test_sac_layer_norm_networks(env, obs_dim, replay_batch):
    """layer_norm: a LayerNorm after each hidden linear layer, before the ReLU, in the actor and
    both Q nets; at initialisation (weight 1, bias 0) each row of a hidden layer leaves it with
    mean 0 and (biased) variance 1."""
    sac = make_sac({"layer_norm": True, "loss_impl": "torchrl", "hidden": (32, 16)}, obs_dim, env.action_spec)
    mlp = sac.actor.module[0].module[0]
    kinds = [type(m).__name__ for m in mlp]
    assert kinds == ["Linear", "LayerNorm", "ReLU", "Linear", "LayerNorm", "ReLU", "Linear"]
    assert [m.normalized_shape for m in mlp if isinstance(m, torch.nn.LayerNorm)] == [(32,), (16,)]
    q_kinds = [type(m).__name__ for m in sac.loss.qvalue_network.module]
    assert q_kinds == kinds
    h = mlp[1](mlp[0](replay_batch["observation"]))
    assert torch.allclose(h.mean(-1), torch.zeros(128), atol=1e-5)
    assert torch.allclose(h.var(-1, unbiased=False), torch.ones(128), atol=1e-3)
    actor_before, q_before = params(sac.actor), sac.loss.qvalue_network_params.data.clone()
    assert all_finite(sac.update(replay_batch.clone()))
    assert changed(actor_before, sac.actor) and not td_equal(sac.loss.qvalue_network_params.data, q_before)


def test_crossq_update_and_policy_delay(env, obs_dim, replay_batch):
    """Every update steps the Q nets; the actor and log(alpha) move on every policy_delay-th
    (here the 3rd) only. No target nets. Adam's betas are CrossQ's (0.5, 0.999) on the actor and
    Q nets."""
    torch.manual_seed(0)
    algo = make_crossq({}, obs_dim, env.action_spec)
    loss = algo.loss
    assert not any(k.startswith("target_") for k in loss.state_dict())
    assert algo.optimisers["critic"].param_groups[0]["betas"] == (0.5, 0.999)
    assert algo.optimisers["actor"].param_groups[0]["betas"] == (0.5, 0.999)
    assert algo.optimisers["alpha"].param_groups[0]["betas"] == (0.9, 0.999)
    actor_before = params(algo.actor)
    for step in (1, 2, 3):
        q_before = loss.qvalue_network_params.data.clone()
        logs = algo.update(replay_batch.clone())
        assert all_finite(logs) and logs["num_updates"] == step and logs["actor_step"] == float(step == 3)
        assert not td_equal(loss.qvalue_network_params.data, q_before)
        assert changed(actor_before, algo.actor) == (step == 3)
        assert (algo.alpha != 1.0) == (step == 3)
    assert {"loss_qvalue", "loss_actor", "loss_alpha", "alpha", "entropy", "td_error"} <= set(logs)
    assert logs["loss_actor"] == algo.update(replay_batch.clone())["loss_actor"]  # held until the next actor step


def test_crossq_batch_renorm_statistics_hand_computed(env, obs_dim, replay_batch):
    """One Q step's forward runs s and s' together through each Q net's first batch
    renormalisation, whose input is [observation, action]: its running mean starts at 0 and
    moves by momentum 0.01 toward the mean of the 2N rows; its running variance starts at 1 and
    moves toward their unbiased variance. On the observation columns this is a number of the
    batch alone (the next actions are the actor's draws)."""
    torch.manual_seed(0)
    algo = make_crossq({}, obs_dim, env.action_spec)
    algo.update(replay_batch.clone())
    rows = torch.cat([replay_batch["observation"], replay_batch["next", "observation"]])  # [256, obs_dim]
    first = algo.loss.qvalue_network_params["module", "0"]
    for k in range(2):  # both Q nets see the same rows
        assert torch.allclose(first["running_mean"][k, :obs_dim], 0.01 * rows.mean(0), atol=1e-6)
        assert torch.allclose(first["running_var"][k, :obs_dim], 0.99 + 0.01 * rows.var(0, unbiased=True), atol=1e-6)
        assert int(first["num_batches_tracked"][k]) == 1
    state = algo.state_dict()["loss"]
    assert torch.equal(state["qvalue_network_params.module.0.running_mean"], first["running_mean"])


def test_batch_renorm_counter_stops_at_the_warm_up():
    """torchrl's BatchRenorm1d counts past ``warmup_steps`` (an out-of-place clamp whose result is
    dropped), so its r and d corrections grow past their clamps; CappedBatchRenorm1d holds the
    count. When the first assertion fails torchrl has fixed it, and CappedBatchRenorm1d can go."""
    from torchrl.modules import BatchRenorm1d

    x = torch.randn(16, 3, generator=torch.Generator().manual_seed(0))
    theirs, ours = BatchRenorm1d(3, warmup_steps=2), CappedBatchRenorm1d(3, warmup_steps=2)
    for _ in range(5):
        theirs(x), ours(x)
    assert int(theirs.num_batches_tracked) == 5
    assert int(ours.num_batches_tracked) == 2
    ours.eval()
    ours(x)
    assert int(ours.num_batches_tracked) == 2  # eval mode neither counts nor moves the statistics


def test_crossq_acting_ignores_modes_and_batch(env, obs_dim, replay_batch):
    """The actor is a plain MLP: a row's deterministic action is the same alone or in a batch,
    whatever the train/eval mode of the actor or of the Q nets (whose batch statistics never act)."""
    torch.manual_seed(0)
    algo = make_crossq({"policy_delay": 1}, obs_dim, env.action_spec)
    algo.update(replay_batch.clone())
    obs = TensorDict({"observation": replay_batch["observation"][:8]}, [8])
    outs = []
    for mode in (True, False):
        algo.loss.train(mode)
        algo.actor.train(mode)
        with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
            outs.append(algo.actor(obs.clone())["action"])
            outs.append(torch.cat([algo.actor(obs[i : i + 1].clone())["action"] for i in range(8)]))
    for o in outs[1:]:
        assert torch.allclose(o, outs[0], atol=1e-6)


def _sac_after(updates: int, obs_dim: int, spec, batch: TensorDictBase, **cfg) -> dict:
    torch.manual_seed(0)
    sac = make_sac(cfg, obs_dim, spec)
    for i in range(updates):
        torch.manual_seed(100 + i)  # the same actor noise each step, whatever each path draws
        sac.update(batch.clone())
    return sac.state_dict()


def test_sac_compiled_update_matches_eager(env, obs_dim, replay_batch):
    """``compile: true`` (of torchrl's SACLoss) is the same SAC: same parameters, targets and optimiser moments after
    a few updates from the same seed, up to float rounding. Inductor must draw the actor noise
    with torch's own generator (``fallback_random``) for the two paths to see the same samples."""
    import torch._inductor.config as inductor_config

    eager = _sac_after(5, obs_dim, env.action_spec, replay_batch, loss_impl="torchrl")
    with inductor_config.patch(fallback_random=True):
        compiled = _sac_after(5, obs_dim, env.action_spec, replay_batch, loss_impl="torchrl", compile=True)
    for key, value in eager["loss"].items():
        if value.is_floating_point():
            assert torch.allclose(value, compiled["loss"][key], rtol=1e-4, atol=1e-6), key
    moments_e, moments_c = eager["optimisers"]["sac"]["state"], compiled["optimisers"]["sac"]["state"]
    for i in moments_e:
        assert torch.allclose(moments_e[i]["exp_avg"], moments_c[i]["exp_avg"], rtol=1e-4, atol=1e-7), i


def test_sac_loads_three_optimiser_checkpoints(env, obs_dim, replay_batch):
    """Checkpoints written before the three Adams became one grouped Adam still resume."""
    torch.manual_seed(0)
    a = make_sac({}, obs_dim, env.action_spec)
    a.update(replay_batch.clone())
    state = copy.deepcopy(a.state_dict())
    merged, old, offset = state["optimisers"]["sac"], {}, 0
    for group in merged["param_groups"]:  # split the grouped Adam back into the old layout
        idx = group["params"]
        old[group["name"]] = {
            "state": {i - offset: merged["state"][i] for i in idx if i in merged["state"]},
            "param_groups": [{**{k: v for k, v in group.items() if k != "name"}, "params": [i - offset for i in idx]}],
        }
        offset += len(idx)
    torch.manual_seed(123)
    b = make_sac({}, obs_dim, env.action_spec)
    b.load_state_dict({**state, "optimisers": old})
    _assert_same(a.state_dict(), b.state_dict())


def test_sac_clips_each_group(env, obs_dim, replay_batch):
    sac = make_sac({"max_grad_norm": 1e-3}, obs_dim, env.action_spec)
    logs = sac.update(replay_batch.clone())
    assert {"grad_norm_actor", "grad_norm_critic", "grad_norm_alpha"} <= set(logs)


def test_ddpg_update_and_exploration(env, obs_dim, replay_batch):
    ddpg = make_ddpg({}, obs_dim, env.action_spec)
    actor_before, critic_before = params(ddpg.actor), ddpg.loss.value_network_params.data.clone()
    target_before = ddpg.loss.target_value_network_params.data.clone()
    logs = ddpg.update(replay_batch.clone())
    assert all_finite(logs) and {"loss_actor", "loss_value"} <= set(logs)
    assert changed(actor_before, ddpg.actor)
    assert not td_equal(ddpg.loss.value_network_params.data, critic_before)
    assert not td_equal(ddpg.loss.target_value_network_params.data, target_before)
    # noise only while exploring; annealing lowers sigma towards sigma_end
    td = env.reset()
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        a_det = ddpg.exploration_policy(td.clone())["action"]
        assert torch.equal(a_det, ddpg.actor(td.clone())["action"])
    with set_exploration_type(ExplorationType.RANDOM):
        a_rnd = ddpg.exploration_policy(td.clone())["action"]
    assert not torch.equal(a_det, a_rnd) and a_rnd.abs().max() <= 1.0
    sigma0 = float(ddpg.noise.sigma)
    ddpg.noise.step(1000)
    assert float(ddpg.noise.sigma) < sigma0


def test_ddpg_ou_noise(env, obs_dim, replay_batch):
    ddpg = make_ddpg({"noise": {"kind": "ou", "sigma_init": 0.2, "sigma_end": 0.1}}, obs_dim, env.action_spec)
    td = env.reset()
    td["is_init"] = torch.ones(8, 1, dtype=torch.bool)  # what torchrl's InitTracker writes
    with set_exploration_type(ExplorationType.RANDOM):
        a = ddpg.exploration_policy(td)["action"]
    assert a.shape == (8, 2) and a.abs().max() <= 1.0
    ddpg.noise.step(10_000)
    assert all_finite(ddpg.update(replay_batch.clone()))


def test_ppo_update(env, obs_dim):
    ppo = make_ppo({"epochs": 2, "minibatch_size": 32}, obs_dim, env.action_spec)
    batch = on_policy_batch(env, ppo.actor)
    assert batch.shape == (8, 16) and "action_log_prob" in batch.keys()
    actor_before, critic_before = params(ppo.actor), params(ppo.critic)
    logs = ppo.update(batch)
    assert all_finite(logs) and {"loss_objective", "loss_critic", "clip_fraction"} <= set(logs)
    assert changed(actor_before, ppo.actor) and changed(critic_before, ppo.critic)
    with pytest.raises(KeyError, match="action_log_prob"):
        ppo.update(batch.exclude("action_log_prob"))


def test_ppo_lagrangian_update(env, obs_dim):
    algo = make_ppo_lagrangian({"epochs": 2, "minibatch_size": 32, "lagrange": {"lr": 0.1}}, obs_dim, env.action_spec)
    batch = on_policy_batch(env, algo.actor)
    before = [params(m) for m in (algo.actor, algo.critic, algo.cost_critic)]
    logs = algo.update(batch)
    assert all_finite(logs)
    assert {"lambda", "cost_limit", "cost_mean_step", "cost_rate", "loss_cost_critic", "kl", "epochs_run"} <= set(logs)
    assert all(changed(b, m) for b, m in zip(before, (algo.actor, algo.critic, algo.cost_critic)))
    # the multiplier took one dual-ascent step on the episodes that ended in the batch (if any)
    if logs["episodes_measured"] > 0:
        assert logs["lambda"] == pytest.approx(max(0.0, 0.1 * (logs["episode_cost"] - 0.05)))
    else:
        assert logs["lambda"] == 0.0 and "episode_cost" not in logs
    lam = logs["lambda"]
    logs = algo.update(batch, episode_cost=0.55)
    assert logs["episode_cost"] == 0.55 and logs["episode_cost_given"] == 1.0
    assert logs["lambda"] == pytest.approx(max(0.0, lam + 0.1 * 0.5))
    with pytest.raises(KeyError, match="cost"):
        algo.update(batch.exclude(("next", "cost")))


def _hand_batch(obs_dim: int, cost: list[list[float]], done: list[list[bool]], actor) -> TensorDict:
    """A ``[2, 4]`` on-policy batch with given costs and episode ends; zero reward."""
    g = torch.Generator().manual_seed(3)
    b, t = 2, 4
    td = TensorDict(
        {
            "observation": torch.randn(b, t, obs_dim, generator=g),
            "next": {
                "observation": torch.randn(b, t, obs_dim, generator=g),
                "reward": torch.zeros(b, t, 1),
                "cost": torch.tensor(cost, dtype=torch.float32).unsqueeze(-1),
                "done": torch.tensor(done).unsqueeze(-1),
                "terminated": torch.tensor(done).unsqueeze(-1),
            },
        },
        [b, t],
    )
    with torch.no_grad(), set_exploration_type(ExplorationType.RANDOM):
        td.update(actor(td.select("observation").copy()).select("action", "action_log_prob"))
    return td


def test_cpo_multiplier_on_discounted_episode_cost(obs_dim):
    """J_c = mean over the episodes ended in the batch of sum_t gamma_c^t c_t; one dual step.

    gamma_c = 0.5, lr = 0.1, d = 0.05. Batch 1: row 0 costs 1 at t = 1 and ends there
    (0.5^1 = 0.5); row 1 costs 1 at t = 3 and ends there (0.5^3 = 0.125): J_c = 0.3125,
    lambda = 0.1 * (0.3125 - 0.05) = 0.02625. Batch 2: row 0's episode began at t = 2 of
    batch 1, so its cost 1 at t = 0 here is its third step (0.5^2 = 0.25) and it ends; row 1
    does not end: J_c = 0.25, lambda = 0.02625 + 0.1 * 0.2 = 0.04625. Batch 3: nothing ends, no
    step. Batch 4: row 1's episode, open for 8 steps without cost, ends with cost 1 at its 9th
    (0.5^8); row 0 ends a zero-cost episode: J_c = 0.5^8 / 2, lambda = max(0, 0.04625 + 0.1 *
    (0.001953125 - 0.05)).
    """
    spec = Bounded(-torch.ones(2), torch.ones(2), shape=(2,))
    algo = make_ppo_lagrangian(
        {"epochs": 1, "minibatch_size": 8, "cost_gamma": 0.5, "lagrange": {"lr": 0.1}, "target_kl": None}, obs_dim, spec
    )
    f, T = False, True
    b1 = _hand_batch(obs_dim, [[0, 1, 0, 0], [0, 0, 0, 1]], [[f, T, f, f], [f, f, f, T]], algo.actor)
    logs = algo.update(b1)
    assert logs["episodes_measured"] == 2 and logs["episode_cost"] == pytest.approx(0.3125)
    assert logs["lambda"] == pytest.approx(0.02625)
    b2 = _hand_batch(obs_dim, [[1, 0, 0, 0], [0, 0, 0, 0]], [[T, f, f, f], [f, f, f, f]], algo.actor)
    logs = algo.update(b2)
    assert logs["episodes_measured"] == 1 and logs["episode_cost"] == pytest.approx(0.25)
    assert logs["lambda"] == pytest.approx(0.04625)
    b3 = _hand_batch(obs_dim, [[0, 0, 0, 0], [0, 0, 0, 0]], [[f, f, f, f], [f, f, f, f]], algo.actor)
    logs = algo.update(b3)
    assert logs["episodes_measured"] == 0 and logs["lambda"] == pytest.approx(0.04625)
    # resume mid-episode: the open episodes' running costs travel in the state dict
    state = copy.deepcopy(algo.state_dict())
    other = make_ppo_lagrangian(
        {"epochs": 1, "minibatch_size": 8, "cost_gamma": 0.5, "lagrange": {"lr": 0.1}, "target_kl": None}, obs_dim, spec
    )
    other.load_state_dict(state)
    b4 = _hand_batch(obs_dim, [[0, 0, 0, 0], [1, 0, 0, 0]], [[T, f, f, f], [T, f, f, f]], algo.actor)
    expected = max(0.0, 0.04625 + 0.1 * (0.5**8 / 2 - 0.05))
    for learner in (algo, other):
        logs = learner.update(b4.clone())
        assert logs["episode_cost"] == pytest.approx(0.5**8 / 2) and logs["lambda"] == pytest.approx(expected)


def test_gaussian_kl_hand_computed():
    # KL(N(0,1) || N(1,2)) = ln 2 + (1 + 1) / (2 * 4) - 1/2 = 0.693147 + 0.25 - 0.5 per dimension
    kl = gaussian_kl(torch.zeros(3, 2), torch.ones(3, 2), torch.ones(3, 2), 2 * torch.ones(3, 2))
    assert torch.allclose(kl, torch.full((3,), 2 * (math.log(2) - 0.25)))
    assert float(gaussian_kl(torch.ones(2), torch.ones(2), torch.ones(2), torch.ones(2))) == 0.0


def test_cpo_kl_early_stop(obs_dim):
    """The update stops before the minibatch step that would start from a mean KL above
    target_kl; without a target it runs every epoch.

    Batch of 8 steps, minibatches of 2: 4 steps an epoch, 5 epochs = 20 steps at most. Before
    the first step the KL is 0, so one step is always taken.
    """
    spec = Bounded(-torch.ones(2), torch.ones(2), shape=(2,))
    base = {"epochs": 5, "minibatch_size": 2, "actor_lr": 1e-2, "lagrange": {"lr": 0.1}}
    f = False
    runs = {}
    for target in (None, 1e-9, 1e3):
        torch.manual_seed(0)
        algo = make_ppo_lagrangian({**base, "target_kl": target}, obs_dim, spec)
        batch = _hand_batch(obs_dim, [[0, 0, 0, 0], [0, 0, 0, 0]], [[f] * 4, [f] * 4], algo.actor)
        batch["next", "reward"] = torch.arange(8.0).reshape(2, 4, 1)  # a non-zero advantage
        flat_obs = batch.select("observation").reshape(-1)
        with torch.no_grad():
            old = algo.actor.get_dist(flat_obs.copy())
            old_loc, old_scale = old.loc.clone(), old.scale.clone()
        logs = algo.update(batch)
        # the logged KL is the mean KL of the final policy, computed here from its parameters
        with torch.no_grad():
            new = algo.actor.get_dist(flat_obs.copy())
            kl = float(gaussian_kl(old_loc, old_scale, new.loc, new.scale).mean())
        assert logs["kl"] == pytest.approx(kl, rel=1e-6)
        runs[target] = logs
    assert runs[None]["gradient_steps"] == 20 and runs[None]["epochs_run"] == 5 and runs[None]["kl_stopped"] == 0
    assert runs[1e3]["gradient_steps"] == 20 and runs[1e3]["kl_stopped"] == 0
    # any step moves the policy above 1e-9: the second step is refused, the epochs end
    assert runs[1e-9]["gradient_steps"] == 1 and runs[1e-9]["epochs_run"] == 0.25 and runs[1e-9]["kl_stopped"] == 1
    assert runs[1e-9]["kl"] > 1e-9
    # the config's default is the paper's 0.01
    assert make_cpo_config().target_kl == 0.01


def test_lagrangian_advantage_form(env, obs_dim):
    """A_L = (std(A_r) - lambda * centred(A_c)) / (1 + lambda), lambda after this update's step."""
    algo = make_ppo_lagrangian({"epochs": 1, "lagrange": {"init": 2.0, "lr": 1e-9}}, obs_dim, env.action_spec)
    batch = on_policy_batch(env, algo.actor)
    seen = {}
    step = algo._step

    def spy(mb):
        seen.setdefault("mb", mb)
        return step(mb)

    algo._step = spy
    with torch.no_grad():
        ref = algo.cost_gae(algo.gae(batch.copy())).reshape(-1)
    algo.update(batch)
    lam = algo.lagrange.value
    ar, ac = ref["advantage"], ref["cost_advantage"]
    expected = ((ar - ar.mean()) / ar.std() - lam * (ac - ac.mean())) / (1 + lam)
    mb = seen["mb"]
    # minibatch rows are a permutation of the batch: match them by observation
    idx = [int((ref["observation"] == o).all(-1).nonzero()[0]) for o in mb["observation"][:16]]
    assert torch.allclose(mb["lagrangian_advantage"][:16], expected[idx], atol=1e-5)


# ---------------------------------------------------------------- checkpoints
def _assert_same(a, b, path="state"):
    if isinstance(a, dict):
        assert set(a) == set(b), path
        for k in a:
            _assert_same(a[k], b[k], f"{path}.{k}")
    elif isinstance(a, (list, tuple)):
        assert len(a) == len(b), path
        for i, (x, y) in enumerate(zip(a, b)):
            _assert_same(x, y, f"{path}[{i}]")
    elif isinstance(a, torch.Tensor):
        assert torch.equal(a, b), path
    else:
        assert a == b, path


def _learners(obs_dim, spec):
    return {
        "sac": lambda: make_sac({}, obs_dim, spec),
        # a multiplier above 0 and a measurement window left open at the checkpoint
        "sac_lag": lambda: make_sac_lag({"lagrange_every": 2, "lagrange": {"init": 0.5}}, obs_dim, spec),
        "ddpg": lambda: make_ddpg({}, obs_dim, spec),
        "ppo": lambda: make_ppo({"epochs": 1, "minibatch_size": 64}, obs_dim, spec),
        "cpo": lambda: make_ppo_lagrangian({"epochs": 1, "minibatch_size": 64, "lagrange": {"method": "pid"}}, obs_dim, spec),
        "sac_ln": lambda: make_sac({"layer_norm": True, "loss_impl": "torchrl", "hidden": (256, 256)}, obs_dim, spec),
        # policy_delay 2: the continuation below is an actor step, so the delay's phase is restored too
        "crossq": lambda: make_crossq({"policy_delay": 2}, obs_dim, spec),
    }


@pytest.mark.parametrize("name", ["sac", "sac_lag", "ddpg", "ppo", "cpo", "sac_ln", "crossq"])
def test_state_dict_round_trip(name, env, obs_dim, replay_batch):
    make = _learners(obs_dim, env.action_spec)[name]
    torch.manual_seed(0)
    a = make()
    batch = on_policy_batch(env, a.actor) if name in ("ppo", "cpo") else replay_batch
    if name == "ddpg":
        a.noise.step(500)
    a.update(batch.clone())
    state = copy.deepcopy(a.state_dict())
    torch.manual_seed(123)  # different initial weights
    b = make()
    b.load_state_dict(state)
    _assert_same(a.state_dict(), b.state_dict())
    for pa, pb in zip(a.actor.parameters(), b.actor.parameters()):  # the acting policy too
        assert torch.equal(pa, pb)
    # identical continuation: optimiser moments, targets, alpha and lambda all restored
    torch.manual_seed(7)
    la = a.update(batch.clone())
    torch.manual_seed(7)
    lb = b.update(batch.clone())
    assert la == lb
    _assert_same(a.state_dict(), b.state_dict())


# ---------------------------------------------------------------- learning sanity
def test_sac_learns_a_one_step_bandit():
    """Reward -|a - 0.6 * s[:2]|^2 on a 1-step task: SAC beats a uniform-random policy."""
    torch.manual_seed(0)
    spec = Bounded(-1.0, 1.0, shape=(2,))
    cfg = {"actor_lr": 3e-3, "critic_lr": 3e-3, "alpha_lr": 3e-3, "alpha_init": 0.1}
    sac = make_sac(cfg, 3, spec)

    def reward(obs, act):
        return -(act - 0.6 * obs[:, :2]).pow(2).sum(-1, keepdim=True)

    def batch(n=128):
        obs, act = torch.rand(n, 3) * 2 - 1, torch.rand(n, 2) * 2 - 1
        one = torch.ones(n, 1, dtype=torch.bool)
        nxt = {"observation": torch.rand(n, 3) * 2 - 1, "reward": reward(obs, act), "done": one, "terminated": one}
        return TensorDict({"observation": obs, "action": act, "next": nxt}, [n])

    test_obs = torch.rand(1024, 3) * 2 - 1
    random_return = reward(test_obs, torch.rand(1024, 2) * 2 - 1).mean().item()
    for _ in range(300):  # ~200 already reach about -0.003
        sac.update(batch())
    with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
        act = sac.actor(TensorDict({"observation": test_obs}, [1024]))["action"]
    learned = reward(test_obs, act).mean().item()
    assert random_return < -0.7  # E|U - 0.6 s|^2 = 2 * (1/3 + 0.12)
    assert learned > -0.1, (learned, random_return)
