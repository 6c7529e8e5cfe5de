"""The paper's greedy heuristic (uavlae.policies.greedy): each rule on a hand-made state, worked
out by hand, then whole episodes on a hand-made map and on the default random scenarios."""

import math

import pytest
import torch
import yaml

from uavlae.envs import UAVEnv
from uavlae.envs import physics as ph
from uavlae.envs.metrics import rollout_metrics
from uavlae.envs.scenario import Scenario
from uavlae.factories import CONF_DIR
from uavlae.policies.greedy import GreedyConfig, GreedyPolicy, make_greedy_config

LA = (475.0, 0.0, 500.0, 25.0)  # SPEC §1; its centre is (487.5, 12.5)


def _rects(rs):
    if not rs:
        return torch.zeros(1, 1, 4), torch.zeros(1, 1, dtype=torch.bool)
    return torch.tensor([rs], dtype=torch.float32), torch.ones(1, len(rs), dtype=torch.bool)


def _state(pos, ges, *, bz=(), nfz=(), rz=(), ous=(), step=0, energy=8e5):
    """One row of the raw state the env writes (docs/env_contract.md); ``ges``: (x, y, data)."""
    s = {"position": torch.tensor([pos], dtype=torch.float32), "energy_left": torch.tensor([energy]),
         "step": torch.tensor([step]), "landing": torch.tensor([LA])}
    s["ge_pos"] = torch.tensor([[g[:2] for g in ges]], dtype=torch.float32)
    s["ge_remaining"] = torch.tensor([[g[2] for g in ges]], dtype=torch.float32)
    s["ge_mask"] = torch.ones(1, len(ges), dtype=torch.bool)
    for name, rs in (("bz", bz), ("nfz", nfz), ("rz", rz)):
        s[name], s[f"{name}_mask"] = _rects(list(rs))
    if ous:
        s["ou_pos"] = torch.tensor([[o[0] for o in ous]], dtype=torch.float32)
        s["ou_vel"] = torch.tensor([[o[1] for o in ous]], dtype=torch.float32)
        s["ou_mask"] = torch.ones(1, len(ous), dtype=torch.bool)
    else:
        s["ou_pos"], s["ou_vel"], s["ou_mask"] = torch.zeros(1, 1, 2), torch.zeros(1, 1, 2), torch.zeros(1, 1, dtype=torch.bool)
    return s


def _act(policy, *args, **kw):
    return policy.act(_state(*args, **kw))[0].tolist()


def test_config_yaml_mirrors_model_and_validates():
    path = CONF_DIR / "advisor" / "greedy.yaml"
    assert make_greedy_config(yaml.safe_load(path.read_text())) == GreedyConfig()
    with pytest.raises(ValueError, match="greedy.headings"):
        make_greedy_config(headings=2)
    with pytest.raises(ValueError, match="greedy.path_search"):
        make_greedy_config(path_search=True)


def test_flies_straight_at_the_nearest_ge_and_ends_the_step_on_it():
    pol = GreedyPolicy()
    # one GE 50 m away along (3, 4): full speed along it, v / v_max = (0.6, 0.8)
    assert _act(pol, (100, 100), [(130, 140, 2.0)]) == pytest.approx([0.6, 0.8], abs=1e-6)
    # 5 m away: the step ends on it, v = (3, 4) m/s
    assert _act(GreedyPolicy(), (100, 100), [(103, 104, 2.0)]) == pytest.approx([0.3, 0.4], abs=1e-6)
    # two GEs, 50 m and 40 m away: the nearer; without data it does not count
    assert _act(GreedyPolicy(), (100, 100), [(130, 140, 2.0), (60, 100, 1.0)]) == pytest.approx([-1.0, 0.0], abs=1e-6)
    assert _act(GreedyPolicy(), (100, 100), [(130, 140, 2.0), (60, 100, 0.0)]) == pytest.approx([0.6, 0.8], abs=1e-6)
    # no data left anywhere: LA's centre, (387.5, -87.5) / 396.26 at full speed
    d = math.hypot(387.5, 87.5)
    assert _act(GreedyPolicy(), (100, 100), [(60, 100, 0.0)]) == pytest.approx([387.5 / d, -87.5 / d], abs=1e-6)


def test_residential_zone_caps_the_speed():
    # inside an RZ: |v| <= 0.95 * v_limit = 4.75 m/s, i.e. 0.475 of v_max, still toward the GE
    a = _act(GreedyPolicy(), (100, 100), [(300, 100, 2.0)], rz=[(50, 50, 150, 150)])
    assert a == pytest.approx([0.475, 0.0], abs=1e-6)
    # 5 m west of the RZ: the 10 m step would enter it (inflated by 1 m), so capped as well
    a = _act(GreedyPolicy(), (45, 100), [(300, 100, 2.0)], rz=[(50, 50, 150, 150)])
    assert a == pytest.approx([0.475, 0.0], abs=1e-6)
    # 12 m west: the step ends at 43 m, 6 m short of the inflated RZ: full speed
    assert _act(GreedyPolicy(), (38, 100), [(300, 100, 2.0)], rz=[(50, 50, 150, 150)]) == pytest.approx([1.0, 0.0], abs=1e-6)


def test_building_ahead_turns_by_the_smaller_free_turn_and_keeps_the_side():
    """DCU (105, 88), GE due east at (200, 88), BZ (120, 94)-(160, 150), inflated by the 8 m
    clearance to x >= 112, y in [86, 158]. Straight east the step's end (115, 88) is inside.
    Turning right (clockwise) by k * 11.25 degrees: k = 1 ends at (114.81, 86.05), inside; k = 2
    ends at (114.24, 84.17) and crosses x = 112 at y = 85.10 < 86: free. Turning left, the end's
    x must stay below 112: cos(theta) < 0.7, k = 5 (56.25 degrees). Right wins: (cos, sin)(-22.5)."""
    pol = GreedyPolicy()
    bz = [(120, 94, 160, 150)]
    a = _act(pol, (105, 88), [(200, 88, 2.0)], bz=bz)
    assert a == pytest.approx([math.cos(math.radians(22.5)), -math.sin(math.radians(22.5))], abs=1e-5)
    # next slot, the building mirrored about y = 88 (BZ (120, 26)-(160, 82): inflated y in [18, 90]):
    # now the left turn by k = 2 is the smaller free one (the mirror of the above), which a fresh
    # policy takes; this one keeps its side and turns right, by k = 5 (the end's x below 112)
    mirrored = dict(bz=[(120, 26, 160, 82)], step=1)
    fresh = _act(GreedyPolicy(), (105, 88), [(200, 88, 2.0)], **mirrored)
    assert fresh == pytest.approx([math.cos(math.radians(22.5)), math.sin(math.radians(22.5))], abs=1e-5)
    kept = _act(pol, (105, 88), [(200, 88, 2.0)], **mirrored)
    assert kept == pytest.approx([math.cos(math.radians(56.25)), -math.sin(math.radians(56.25))], abs=1e-5)


def test_ou_hover_retreat_and_perception_radius():
    ge = [(200, 100, 2.0)]
    # OU 21 m ahead at 10 m/s toward the DCU: beyond PR = 20 m, so unknown: full speed east
    assert _act(GreedyPolicy(), (100, 100), ge, ous=[((121, 100), (-10, 0))]) == pytest.approx([1.0, 0.0], abs=1e-6)
    # at 19 m it is seen: flying east meets it (closest approach 0); hovering, it ends 9 m away >= 5
    assert _act(GreedyPolicy(), (100, 100), ge, ous=[((119, 100), (-10, 0))]) == pytest.approx([0.0, 0.0], abs=1e-6)
    # at 12 m hovering ends 2 m from it: retreat straight away at v_max, the gap stays 12 m
    assert _act(GreedyPolicy(), (100, 100), ge, ous=[((112, 100), (-10, 0))]) == pytest.approx([-1.0, 0.0], abs=1e-6)
    # once it has passed (now west of the DCU, flying away), the DCU flies on
    assert _act(GreedyPolicy(), (100, 100), ge, ous=[((90, 100), (-10, 0))]) == pytest.approx([1.0, 0.0], abs=1e-6)


def test_heads_home_when_the_slots_left_only_suffice_for_the_return():
    """DCU (400, 100), LA centre 123.74 m away: ceil(12.37) = 13 slots, * 1.5 + 20 = 39.5 slots.
    With 41 slots left (step 959) it still collects (GE due north); with 39 left (step 961) it
    flies to LA along (1, -1) / sqrt(2)."""
    ge = [(400, 150, 2.0)]
    assert _act(GreedyPolicy(), (400, 100), ge, step=959) == pytest.approx([0.0, 1.0], abs=1e-6)
    r = 1 / math.sqrt(2)
    assert _act(GreedyPolicy(), (400, 100), ge, step=961) == pytest.approx([r, -r], abs=1e-6)
    # the energy rule: E_min(123.74 m) = 13 slots * (P(10) + P(0)) = 13 * 294.51 J; * 1.5 + 5000 J
    e_min = float(ph.min_return_energy(torch.tensor(math.hypot(87.5, 87.5)), GreedyPolicy().env_cfg.energy,
                                       GreedyPolicy().env_cfg.motion))
    assert e_min == pytest.approx(13 * (126.03 + 168.48), rel=1e-3)
    assert _act(GreedyPolicy(), (400, 100), ge, energy=1.5 * e_min + 4000) == pytest.approx([r, -r], abs=1e-6)
    assert _act(GreedyPolicy(), (400, 100), ge, energy=1.5 * e_min + 6000) == pytest.approx([0.0, 1.0], abs=1e-6)


def test_loop_escape_abandons_a_ge_without_progress():
    """Held at (100, 100) (no progress), the target GE A (200, 100) is kept for 60 slots; at the
    61st call (step 60) the stall counter reaches stall_patience = 60: A is abandoned and the DCU
    turns to B (100, 300), due north."""
    pol = GreedyPolicy()
    ges = [(200, 100, 2.0), (100, 300, 2.0)]
    for step in range(60):
        assert _act(pol, (100, 100), ges, step=step) == pytest.approx([1.0, 0.0], abs=1e-6)
    assert _act(pol, (100, 100), ges, step=60) == pytest.approx([0.0, 1.0], abs=1e-6)
    # abandoned for the episode; a new episode (step 0) forgets it
    assert _act(pol, (100, 100), ges, step=61) == pytest.approx([0.0, 1.0], abs=1e-6)
    assert _act(pol, (100, 100), ges, step=0) == pytest.approx([1.0, 0.0], abs=1e-6)


def test_memory_does_not_leak_to_another_scenario_at_the_next_step():
    # row 0 abandons its GE 0 after 60 slots without progress; at the next step the row holds
    # another scenario (SAC+Heuristic hands over other rows): GE 0 (130, 100) is the nearest, east
    pol = GreedyPolicy()
    ges = [(200, 100, 2.0), (100, 300, 2.0)]
    for step in range(61):
        pol.act(_state((100, 100), ges, step=step))
    assert _act(pol, (100, 100), ges, step=61) == pytest.approx([0.0, 1.0], abs=1e-6)
    other = [(130, 100, 2.0), (100, 400, 2.0)]
    assert _act(pol, (100, 100), other, step=62) == pytest.approx([1.0, 0.0], abs=1e-6)


def test_memory_round_trips_for_exact_resume():
    pol = GreedyPolicy()
    ges = [(200, 100, 2.0), (100, 300, 2.0)]
    for step in range(30):
        pol.act(_state((100, 100), ges, step=step))
    other = GreedyPolicy()
    other.load_cache_state(pol.cache_state())
    for step in range(30, 70):
        assert torch.equal(pol.act(_state((100, 100), ges, step=step)), other.act(_state((100, 100), ges, step=step)))


def test_building_between_start_and_ge_is_flown_around_and_it_lands():
    start = (12.5, 487.5)
    bz = (60.0, 340.0, 200.0, 470.0)
    ge = (260.0, 290.0)
    assert ph.segment_hits_rects(torch.tensor(start), torch.tensor(ge), torch.tensor([bz]), torch.tensor([True])).any()
    sc = Scenario(bz=[bz], ge_pos=[ge], ge_data=[3.0], start=start)
    env = UAVEnv(batch_size=[1], seed=0, scenarios=[sc])
    rec, agg, traj = rollout_metrics(env, GreedyPolicy(env.cfg))
    assert not rec["collided"].any() and rec["landed"].all()
    assert agg["DCR"] == pytest.approx(1.0, abs=1e-5)
    d = ph.point_rect_distance(traj[0], torch.tensor([bz]), torch.tensor([True])).squeeze(-1)
    assert d.min() >= env.cfg.safety.d_min  # the 8 m clearance holds at every slot's end


def test_default_random_scenarios_b32_seed0():
    # measured (seed 0, B = 32): DCR 0.980, CR 0.031 (one OU collision), SLR 0.969, RVR 0, ECR 0.074
    env = UAVEnv(batch_size=[32], seed=0)
    rec, agg, _ = rollout_metrics(env, GreedyPolicy(env.cfg))
    assert agg["n_episodes"] == 32
    assert agg["DCR"] >= 0.9 and agg["SLR"] >= 0.9 and agg["CR"] <= 0.1 and agg["RVR"] <= 0.05
    assert not rec["bz_collision"].any() and not rec["nfz_entry"].any() and agg["boundary_exit_rate"] == 0.0
