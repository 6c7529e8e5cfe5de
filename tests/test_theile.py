"""The ``theile`` baseline: the DCU-centred maps by hand, the D4 action on maps and vectors, the
ensemble's equivariance (by hand for a quarter turn and a reflection), the regulariser, and
``+exp=theile`` training, resuming from a checkpoint and being evaluated."""

from __future__ import annotations

import copy
import json
import math
from pathlib import Path

import pytest
import torch
from torchrl.envs.utils import ExplorationType, set_exploration_type

from uavlae.algos import make_learner
from uavlae.algos.theile import make_theile, make_theile_config
from uavlae.envs import UAVEnv, make_env_config
from uavlae.envs.maps import MAP_CHANNELS, dcu_maps
from uavlae.envs.scenario import Scenario
from uavlae.envs.world import ObservationLayout
from uavlae.policies.d4 import D4Ensemble, matrix, member_spread, transform_map

CH = {c: i for i, c in enumerate(MAP_CHANNELS)}
# 4 x 4 cells of 10 m (40 m around the DCU) and 4 x 4 of 250 m (1000 m): small enough to write out
HAND_MAPS = {"enabled": True, "local_size": 4, "local_cell": 10.0, "global_size": 4, "global_cell": 250.0}


def _hand_env() -> UAVEnv:
    # DCU at (100, 100); one building over [110, 130] x [100, 115]; a GE with 2 of data_max 3 at
    # (85, 115); an OU 9.4 m away at (95, 92) and one 40 m away at (60, 100), beyond the 20 m perception radius
    scen = Scenario(bz=[(110.0, 100.0, 130.0, 115.0)], ge_pos=[(85.0, 115.0)], ge_data=[2.0],
                    ou_pos=[(95.0, 92.0), (60.0, 100.0)], ou_vel=[(0.0, 0.0), (0.0, 0.0)], start=(100.0, 100.0))
    cfg = {"maps": HAND_MAPS, "ge": {"count": {"min": 1, "max": 1}}, "ou": {"count": {"min": 2, "max": 2}},
           "zones": {"n_nfz": {"min": 0, "max": 1}, "n_rz": {"min": 0, "max": 1}, "n_bz": {"min": 1, "max": 1}}}
    return UAVEnv(cfg, batch_size=[1], seed=0, scenarios=[scen])


def test_maps_of_one_building_by_hand():
    env = _hand_env()
    td = env.reset()
    local, glob = dcu_maps(dict(td["state"].items()), env.cfg)
    assert local.shape == (1, len(MAP_CHANNELS), 4, 4) and glob.shape == (1, len(MAP_CHANNELS), 4, 4)
    # local cells [80, 90], [90, 100], [100, 110], [110, 120] on both axes (row = y, column = x):
    # the building fills column 3 on x, row 2 on y and half of row 3 (y in [110, 115])
    bz = torch.zeros(4, 4)
    bz[2, 3], bz[3, 3] = 1.0, 0.5
    torch.testing.assert_close(local[0, CH["bz"]], bz)
    assert local[0, CH["area"]].eq(1).all() and local[0, CH["nfz"]].eq(0).all() and local[0, CH["landing"]].eq(0).all()
    ge = torch.zeros(4, 4)
    ge[3, 0] = 2.0 / 3.0  # (85, 115): column floor(-1.5 + 2) = 0, row floor(1.5 + 2) = 3
    torch.testing.assert_close(local[0, CH["ge_data"]], ge)
    ou = torch.zeros(4, 4)
    ou[1, 1] = 1.0  # (95, 92): column floor(-0.5 + 2) = 1, row floor(-0.8 + 2) = 1; the far OU is not seen
    torch.testing.assert_close(local[0, CH["ou"]], ou)
    # global cells [-400, -150], [-150, 100], [100, 350], [350, 600]: the area [0, 500] covers
    # 0, 0.4, 1, 0.6 of them on each axis
    cover = torch.tensor([0.0, 0.4, 1.0, 0.6])
    torch.testing.assert_close(glob[0, CH["area"]], cover.unsqueeze(-1) * cover)
    g_bz = torch.zeros(4, 4)
    g_bz[2, 2] = (20 / 250) * (15 / 250)
    torch.testing.assert_close(glob[0, CH["bz"]], g_bz)
    g_la = torch.zeros(4, 4)
    g_la[1, 3] = (25 / 250) * (25 / 250)  # LA [475, 500] x [0, 25]
    torch.testing.assert_close(glob[0, CH["landing"]], g_la)
    g_ou = torch.zeros(4, 4)
    g_ou[1, 1] = 1.0  # the far OU would be at [2, 1]
    torch.testing.assert_close(glob[0, CH["ou"]], g_ou)
    # the observation: the flat one (unchanged), then the two maps flattened
    obs = td["observation"][0]
    n = env.layout.flat_size
    assert obs.shape[0] == n + 2 * len(MAP_CHANNELS) * 16
    torch.testing.assert_close(obs[n : n + 16 * len(MAP_CHANNELS)], local[0].flatten())
    torch.testing.assert_close(obs[n + 16 * len(MAP_CHANNELS) :], glob[0].flatten())


def test_maps_are_off_by_default_and_leave_the_flat_observation_alone():
    plain = UAVEnv(batch_size=[3], seed=5)
    assert not plain.cfg.maps.enabled and plain.layout.size == plain.layout.flat_size == 175
    with_maps = UAVEnv({"maps": {"enabled": True}}, batch_size=[3], seed=5)
    a, b = plain.reset(), with_maps.reset()
    assert torch.equal(b["observation"][:, :175], a["observation"])
    assert with_maps.layout.size == 175 + len(MAP_CHANNELS) * (32 * 32 + 16 * 16)
    with pytest.raises(ValueError, match="maps.local_size"):
        make_env_config({"maps": {"local_size": 31}})


def test_rotating_the_world_about_the_dcu_rotates_the_maps():
    # a sampled world, the DCU put at the centre of the square area, then the whole world turned a
    # quarter turn counter-clockwise about it: every map channel turns with it
    env = UAVEnv({"maps": {"enabled": True}}, batch_size=[4], seed=3)
    s = dict(env.reset()["state"].items())
    c = torch.tensor([250.0, 250.0])
    s["position"] = c.expand(4, 2).clone()

    def turn(p):  # (x, y) -> (-y, x) about c
        d = p - c
        return torch.stack([-d[..., 1], d[..., 0]], -1) + c

    def turn_rect(r):
        a, b = turn(r[..., :2]), turn(r[..., 2:])
        return torch.cat([torch.minimum(a, b), torch.maximum(a, b)], -1)

    t = dict(s)
    for k in ("bz", "nfz", "rz", "landing"):
        t[k] = turn_rect(s[k])
    t["ge_pos"], t["ou_pos"] = turn(s["ge_pos"]), turn(s["ou_pos"])
    for a, b in zip(dcu_maps(s, env.cfg), dcu_maps(t, env.cfg)):
        torch.testing.assert_close(b, transform_map(a, 1), atol=1e-5, rtol=0)
        assert a[:, CH["bz"]].sum() > 0  # there is something to turn


# ------------------------------------------------------------------ the ensemble
TINY_MAPS = {"enabled": True, "local_size": 4, "local_cell": 10.0, "global_size": 4, "global_cell": 250.0}
ONE_OU = {"maps": TINY_MAPS, "ou": {"count": {"min": 1, "max": 1}}, "extra_features": False}


def _layout() -> ObservationLayout:
    return ObservationLayout(make_env_config(ONE_OU))


def _obs(layout: ObservationLayout, local: torch.Tensor, glob: torch.Tensor, ou_rel, ou_vel, vel, energy=0.7):
    obs = torch.zeros(layout.size)
    cols = layout.columns()
    obs[cols["ou_rel"]], obs[cols["ou_vel"]], obs[cols["velocity"]] = map(torch.tensor, (ou_rel, ou_vel, vel))
    obs[cols["ou_seen"]] = 1.0
    obs[cols["energy_left"]] = energy
    obs[layout.flat_size :] = torch.cat([local.flatten(), glob.flatten()])
    return obs.unsqueeze(0)


def _scene(layout):
    """A hand-built input and its images under the quarter turn and the reflection y -> -y, each
    written out cell by cell (not through transform_map)."""
    c = len(MAP_CHANNELS)
    local, glob = torch.zeros(c, 4, 4), torch.zeros(c, 4, 4)
    local[CH["bz"], 1, 3] = 1.0  # a building cell east, a little south: centre (+15, -5) m
    local[CH["ge_data"], 3, 2] = 0.5  # a GE north-east: (+5, +15)
    glob[CH["area"]] = torch.tensor([0.0, 0.4, 1.0, 0.6]).unsqueeze(-1) * torch.tensor([0.0, 0.4, 1.0, 0.6])
    base = _obs(layout, local, glob, ou_rel=(0.3, -0.2), ou_vel=(0.1, 0.4), vel=(0.2, -0.1))
    # quarter turn (x, y) -> (-y, x): (+15, -5) -> (+5, +15) = cell [3, 2]; (+5, +15) -> (-15, +5) = [2, 0]
    t_local, t_glob = torch.zeros_like(local), torch.zeros_like(glob)
    t_local[CH["bz"], 3, 2] = 1.0
    t_local[CH["ge_data"], 2, 0] = 0.5
    t_glob[CH["area"]] = torch.tensor([0.0, 0.4, 1.0, 0.6]).unsqueeze(-1) * torch.tensor([0.6, 1.0, 0.4, 0.0])
    turned = _obs(layout, t_local, t_glob, ou_rel=(0.2, 0.3), ou_vel=(-0.4, 0.1), vel=(0.1, 0.2))
    # reflection (x, y) -> (x, -y): (+15, -5) -> (+15, +5) = [2, 3]; (+5, +15) -> (+5, -15) = [0, 2]
    f_local, f_glob = torch.zeros_like(local), torch.zeros_like(glob)
    f_local[CH["bz"], 2, 3] = 1.0
    f_local[CH["ge_data"], 0, 2] = 0.5
    f_glob[CH["area"]] = torch.tensor([0.6, 1.0, 0.4, 0.0]).unsqueeze(-1) * torch.tensor([0.0, 0.4, 1.0, 0.6])
    mirrored = _obs(layout, f_local, f_glob, ou_rel=(0.3, 0.2), ou_vel=(0.1, -0.4), vel=(0.2, 0.1))
    return base, turned, mirrored


def test_group_elements_by_hand():
    assert matrix(1).tolist() == [[0.0, -1.0], [1.0, 0.0]] and matrix(4).tolist() == [[1.0, 0.0], [0.0, -1.0]]
    m = torch.arange(16.0).reshape(4, 4)  # m[i, j] = 4 i + j
    # the quarter turn: out[i, j] = m[3 - j, i]; the reflection: out[i, j] = m[3 - i, j]
    assert transform_map(m, 1).tolist() == [[12.0, 8.0, 4.0, 0.0], [13.0, 9.0, 5.0, 1.0], [14.0, 10.0, 6.0, 2.0],
                                            [15.0, 11.0, 7.0, 3.0]]
    assert transform_map(m, 4).tolist() == m.flip(0).tolist()
    layout = _layout()
    base, turned, mirrored = _scene(layout)
    net = D4Ensemble(layout, "action")
    lb, gb, vb, ib = net.inputs(base)
    lt, gt, vt, it = net.inputs(turned)
    torch.testing.assert_close(transform_map(lb, 1), lt)
    torch.testing.assert_close(transform_map(gb, 1), gt)
    torch.testing.assert_close(vb @ matrix(1).T, vt)
    assert torch.equal(ib, it)


def test_ensemble_action_turns_and_mirrors_with_its_input():
    layout = _layout()
    base, turned, mirrored = _scene(layout)
    torch.manual_seed(0)
    algo = make_theile({"cnn": {"channels": [4, 4], "head_hidden": [16]}}, layout.size,
                       UAVEnv(ONE_OU, batch_size=[1], seed=0).action_spec, layout)
    inputs = {"base": base, "turned": turned, "mirrored": mirrored}
    with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
        act = {k: algo.actor(_td(o))["action"][0] for k, o in inputs.items()}
        value = {k: algo.critic(_td(o))["state_value"][0, 0] for k, o in inputs.items()}
    ax, ay = act["base"].tolist()
    assert abs(ax) > 1e-4 and abs(ay) > 1e-4  # a non-trivial action to turn
    # the quarter turn takes the action (ax, ay) to (-ay, ax); the reflection to (ax, -ay)
    torch.testing.assert_close(act["turned"], torch.tensor([-ay, ax]), atol=1e-6, rtol=1e-5)
    torch.testing.assert_close(act["mirrored"], torch.tensor([ax, -ay]), atol=1e-6, rtol=1e-5)
    torch.testing.assert_close(value["turned"], value["base"], atol=1e-6, rtol=1e-5)
    torch.testing.assert_close(value["mirrored"], value["base"], atol=1e-6, rtol=1e-5)
    with torch.no_grad():  # the per-axis scales swap under the quarter turn
        s_base = algo.actor_net(base)[0, 2:]
        s_turn = algo.actor_net(turned)[0, 2:]
        torch.testing.assert_close(s_turn, s_base.flip(0), atol=1e-6, rtol=1e-5)
        # one member alone is not equivariant: the averaging is what makes it so
        one = algo.actor_net.net(*algo.actor_net.inputs(base))[0, :2]
        one_t = algo.actor_net.net(*algo.actor_net.inputs(turned))[0, :2]
        assert not torch.allclose(one_t, torch.stack([-one[1], one[0]]), atol=1e-4)


def _td(obs):
    from tensordict import TensorDict

    return TensorDict({"observation": obs}, batch_size=obs.shape[:1])


def _linear_on_velocity(layout, w, b) -> D4Ensemble:
    """An ensemble whose member is f(o) = W v + b on the DCU's velocity v alone (every other weight 0)."""
    net = D4Ensemble(layout, "action", channels=(2,), hidden=())
    with torch.no_grad():
        for p in net.parameters():
            p.zero_()
        head = net.net.head[0]
        n_maps = head.in_features - 2 * net.inputs.n_vec - net.inputs.n_inv
        v = n_maps + 2 * 2  # vector pairs: OU rel, OU vel, then the DCU velocity
        head.weight[:2, v : v + 2] = torch.tensor(w)
        head.bias[:2] = torch.tensor(b)
    return net


def test_ensemble_of_a_linear_member_by_hand():
    # (1/8) sum_e R_e^-1 (W R_e v + b) = (tr W / 2) v: the group average of W is its trace part,
    # and the R_e^-1 b average to 0. W = [[1, 2], [3, 4]], v = (0.2, -0.1): 2.5 v = (0.5, -0.25).
    layout = _layout()
    base, _, _ = _scene(layout)
    net = _linear_on_velocity(layout, [[1.0, 2.0], [3.0, 4.0]], [0.5, -0.7])
    with torch.no_grad():
        torch.testing.assert_close(net(base)[0, :2], torch.tensor([0.5, -0.25]))
        members = net.members(base)[:, 0, :2]
        # member e = R_e^-1 (W R_e v + b), e.g. e = 0: W v + b = (0.0 + 0.5, 0.2 - 0.7) = (0.5, -0.5)
        torch.testing.assert_close(members[0], torch.tensor([0.5, -0.5]))
        assert member_spread(members) > 0
        # W = 3 I, b = 0: every member is 3 v, they agree and the regulariser is 0
        agree = _linear_on_velocity(layout, [[3.0, 0.0], [0.0, 3.0]], [0.0, 0.0])
        assert float(member_spread(agree.members(base)[..., :2])) == 0.0


def test_regulariser_by_hand():
    # 8 members, two samples: member e says (e, 0) for sample 0 and (0, 1) for sample 1.
    # Sample 0: mean 3.5, (1/8) sum (e - 3.5)^2 = 5.25; sample 1: all agree, 0. Mean: 2.625.
    m = torch.zeros(8, 2, 2)
    m[:, 0, 0] = torch.arange(8.0)
    m[:, 1, 1] = 1.0
    assert float(member_spread(m)) == pytest.approx(2.625)
    assert float(member_spread(torch.ones(8, 5, 2))) == 0.0
    # the learner's term: weight x the spread of the actor's back-transformed means
    layout = _layout()
    spec = UAVEnv(ONE_OU, batch_size=[1], seed=0).action_spec
    algo = make_theile({"regularizer": {"actor": 0.25, "critic": 0.5}}, layout.size, spec, layout)
    base, turned, _ = _scene(layout)
    mb = _td(torch.cat([base, turned]))
    terms = algo.regularizer(mb)
    with torch.no_grad():
        a = member_spread(algo.actor_net.members(mb["observation"])[..., :2])
        c = member_spread(algo.critic_net.members(mb["observation"]))
    assert float(terms["loss_equivariance_actor"].detach()) == pytest.approx(0.25 * float(a), rel=1e-6)
    assert float(terms["loss_equivariance_critic"].detach()) == pytest.approx(0.5 * float(c), rel=1e-6)
    assert set(make_theile(make_theile_config({"regularizer": {"actor": 0.0}}), layout.size, spec, layout)
               .regularizer(mb)) == set()


def test_update_and_bad_configs():
    env = UAVEnv({"maps": TINY_MAPS}, batch_size=[4], seed=2)
    algo = make_learner({"name": "theile", "epochs": 1, "minibatch_size": 16}, env.layout.size, env.action_spec,
                        layout=env.layout)
    torch.manual_seed(1)
    with torch.no_grad(), set_exploration_type(ExplorationType.RANDOM):
        batch = env.rollout(8, algo.actor, break_when_any_done=False)
    before = [p.detach().clone() for p in algo.actor.parameters()]
    logs = algo.update(batch)
    assert all(math.isfinite(v) for v in logs.values()) and logs["loss_equivariance_actor"] > 0
    assert any(not torch.equal(b, p) for b, p in zip(before, algo.actor.parameters()))
    plain = UAVEnv(batch_size=[1], seed=0)
    with pytest.raises(ValueError, match="env.maps.enabled"):
        make_theile({}, plain.layout.size, plain.action_spec, plain.layout)
    with pytest.raises(ValueError, match="ObservationLayout"):
        make_theile({}, env.layout.size, env.action_spec)
    with pytest.raises(ValueError, match="algo.regularizer.actor"):
        make_theile_config({"regularizer": {"actor": -1.0}})


# ------------------------------------------------------------------ training, resume, evaluation
TRAIN = [
    "trainer.total_frames=256", "trainer.env_batch_size=4", "trainer.frames_per_batch=64",
    "trainer.eval_episodes=2", "trainer.eval_max_steps=10", "trainer.eval_every_frames=128",
    "trainer.checkpoint_every_frames=64", "trainer.keep_checkpoints=2", "trainer.eval_plots=1",
    "trainer.progress_bar=false", "trainer.baselines=false", "logger.wandb.mode=disabled",
    "algo.epochs=1", "algo.minibatch_size=32", "env.maps.local_size=16", "env.maps.global_size=8",
    "env.maps.global_cell=125.0",
]


@pytest.mark.timeout(600)
def test_exp_theile_trains_resumes_and_evaluates(tmp_path):
    from hydra import compose, initialize_config_dir

    from uavlae.checkpoint import LAST, PREV, load_checkpoint
    from uavlae.evaluate import evaluate_checkpoint
    from uavlae.factories import CONF_DIR
    from uavlae.train import run

    def cfg(*o):
        with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
            return compose("config", overrides=list(o))

    straight = run(cfg("+exp=theile", f"run_dir={tmp_path / 'a'}", *TRAIN))
    assert straight["frames"] == 256 and straight["updates"] == 4
    assert 0.0 <= straight["eval/DCR"] <= 1.0
    state, _ = load_checkpoint(tmp_path / "a")
    assert state["config"]["env"]["maps"]["enabled"] and state["config"]["algo"]["name"] == "theile"
    # the same run, cut short after its checkpoint at 192 frames, then resumed from it
    b = tmp_path / "b"
    run(cfg("+exp=theile", f"run_dir={b}", *TRAIN))
    (b / "checkpoints" / LAST).unlink()
    (b / "final_metrics.json").unlink()
    assert load_checkpoint(b / "checkpoints" / PREV)[0]["counters"]["frames"] == 192
    resumed = run(cfg(f"resume={b / 'checkpoints' / PREV}", "trainer.progress_bar=false", "logger.wandb.mode=disabled"))
    assert resumed.pop("wall_s") > 0 and straight.pop("wall_s") > 0
    assert resumed == straight
    # the evaluator rebuilds the map observation from the checkpoint's env config
    agg = evaluate_checkpoint(cfg(f"checkpoint={tmp_path / 'a'}", "trainer.eval_max_steps=10", "trainer.eval_plots=0"))
    final = json.loads((Path(tmp_path / "a") / "final_metrics.json").read_text())
    assert agg["DCR"] == pytest.approx(final["eval/DCR"]) and agg["mean_return"] == pytest.approx(final["eval/mean_return"])
    # and the exported actor is the deterministic ensemble
    from uavlae.export import export_checkpoint
    from uavlae.fly import load_actor

    env = UAVEnv(make_env_config(state["config"]["env"]), batch_size=[3], seed=1)
    learner = make_learner(state["config"]["algo"], env.layout.size, env.action_spec, layout=env.layout)
    learner.load_state_dict(load_checkpoint(tmp_path / "a")[0]["learner"])
    td = env.reset()
    with set_exploration_type(ExplorationType.DETERMINISTIC), torch.no_grad():
        expected = learner.actor(td.clone())["action"]
    exported, _ = load_actor(export_checkpoint(tmp_path / "a", tmp_path / "actor.pt2"))
    torch.testing.assert_close(exported(td["observation"]), expected)


def test_maps_inside_the_compiled_step_match_eager():
    # the maps are built inside the compiled step (one graph, fullgraph): same observation as eager
    b = 4
    cfg = {"maps": {"enabled": True, "local_size": 8, "global_size": 4, "global_cell": 250.0}}
    eager = UAVEnv(cfg, batch_size=[b], seed=3)
    compiled = UAVEnv(cfg, batch_size=[b], seed=3, compile_step=True)
    td_e, td_c = eager.reset(), compiled.reset()
    gen = torch.Generator().manual_seed(0)
    for _ in range(3):
        action = torch.rand(b, 2, generator=gen) * 2 - 1
        td_e["action"], td_c["action"] = action, action.clone()
        out_e, td_e = eager.step_and_maybe_reset(td_e)
        out_c, td_c = compiled.step_and_maybe_reset(td_c)
        torch.testing.assert_close(out_c["next", "observation"], out_e["next", "observation"], rtol=1e-5, atol=1e-4)


def test_regulariser_reuses_the_losss_pass_with_the_same_gradients():
    # PPO's loss runs the actor and the critic on the minibatch; the regulariser takes the members
    # of those passes instead of running the 8 members again: same value, same gradients
    env = UAVEnv({"maps": TINY_MAPS}, batch_size=[4], seed=2)
    algo = make_theile({"regularizer": {"actor": 0.3, "critic": 0.2}}, env.layout.size, env.action_spec, env.layout)
    with torch.no_grad(), set_exploration_type(ExplorationType.RANDOM):
        batch = algo.gae(env.rollout(4, algo.actor, break_when_any_done=False))
    mb = batch.reshape(-1)
    params = [p for m in (algo.actor_net, algo.critic_net) for p in m.parameters()]

    def grads(total):
        g = torch.autograd.grad(total, params, allow_unused=True)
        return [torch.zeros_like(p) if x is None else x for p, x in zip(params, g)]

    algo.loss(mb)
    assert algo.actor_net._kept is not None and algo.actor_net._kept[0] is mb["observation"]
    kept = algo.regularizer(mb)
    assert algo.actor_net._kept is None and algo.critic_net._kept is None
    fresh = algo.regularizer(mb)  # nothing kept now: new passes
    for k in ("loss_equivariance_actor", "loss_equivariance_critic"):
        torch.testing.assert_close(kept[k], fresh[k])
    for a, b in zip(grads(sum(kept.values())), grads(sum(fresh.values()))):
        torch.testing.assert_close(a, b)
    # under no_grad (collection, GAE) nothing is kept
    with torch.no_grad():
        algo.actor(mb.select("observation").clone())
    assert algo.actor_net._kept is None
    # a kept pass does not travel with a copy of the network (the export deep-copies it)
    algo.actor(mb.select("observation").clone())
    assert algo.actor_net._kept is not None and copy.deepcopy(algo.actor_net)._kept is None


def test_yaml_mirrors_the_config():
    import yaml

    from uavlae.algos.theile import TheileConfig
    from uavlae.factories import CONF_DIR

    data = yaml.safe_load((CONF_DIR / "algo" / "theile.yaml").read_text())
    assert set(data) == set(TheileConfig.model_fields)
    assert make_theile_config(data) == TheileConfig()
