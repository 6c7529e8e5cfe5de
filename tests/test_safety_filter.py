"""The safety filter (uavlae/policies/safety.py, docs/model.md §10) on hand-placed states whose
answers are worked out by hand, and its guarantee on sampled scenarios."""

import math

import pytest
import torch
import yaml

from uavlae.envs import UAVEnv, make_env_config
from uavlae.envs import physics as ph
from uavlae.envs import world
from uavlae.envs.metrics import rollout_metrics
from uavlae.factories import CONF_DIR
from uavlae.policies.random import UniformRandomPolicy
from uavlae.policies.safety import FilteredPolicy, SafetyFilter, SafetyFilterConfig, make_safety_filter_config

# a small candidate set, so each answer below can be worked out by hand: the wish and its
# shortenings (1, .75, .5, .25, .1), its x and y parts at the same factors, east / north / west /
# south at 10 m/s, hovering
FOUR = {"mode": "deploy", "headings": 4, "ring_speeds": [1.0]}
NONE4 = torch.zeros(1, 0, 4)
NONE = torch.zeros(1, 0, dtype=torch.bool)


def _state(p, bz=(), nfz=(), rz=(), ou=(), ou_vel=()):
    """A raw state of one row with the given zones and OUs (the filter reads no more)."""
    def rects(rs):
        return (torch.tensor([rs], dtype=torch.float32), torch.ones(1, len(rs), dtype=torch.bool)) if rs else (NONE4, NONE)

    s = {"position": torch.tensor([p], dtype=torch.float32)}
    for name, rs in (("bz", bz), ("nfz", nfz), ("rz", rz)):
        s[name], s[name + "_mask"] = rects(list(rs))
    k = len(ou)
    s["ou_pos"] = torch.tensor([list(ou)], dtype=torch.float32).reshape(1, k, 2)
    s["ou_vel"] = torch.tensor([list(ou_vel)], dtype=torch.float32).reshape(1, k, 2)
    s["ou_mask"] = torch.ones(1, k, dtype=torch.bool)
    return s


def _filter(cfg=FOUR, **env):
    return SafetyFilter(make_env_config(env or None), cfg)


def test_config_yaml_mirrors_model_and_validates():
    data = yaml.safe_load((CONF_DIR / "safety_filter" / "default.yaml").read_text())
    assert make_safety_filter_config(data) == SafetyFilterConfig()
    assert SafetyFilterConfig().mode == "off"
    with pytest.raises(ValueError, match="safety_filter.mode"):
        make_safety_filter_config(mode="always")
    with pytest.raises(ValueError, match="safety_filter.rz_speed_margin"):
        make_safety_filter_config(rz_speed_margin=1.2)


def test_building_ahead_shortens_the_step_and_a_safe_action_is_unchanged():
    # BZ's west edge 5 m east of the DCU; clearance 1 m. East at 10, 7.5 and 5 m/s ends at or in
    # the building; 2.5 m/s ends 2.5 m from it (>= min(1, 5) = 1) and its segment misses the BZ
    # inflated by min(1, 5 - 0.001) = 1 m (x >= 104): the nearest admissible candidate, |dv| = 7.5.
    f = _filter()
    s = _state((100.0, 100.0), bz=[(105.0, 80.0, 150.0, 120.0)])
    action, changed, delta = f.filter_action(s, torch.tensor([[1.0, 0.0]]))
    assert action.tolist() == [[0.25, 0.0]]
    assert changed.tolist() == [True] and delta.item() == pytest.approx(7.5)
    # west, away from the building: returned as it came
    safe = torch.tensor([[-0.6, 0.3]])
    action, changed, delta = f.filter_action(s, safe)
    assert torch.equal(action, safe) and changed.tolist() == [False] and delta.item() == 0.0


def test_a_dcu_inside_the_clearance_never_gets_nearer():
    # clearance 3 m, the DCU 2 m west of the BZ: 1 m/s east would end 1 m from it (< min(3, 2) = 2):
    # changed to the nearest admissible, hovering (every shortening of the wish also gets nearer);
    # 10 m/s north, along the wall at 2 m, keeps its distance and stays as it is.
    f = _filter({**FOUR, "filter_clearance": 3.0})
    s = _state((100.0, 100.0), bz=[(102.0, 50.0, 150.0, 300.0)])
    action, changed, _ = f.filter_action(s, torch.tensor([[0.1, 0.0]]))
    assert changed.tolist() == [True] and action.abs().max().item() == 0.0
    along = torch.tensor([[0.0, 1.0]])
    action, changed, _ = f.filter_action(s, along)
    assert torch.equal(action, along) and changed.tolist() == [False]


def test_ten_metres_a_second_across_an_rz_edge_is_capped():
    # an RZ 3 m east: the segment east touches it (inflated by 1 m), so its speed is capped at
    # 0.95 * v_limit = 4.75 m/s, heading kept: action (0.475, 0). The env then sees no speeding,
    # where the wish would have sped (10 > 5 on a segment that meets the RZ).
    f = _filter()
    rz = [(103.0, 50.0, 200.0, 150.0)]
    s = _state((100.0, 100.0), rz=rz)
    action, changed, delta = f.filter_action(s, torch.tensor([[1.0, 0.0]]))
    assert action[0, 0].item() == pytest.approx(0.475) and action[0, 1].item() == 0.0
    assert delta.item() == pytest.approx(5.25)
    rz_t = torch.tensor([rz])
    for a, speeding in ((action, False), (torch.tensor([[1.0, 0.0]]), True)):
        v = ph.action_to_velocity(a, 10.0)
        touches = ph.segment_hits_rects(s["position"], s["position"] + v, rz_t, torch.ones(1, 1, dtype=torch.bool))
        assert bool(touches.any()) and bool(v.norm() > 5.0 + 1e-4) == speeding


def test_cruise_flies_the_wish_at_full_speed_unless_a_rule_binds():
    """safety_filter.cruise: in open air (0.3, 0.4), 5 m/s, is flown at 10 m/s in its direction,
    (0.6, 0.8), and counts as unchanged (the filter did not intervene); (0.03, 0), 0.3 m/s, under
    the 0.5 m/s floor, stays as it is. The RZ 3 m east caps (0.3, 0), 3 m/s cruising at 10, at
    4.75 m/s: (0.475, 0), a change of 10 - 4.75 = 5.25 m/s from the cruise command."""
    f = _filter({**FOUR, "cruise": True})
    s = _state((100.0, 100.0))
    action, changed, delta = f.filter_action(s, torch.tensor([[0.3, 0.4]]))
    torch.testing.assert_close(action, torch.tensor([[0.6, 0.8]]))
    assert changed.tolist() == [False] and delta.item() == 0.0
    hover = torch.tensor([[0.03, 0.0]])
    action, changed, _ = f.filter_action(s, hover)
    assert torch.equal(action, hover) and changed.tolist() == [False]
    s = _state((100.0, 100.0), rz=[(103.0, 50.0, 200.0, 150.0)])
    action, changed, delta = f.filter_action(s, torch.tensor([[0.3, 0.0]]))
    assert action[0, 0].item() == pytest.approx(0.475) and action[0, 1].item() == 0.0
    assert changed.tolist() == [True] and delta.item() == pytest.approx(5.25)
    # without cruise the same 3 m/s is under the cap and flies as it is
    slow = torch.tensor([[0.3, 0.0]])
    action, changed, _ = _filter().filter_action(s, slow)
    assert torch.equal(action, slow) and changed.tolist() == [False]


def test_corner_with_the_boundary_and_a_building():
    # 0.5 m above the south edge (so every step ends at y >= 0.5), a BZ 2 m east. The wish
    # (7.07, -7.07) leaves the area; so does its y part and all their shortenings; its x part
    # ends in the BZ at 1, .75 and .5, 0.23 m from it at .25 (< min(1, 2) = 1); at .1, (0.707, 0)
    # ends 1.293 m from it and misses the BZ inflated by 1 m: |dv| = sqrt(6.364^2 + 7.071^2) = 9.513,
    # nearer than hovering (10) or north / west (18.48).
    f = _filter()
    s = _state((100.0, 0.5), bz=[(102.0, 0.0, 150.0, 50.0)])
    action, changed, delta = f.filter_action(s, torch.tensor([[1.0, -1.0]]))
    assert changed.tolist() == [True]
    assert action[0, 0].item() == pytest.approx(0.1 * math.sqrt(0.5), rel=1e-5) and action[0, 1].item() == 0.0
    assert delta.item() == pytest.approx(math.hypot(10 * math.sqrt(0.5) * 0.9, 10 * math.sqrt(0.5)), rel=1e-5)


def test_an_ou_on_a_collision_course_is_avoided():
    # head-on: the OU 15 m east flies west at 10 m/s, the wish east at 10 m/s: they would meet
    # after 0.75 s. The executed velocity keeps the predicted closest approach (OU at its
    # velocity) >= min(5, 15) = 5 m, and the env's step with that OU motion records no collision.
    f = _filter({"mode": "deploy"})
    s = _state((100.0, 100.0), ou=[(115.0, 100.0)], ou_vel=[(-10.0, 0.0)])
    wish = torch.tensor([[1.0, 0.0]])
    assert ph.closest_approach(s["position"], 10 * wish, s["ou_pos"], s["ou_vel"], 1.0).item() == 0.0
    action, changed, _ = f.filter_action(s, wish)
    v = ph.action_to_velocity(action, 10.0)
    assert changed.tolist() == [True]
    assert ph.closest_approach(s["position"], v, s["ou_pos"], s["ou_vel"], 1.0).item() >= 5.0
    # an OU outside the perception radius (25 m > 20 m) is not seen, so nothing changes
    far = _state((100.0, 100.0), ou=[(125.0, 100.0)], ou_vel=[(-10.0, 0.0)])
    assert f.filter_action(far, wish)[1].tolist() == [False]


def test_random_actions_through_the_filter_keep_the_static_rules_on_sampled_scenarios():
    # the guarantee: hovering is always admissible, so whatever is proposed no BZ or NFZ is met,
    # no step leaves the area and no RZ is sped through (docs/model.md §10)
    cfg = make_env_config(None)
    env = UAVEnv(cfg, batch_size=[24], seed=5)
    pilot = FilteredPolicy(UniformRandomPolicy(env.action_spec, seed=1), SafetyFilter(cfg, {"mode": "deploy"}))
    rec, agg, _ = rollout_metrics(env, pilot, max_steps=250, cfg=cfg)
    for event in ("bz_collision", "nfz_entry", "boundary_exit", "rz_speeding"):
        assert not rec[event].any(), event
    unfiltered = rollout_metrics(env, UniformRandomPolicy(env.action_spec, seed=1), max_steps=250, cfg=cfg)[0]
    assert unfiltered["collided"].sum() >= 5  # the same proposals unfiltered crash often (9 of 24)
    stats = pilot.stats.snapshot()
    assert 0 < stats["intervention_rate"] < 1 and stats["mean_change"] > 0


def test_filter_is_one_graph_for_torch_export():
    f = _filter({"mode": "deploy"})
    s = _state((100.0, 100.0), bz=[(105.0, 80.0, 150.0, 120.0)], rz=[(50.0, 50.0, 90.0, 150.0)],
               ou=[(110.0, 95.0)], ou_vel=[(0.0, 3.0)])

    class Velocity(torch.nn.Module):
        def __init__(self):
            super().__init__()
            self.f = f

        def forward(self, s, wish):
            return self.f.velocity(s, wish)

    wish = torch.tensor([[10.0, 0.0]])
    program = torch.export.export(Velocity(), (s, wish))
    assert torch.equal(program.module()(s, wish), f.velocity(s, wish))


def test_world_state_keys_cover_the_filter():
    # the filter reads only raw state entries the env keeps (docs/env_contract.md)
    from uavlae.policies.safety import STATE_KEYS

    assert set(STATE_KEYS) <= set(world.STATE_KEYS)


def _east_collector(cfg, safety_cfg):
    """A collector over one row that starts at (100, 100) with a building 5 m east, whose policy
    always asks 10 m/s east, through a filter of ``safety_cfg``."""
    from tensordict.nn import TensorDictModuleBase

    from uavlae.collect import UAVCollector
    from uavlae.envs.scenario import Scenario
    from uavlae.policies.override import OverridePolicy

    class East(TensorDictModuleBase):
        in_keys, out_keys = ["observation"], ["action"]

        def forward(self, td):
            td.set("action", torch.tensor([[1.0, 0.0]]).expand(td.batch_size[0], 2).clone())
            return td

    sc = Scenario(bz=[(105.0, 80.0, 150.0, 120.0)], ge_pos=[(300.0, 300.0)], ge_data=[1.0], start=(100.0, 100.0))
    env = UAVEnv(cfg, batch_size=[1], seed=0, scenarios=[sc])
    return UAVCollector(env, OverridePolicy(East(), None, mode="never", fallback="policy", seed=0),
                        frames_per_batch=1, safety=SafetyFilter(cfg, safety_cfg))


def test_collector_stores_the_filtered_action_and_prices_the_change():
    """A policy that asks 10 m/s east with a building 5 m east of the start: the filter flies
    (2.5, 0) instead (the hand-worked case above, with the four-heading ring), the transition
    stores that action, records |dv| = 7.5 m/s, and with penalty 2 the reward loses
    2 * 7.5 / 10 = 1.5 against the same step with penalty 0."""
    cfg = make_env_config({"ou": {"count": {"min": 0, "max": 0}}})
    rewards = {}
    for penalty in (0.0, 2.0):
        col = _east_collector(cfg, {**FOUR, "penalty": penalty})
        tr = col.step()
        assert tr["action"].tolist() == [[0.25, 0.0]]
        assert tr["safety", "changed"].tolist() == [True] and tr["safety", "delta"].item() == pytest.approx(7.5)
        assert not tr["next", "events", "bz_collision"].any()
        rewards[penalty] = tr["next", "reward"].item()
        assert col.safety_totals.snapshot()["intervention_rate"] == 1.0
    assert rewards[0.0] - rewards[2.0] == pytest.approx(1.5, abs=1e-5)


def test_collector_can_store_the_wish_and_count_the_change_as_cost():
    """The same step as above (10 m/s east, the filter flies 2.5 m/s, |dv| = 7.5 m/s). With
    learn_from=proposed the transition stores the wish (1, 0) with the reward of the corrected
    flight; with cost 2 its ("next", "cost") gains 2 * 7.5 / 10 = 1.5 over the env's 0 (no event),
    while the episode tracker, which reports docs/model.md §7's cost, still counts 0."""
    cfg = make_env_config({"ou": {"count": {"min": 0, "max": 0}}})
    out = {}
    for learn_from, cost in (("executed", 0.0), ("proposed", 2.0)):
        col = _east_collector(cfg, {**FOUR, "learn_from": learn_from, "cost": cost})
        out[learn_from] = tr = col.step()
        assert tr["safety", "delta"].item() == pytest.approx(7.5)
        assert not tr["next", "events", "bz_collision"].any()
        assert col.tracker.state_dict()["acc"]["cost"].tolist() == [0.0]
    assert out["executed"]["action"].tolist() == [[0.25, 0.0]]
    assert out["proposed"]["action"].tolist() == [[1.0, 0.0]]
    # the executed flight is the same: same next state, same reward
    assert torch.equal(out["proposed"]["next", "observation"], out["executed"]["next", "observation"])
    assert out["proposed"]["next", "reward"].item() == out["executed"]["next", "reward"].item()
    assert out["executed"]["next", "cost"].item() == 0.0
    assert out["proposed"]["next", "cost"].item() == pytest.approx(1.5)


def test_an_advised_run_flies_its_with_advisor_evaluation_through_its_filter(tmp_path):
    """The with-advisor evaluation of a filtered run is the pilot's flight with the advisor
    acting too: the filter's counts come back beside the override's, and the filter leaves no
    RZ speeding (hovering is always admissible), as it does for the actor alone."""
    from tests.test_train import _run

    final = _run("sac_heuristic_planner", tmp_path / "r", "safety_filter.mode=train_and_deploy",
                 "trainer.eval_with_advisor=true", "trainer.eval_max_steps=60")
    assert final["advised/safety/rows"] > 0 and 0 <= final["advised/safety/intervention_rate"] <= 1
    assert final["advised/override/triggered"] >= 0 and final["advised/RVR"] == 0.0
