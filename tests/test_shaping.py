"""The learning aids beyond the paper (``env=shaped``): the progress reward and the ego-centric
observation columns, on hand-made scenarios with hand-computed values.

Progress: w·(Φ(s') − Φ(s)), Φ = −(d_target + d_tar·n_left)/d_tar, w = 8, d_tar = 707; the target
is the nearest GE with data (ground distance), else the nearest point of LA = [475,500]x[0,25].
"""

import math

import pytest
import torch
from hydra import compose, initialize_config_dir

from uavlae.envs import UAVEnv, make_env_config
from uavlae.envs.scenario import Scenario
from uavlae.factories import CONF_DIR

SHAPED = {"reward": {"progress_weight": 8.0}, "ego_features": True}


def env_with(start, cfg=SHAPED, b=1, **kw):
    base = dict(nfz=[], rz=[], bz=[], ou_pos=[], ou_vel=[])
    base.update(kw)
    return UAVEnv(cfg, batch_size=[b], seed=0, scenarios=[Scenario(start=start, **base)])


def step(env, td, action):
    td["action"] = torch.tensor([action], dtype=torch.float32).expand(env.batch_size[0], 2)
    out = env.step(td)
    return out["next"], env.step_mdp(out)


def progress(nxt):
    return float(nxt["reward_terms", "progress"][0].item())


def test_approaching_the_nearest_ge_earns_its_distance():
    # GEs at (300,300) and (100,100); from (300,400) south 10 m: d 100 -> 90, still out of range
    env = env_with((300.0, 400.0), ge_pos=[(300.0, 300.0), (100.0, 100.0)], ge_data=[2.0, 1.0])
    nxt, _ = step(env, env.reset(), (0.0, -1.0))
    assert float(nxt["state", "slot_data"][0].item()) == 0.0
    assert progress(nxt) == pytest.approx(8 * 10 / 707, abs=1e-5)  # 0.11315
    # the reward is the sum of its terms, the progress term included
    total = sum(nxt["reward_terms", k] for k in nxt["reward_terms"].keys())
    torch.testing.assert_close(nxt["reward"], total)


def test_finishing_a_ge_pays_one_unit_less_the_jump_to_the_next():
    # hover 5 m from a GE with 1 unit (SNR 0.01·0.36/125/1e-6 = 28.8, rate 4.9): emptied in one slot;
    # Φ: -(5 + 1414)/707 -> -(|(100,100)-(300,305)| + 707)/707, |.| = sqrt(82025) = 286.40
    env = env_with((300.0, 305.0), ge_pos=[(300.0, 300.0), (100.0, 100.0)], ge_data=[1.0, 1.0])
    nxt, _ = step(env, env.reset(), (0.0, 0.0))
    assert float(nxt["state", "slot_data"][0].item()) == pytest.approx(1.0)
    want = 8 * (1419 - math.sqrt(82025) - 707) / 707  # 4.8158
    assert progress(nxt) == pytest.approx(want, abs=1e-4)


def test_after_the_last_ge_the_target_is_la():
    # last GE emptied at (480,45): Φ -1 -> -d_LA/707 with d_LA = 45 - 25 = 20; then 10 m south: +8·10/707
    env = env_with((480.0, 45.0), ge_pos=[(480.0, 45.0)], ge_data=[1.0])
    nxt, td = step(env, env.reset(), (0.0, 0.0))
    assert progress(nxt) == pytest.approx(8 * (1 - 20 / 707), abs=1e-4)  # 7.7737
    nxt, _ = step(env, td, (0.0, -1.0))  # (480, 35): 10 m from LA
    assert progress(nxt) == pytest.approx(8 * 10 / 707, abs=1e-5)


def potential(state, i):
    """Φ computed here from the raw state, independently of the env's code."""
    p = state["position"][i]
    left = state["ge_remaining"][i] > 0
    if left.any():
        d = min(float(torch.linalg.vector_norm(g - p)) for g, k in zip(state["ge_pos"][i], left) if k)
    else:
        x, y = float(p[0]), float(p[1])
        d = math.hypot(max(475 - x, 0.0, x - 500), max(0.0 - y, 0.0, y - 25))
    return -(d + 707 * int(left.sum())) / 707


def test_progress_telescopes_over_an_episode():
    # its sum is 8·(Φ(end) - Φ(start)): hovering or looping cannot farm it
    cfg = {**SHAPED, "terminate_on_collision": False}
    env = UAVEnv(cfg, batch_size=[3], seed=5)
    td = env.reset()
    phi0 = [potential(td["state"], i) for i in range(3)]
    total = torch.zeros(3, dtype=torch.float64)
    g = torch.Generator().manual_seed(1)
    for _ in range(40):
        td["action"] = torch.rand(3, 2, generator=g) * 2 - 1
        out = env.step(td)
        total += out["next", "reward_terms", "progress"].squeeze(-1).double()
        td = env.step_mdp(out)
    assert not out["next", "done"].any()
    want = [8 * (potential(td["state"], i) - phi0[i]) for i in range(3)]
    torch.testing.assert_close(total, torch.tensor(want, dtype=torch.float64), atol=1e-3, rtol=0)


def test_ego_columns_hand_values():
    # DCU at (100,100); GEs (100,400) and (400,400): target vector (0,300) / the area's diagonal
    # (500·sqrt 2 = 707.107), direction (0,1);
    # BZ [130,90,200,200]: nearest point (130,100), vector (30,0)/50; NFZ [0,160,50,300]: nearest
    # point (50,160), vector (-50,60), longer than 50, so saturated to length 50 then /50
    env = env_with((100.0, 100.0), ge_pos=[(100.0, 400.0), (400.0, 400.0)], ge_data=[1.0, 1.0],
                   bz=[(130.0, 90.0, 200.0, 200.0)], nfz=[(0.0, 160.0, 50.0, 300.0)])
    obs = env.reset()["observation"][0]
    n = math.hypot(50, 60)
    want = [0.0, 300 / math.hypot(500, 500), 0.0, 1.0, 0.6, 0.0, -50 / n, 60 / n]
    torch.testing.assert_close(obs[-8:], torch.tensor(want), atol=1e-5, rtol=0)


def test_off_by_default_and_sizes():
    plain = UAVEnv(batch_size=[2], seed=0)
    # SPEC §6 + extras: 5·15 GE + 5·9 zone + 5·7 OU + 14 DCU + 6 extra = 175 columns
    assert plain.layout.size == 175
    td = plain.rollout(5, break_when_any_done=False)
    assert (td["next", "reward_terms", "progress"] == 0).all()
    assert UAVEnv(SHAPED, batch_size=[2], seed=0).layout.size == 183


def test_env_shaped_group_composes():
    with initialize_config_dir(str(CONF_DIR), version_base="1.3"):
        cfg = compose("config", overrides=["+exp=sac", "env=shaped"])
    ec = make_env_config(cfg.env)
    assert ec.reward.progress_weight == 8.0 and ec.ego_features
    assert ec.reward.sigma == make_env_config(None).reward.sigma  # the SPEC terms are untouched


def test_env_shaped_geodesic_groups_compose():
    with initialize_config_dir(str(CONF_DIR), version_base="1.3"):
        hard = make_env_config(compose("config", overrides=["+exp=sac", "env=shaped_geodesic"]).env)
        soft = make_env_config(compose("config", overrides=["+exp=sac", "env=shaped_geodesic_soft"]).env)
    assert hard.reward.progress_metric == soft.reward.progress_metric == "geodesic"
    assert hard.reward.progress_clearance_cost == 0.0 and soft.reward.progress_clearance_cost == 10.0
    assert soft.model_dump()["reward"] | {"progress_clearance_cost": 0.0} == hard.model_dump()["reward"]


def test_progress_weight_must_be_nonnegative():
    with pytest.raises(ValueError, match="progress_weight"):
        make_env_config(reward={"progress_weight": -1.0})


# ---------------------------------------------------------------- geodesic progress metric
GEO = {"reward": {"progress_weight": 8.0, "progress_metric": "geodesic"}, "ego_features": True}
WALL = dict(bz=[(100.0, 0.0, 120.0, 400.0)])  # a wall from the south edge up to y = 400


def test_geodesic_distance_goes_around_a_wall():
    # DCU (50,100), GE (170,100) behind the wall: 120 m straight. The way keeps the 12 m clearance,
    # so it passes the wall's top at y = 412 between x = 88 and 132: 2·sqrt(38² + 312²) + 44 = 672.6
    # m; on the 8-connected 10 m grid each leg costs 28·10 + 3·10·sqrt 2 = 322.4 m, and the top 50 m,
    # so the field reads between 660 and 720 (plus half a cell at each end)
    env = env_with((50.0, 100.0), cfg=GEO, ge_pos=[(170.0, 100.0)], ge_data=[1.0], **WALL)
    td = env.reset()
    from uavlae.envs.geodesic import geodesic_target

    state = {k: v for k, v in td["state"].items()}
    d, unit, _ = geodesic_target(state, env.cfg)
    assert 660.0 < float(d[0]) < 720.0
    # the way goes north toward the wall's end (on the grid, north-east is as short while x < 85):
    # (0.707, 0.707) toward the centre (65,115), not east (1, 0) into the wall
    assert float(unit[0, 1]) > 0.7
    obs = td["observation"][0]
    torch.testing.assert_close(obs[-6:-4], unit[0])  # the ego direction column is that way


def test_geodesic_progress_rewards_the_detour_not_the_wall():
    env = env_with((50.0, 100.0), cfg=GEO, ge_pos=[(170.0, 100.0)], ge_data=[1.0], **WALL)
    north, _ = step(env, env.reset(), (0.0, 1.0))
    south, _ = step(env, env.reset(), (0.0, -1.0))
    # 10 m north shortens the way round by about 10·300/304 m, 10 m south lengthens it about as
    # much, although both keep the straight-line distance to the GE almost unchanged
    want = 8 * 10 * 300 / math.hypot(50, 300) / 707  # 0.1116
    assert progress(north) == pytest.approx(want, abs=0.03)
    assert progress(south) == pytest.approx(-want, abs=0.03)


def test_geodesic_off_the_grid_keys_only_when_used():
    assert "geo_field" not in UAVEnv(SHAPED, batch_size=[1], seed=0).reset()["state"].keys()
    env = UAVEnv(GEO, batch_size=[2], seed=0)
    td = env.rollout(3, break_when_any_done=False)
    assert td["state", "geo_field"].shape == (2, 3, 16, 50 * 50)  # 15 GEs + LA, 50 x 50 cells
    from torchrl.envs.utils import check_env_specs

    check_env_specs(env, seed=0)


def test_following_the_geodesic_direction_never_enters_a_zone():
    # The direction column alone, flown at full speed over 16 saved evaluation scenarios, never
    # meets a BZ or NFZ: the way keeps the clearance, and a DCU that came closer heads for a free
    # cell (following the fill of blocked cells used to cut zone corners: 18 entries in 32
    # scenarios before that rule)
    from pathlib import Path

    from uavlae.envs.scenario import load_scenarios

    sc = load_scenarios(Path(__file__).parents[1] / "results" / "eval_set_32.json")[:16]
    env = UAVEnv(GEO, batch_size=[len(sc)], seed=1, scenarios=sc)
    td = env.reset()
    alive = torch.ones(len(sc), dtype=torch.bool)
    entered = 0
    for _ in range(1000):
        td["action"] = td["observation"][:, -6:-4]
        out = env.step(td)
        nxt = out["next"]
        hit = (nxt["events", "bz_collision"] | nxt["events", "nfz_entry"]).squeeze(-1)
        entered += int((hit & alive).sum())
        alive &= ~nxt["done"].squeeze(-1)
        if not alive.any():
            break
        td = env.step_mdp(out)
    assert entered == 0


# An NFZ 12 m from the east edge: x in [400, 488], y in [150, 300]. The GE at (495, 225), the centre
# of cell (49, 22), lies in the 12 m wide corridor between the NFZ and the edge.
CORRIDOR = dict(nfz=[(400.0, 150.0, 488.0, 300.0)], ge_pos=[(495.0, 225.0)], ge_data=[1.0])


def _field_at(cfg, p):
    from uavlae.envs.geodesic import geodesic_lookup

    env = env_with(p, cfg=cfg, **CORRIDOR)
    td = env.reset()
    state = {k: v for k, v in td["state"].items()}
    return float(geodesic_lookup(state["geo_field"], state["position"], env.cfg)[0, 0])


def test_clearance_walls_cut_a_corridor_ge_off():
    # progress_clearance_cost 0 (the default): every cell of the corridor column x = 495 is within
    # 12 m of the NFZ (7 m from its east side; (495, 305) is sqrt(7² + 5²) = 8.6 m from its corner),
    # so from the free cell (495, 315) the GE reads unreachable (the field's "far" value)
    from uavlae.envs.geodesic import _BIG

    assert _field_at(GEO, (495.0, 315.0)) >= _BIG


def test_clearance_cost_opens_the_corridor_at_k_times_the_step():
    # progress_clearance_cost 10: cells within d_min = 5 m stay walls (the column x = 485 is 3 m from
    # the NFZ), the corridor column x = 495 costs 10 x 10 m per cell. From the GE's cell (225) north
    # to (305): 8 corridor cells, 8·100 = 800; then the free cell (315): + 10 m -> 810 m
    cfg = {**GEO, "reward": {**GEO["reward"], "progress_clearance_cost": 10.0}}
    assert _field_at(cfg, (495.0, 315.0)) == pytest.approx(810.0, abs=1e-3)
    assert _field_at(cfg, (495.0, 305.0)) == pytest.approx(800.0, abs=1e-3)
    # and the direction column points down the corridor (south), not back out of it
    from uavlae.envs.geodesic import geodesic_target

    env = env_with((495.0, 305.0), cfg=cfg, **CORRIDOR)
    state = {k: v for k, v in env.reset()["state"].items()}
    _, unit, _ = geodesic_target(state, env.cfg)
    torch.testing.assert_close(unit[0], torch.tensor([0.0, -1.0]))


def test_clearance_cost_between_zero_and_one_is_refused():
    with pytest.raises(ValueError, match="progress_clearance_cost"):
        make_env_config({"reward": {"progress_clearance_cost": 0.5}})


def test_geodesic_step_compiles_and_agrees_with_eager():
    eager = UAVEnv(GEO, batch_size=[4], seed=0)
    comp = UAVEnv(GEO, batch_size=[4], seed=0, compile_step=True)
    a, b = eager.reset(), comp.reset()
    g = torch.Generator().manual_seed(0)
    for _ in range(4):
        act = torch.rand(4, 2, generator=g) * 2 - 1
        a["action"], b["action"] = act, act.clone()
        oa, a = eager.step_and_maybe_reset(a)
        ob, b = comp.step_and_maybe_reset(b)
        torch.testing.assert_close(ob["next", "observation"], oa["next", "observation"], atol=1e-5, rtol=0)
        torch.testing.assert_close(ob["next", "reward"], oa["next", "reward"], atol=1e-5, rtol=0)
