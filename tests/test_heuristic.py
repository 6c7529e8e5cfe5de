"""The greedy heuristic (SPEC §8) on hand-made maps and on the default random scenarios."""


import pytest
import torch
import yaml

from uavlae.envs import UAVEnv, make_env_config
from uavlae.envs import physics as ph
from uavlae.envs.metrics import aggregate, rollout_metrics
from uavlae.envs.scenario import Scenario
from uavlae.factories import CONF_DIR
from uavlae.policies.heuristic import HeuristicConfig, HeuristicPolicy, make_heuristic_config

START = (12.5, 487.5)  # centre of TA


def _run(scenarios, batch=None, seed=0, env_cfg=None, policy=None):
    env = UAVEnv(env_cfg, batch_size=[batch or len(scenarios)], seed=seed, scenarios=scenarios)
    policy = policy or HeuristicPolicy(env.cfg)
    records, agg, traj = rollout_metrics(env, policy)
    return env, records, agg, traj


def test_config_yaml_mirrors_model_and_validates():
    path = CONF_DIR / "advisor" / "heuristic.yaml"
    data = yaml.safe_load(path.read_text())
    assert make_heuristic_config(data) == HeuristicConfig()
    with pytest.raises(ValueError, match="heuristic.grid_cell"):
        make_heuristic_config(grid_cell=5.0)
    with pytest.raises(ValueError, match="tight_clearance"):
        make_heuristic_config(tight_clearance=9.0)
    with pytest.raises(ValueError, match="clearance=4.0 must be > env.safety.d_min=5.0"):
        HeuristicPolicy(make_env_config(), {"clearance": 4.0, "tight_clearance": 2.0})


def test_torchrl_rollout_action_shape_and_unbatched_act():
    env = UAVEnv(batch_size=[4], seed=3)
    policy = HeuristicPolicy(env.cfg)
    td = env.rollout(6, policy, break_when_any_done=False)
    assert td["action"].shape == (4, 6, 2)
    assert (td["action"].abs() <= 1).all()
    one = policy.act(td[0, -1]["next", "state"])
    assert one.shape == (2,) and (one.abs() <= 1).all()


def test_building_between_start_and_ge_is_flown_around():
    # the straight line from the start to the only GE crosses the building
    bz = (60.0, 340.0, 200.0, 470.0)
    ge = (260.0, 290.0)
    p0, p1 = torch.tensor(START), torch.tensor(ge)
    assert ph.segment_hits_rects(p0, p1, torch.tensor([bz]), torch.tensor([True])).any()
    sc = Scenario(bz=[bz], ge_pos=[ge], ge_data=[3.0], start=START)
    env, rec, agg, traj = _run([sc], batch=2)
    assert not rec["bz_collision"].any() and not rec["collided"].any()
    assert rec["landed"].all()
    assert agg["DCR"] == pytest.approx(1.0, abs=1e-5)
    # the planned path keeps its clearance (the end points of every slot)
    for t in traj:
        d = ph.point_rect_distance(t, torch.tensor([bz]), torch.tensor([True])).squeeze(-1)
        assert d.min() >= env.cfg.safety.d_min


def test_default_random_scenarios_b32_seed0():
    # measured (seed 0, B=32): DCR 1.000, CR 0.000, SLR 1.000, RVR 0.000, ECR 0.059
    env = UAVEnv(batch_size=[32], seed=0)
    rec, agg, _ = rollout_metrics(env, HeuristicPolicy(env.cfg))
    assert agg["n_episodes"] == 32
    assert agg["DCR"] >= 0.97
    assert agg["CR"] <= 0.07
    assert agg["SLR"] >= 0.9
    assert agg["RVR"] <= 0.07
    assert agg["boundary_exit_rate"] == 0.0
    assert agg["ECR"] <= 0.15


def test_rz_crossing_keeps_the_speed_limit():
    rz = (150.0, 0.0, 250.0, 500.0)  # a band every route to LA must cross
    sc = Scenario(rz=[rz], ge_pos=[(350.0, 400.0), (100.0, 250.0)], ge_data=[2.0, 2.0], start=START)
    env, rec, agg, traj = _run([sc], batch=2)
    assert not rec["rz_speeding"].any()
    assert rec["landed"].all() and agg["DCR"] == pytest.approx(1.0, abs=1e-5)
    for t in traj:  # it did cross the band
        assert (t[:, 0] < rz[0]).any() and (t[:, 0] > rz[2]).any()


def test_head_on_ou_is_avoided():
    env_cfg = make_env_config(ou={"p_turn": 0.0})
    ge = (400.0, 487.5)
    scenarios = [  # OUs flying west along (or next to) the DCU's line east
        Scenario(ge_pos=[ge], ge_data=[3.0], ou_pos=[(150.0, 487.5 + dy)], ou_vel=[(-v, 0.0)], start=START)
        for dy, v in ((0.0, 10.0), (0.6, 10.0), (-0.8, 7.0), (0.0, 4.0))
    ]
    # without avoidance the straight flight east meets the OU
    env = UAVEnv(env_cfg, batch_size=[4], seed=0, scenarios=scenarios)

    def straight(td):
        td.set("action", torch.tensor([[1.0, 0.0]]).expand(4, 2).clone())
        return td

    rec, _, _ = rollout_metrics(env, straight, max_steps=40)
    assert rec["ou_collision"].all()

    env, rec, agg, _ = _run(scenarios, env_cfg=env_cfg)
    assert not rec["ou_collision"].any()
    assert rec["landed"].all() and agg["DCR"] == pytest.approx(1.0, abs=1e-5)


def test_low_energy_goes_home_and_lands():
    # with barely any energy budget the heuristic skips far GEs and lands instead of running out
    env_cfg = make_env_config(energy={"e_limit": 38000.0, "e_total": 1e6})
    sc = Scenario(ge_pos=[(50.0, 450.0), (60.0, 60.0)], ge_data=[2.0, 2.0], start=START)
    env, rec, agg, _ = _run([sc], env_cfg=env_cfg)
    assert rec["landed"].all() and not rec["energy_exhausted"].any()
    # the near GE is collected, the far one (needs ~(430 + 430) m of flight) is not affordable
    assert 0.4 < agg["DCR"] < 0.6


def test_graph_is_cached_per_row():
    env = UAVEnv(batch_size=[3], seed=5)
    policy = HeuristicPolicy(env.cfg)
    td = env.reset()
    for _ in range(3):
        td = env.step(policy(td))["next"].clone()
    assert policy.graph_rebuilds == 3  # built once per row, reused while the map is unchanged
    agg = aggregate(rollout_metrics(env, policy, max_steps=5)[0])
    assert agg["n_episodes"] == 3


def test_narrow_gap_uses_the_tight_clearance():
    # a wall across the map with one 8 m gap: no corner at the normal clearance fits in it, so the
    # row gets the tight corners; the path through it stays clear of both sides
    bz, nfz = (0.0, 200.0, 150.0, 260.0), (158.0, 200.0, 500.0, 260.0)
    sc = Scenario(bz=[bz], nfz=[nfz], ge_pos=[(80.0, 150.0)], ge_data=[2.0], start=START)
    env = UAVEnv(batch_size=[1], seed=0, scenarios=[sc])
    policy = HeuristicPolicy(env.cfg)
    rec, agg, _ = rollout_metrics(env, policy)
    assert policy.tight_rows == 1
    assert not rec["collided"].any() and rec["landed"].all()
    assert agg["DCR"] == pytest.approx(1.0, abs=1e-5)
