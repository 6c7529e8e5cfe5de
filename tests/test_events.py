"""Events, termination and reward terms of one slot on hand-made scenarios, through UAVEnv.

Defaults (SPEC): v_max 10, v_limit 5, v_land 1, t_fly = t_hover = 1, sigma = [8, .4, .4, .4, .6,
.4, .6, 1, .01], d_min 5, d_safe 15, landing bonus 10, crash penalty 10, LA = [475,500]x[0,25].
"""

import pytest
import torch

from uavlae.envs import UAVEnv
from uavlae.envs.scenario import Scenario

FAR_GE = dict(ge_pos=[(250.0, 450.0)], ge_data=[1.0])  # far from every test site: data remains


def one_step(start, action, cfg=None, **zones):
    kw = dict(nfz=[], rz=[], bz=[], ou_pos=[], ou_vel=[], **FAR_GE)
    kw.update(zones)
    env = UAVEnv(cfg, batch_size=[1], seed=0, scenarios=[Scenario(start=start, **kw)])
    td = env.reset()
    td["action"] = torch.tensor([action], dtype=torch.float32)
    return env.step(td)["next"]


def ev(out, name):
    return bool(out["events", name].item())


def term(out, name):
    return float(out["reward_terms", name].item())


def test_leaving_the_area_clips_and_flags_without_ending():
    out = one_step((5.0, 250.0), (-1.0, 0.0))  # would fly to x = -5
    assert ev(out, "boundary_exit")
    torch.testing.assert_close(out["state", "position"], torch.tensor([[0.0, 250.0]]))
    assert term(out, "r6") == pytest.approx(-0.4)  # -sigma6 outside A
    assert not out["done"].item()
    assert float(out["cost"].item()) == pytest.approx(1.0)  # boundary-exit weight 1


def test_near_boundary_ramp_inside():
    # ends at x = 10: ramp = (15 - 10) / (15 - 5) = 0.5 -> r6 = -0.4 * 0.5
    out = one_step((20.0, 250.0), (-1.0, 0.0))
    assert not ev(out, "boundary_exit")
    assert term(out, "r6") == pytest.approx(-0.2)


RZ = [(100.0, 100.0, 200.0, 200.0)]


@pytest.mark.parametrize(
    "start, action, speeding, r5",
    [
        ((150.0, 150.0), (1.0, 0.0), True, -0.6),  # inside, 10 m/s: excess (10-5)/(10-5) = 1
        ((150.0, 150.0), (0.75, 0.0), True, -0.3),  # inside, 7.5 m/s: excess 0.5
        ((150.0, 150.0), (0.5, 0.0), False, 0.0),  # inside at exactly v_limit: legal
        ((95.0, 150.0), (1.0, 0.0), True, -0.6),  # segment 95 -> 105 enters the RZ
        ((150.0, 300.0), (1.0, 0.0), False, 0.0),  # outside every RZ: any speed
    ],
)
def test_speeding_only_inside_rz(start, action, speeding, r5):
    out = one_step(start, action, rz=RZ)
    assert ev(out, "rz_speeding") is speeding
    assert term(out, "r5") == pytest.approx(r5, abs=1e-5)
    assert not out["done"].item()  # a violation, not an end


@pytest.mark.parametrize(
    "start, action, with_data, landed",
    [
        ((480.0, 10.0), (0.05, 0.0), True, True),  # inside LA at 0.5 m/s
        ((480.0, 10.0), (0.5, 0.0), True, False),  # inside LA but 5 m/s with data left
        ((480.0, 10.0), (0.5, 0.0), False, True),  # 5 m/s but every GE is done
        ((400.0, 10.0), (0.05, 0.0), True, False),  # slow, but outside LA
    ],
)
def test_landing_only_inside_la_and_slow_or_done(start, action, with_data, landed):
    ge = FAR_GE if with_data else dict(ge_pos=[], ge_data=[])
    out = one_step(start, action, **ge)
    assert ev(out, "landed") is landed
    assert bool(out["terminated"].item()) is landed
    assert term(out, "landing") == pytest.approx(10.0 if landed else 0.0)


def test_building_collision_between_end_points_ends_with_crash_penalty():
    # the segment (100, 99) -> (107.07, 106.07) (line y = x - 1) enters the building's west
    # side at (105, 104) and leaves its top at (106, 105): it clips the corner (105, 105) while
    # both end points are outside
    bz = [(105.0, 80.0, 150.0, 105.0)]
    out = one_step((100.0, 99.0), (0.7071, 0.7071), bz=bz)
    assert ev(out, "bz_collision")
    assert bool(out["terminated"].item())
    assert term(out, "crash") == pytest.approx(-10.0)
    assert float(out["cost"].item()) == pytest.approx(1.0)


def test_segment_passing_above_the_corner_is_clear():
    # line y = x + 4 passes (105, 109): 4 m above the corner (105, 105)
    out = one_step((100.0, 104.0), (0.7071, 0.7071), bz=[(105.0, 80.0, 150.0, 105.0)])
    assert not ev(out, "bz_collision") and not out["done"].item()


def test_collision_does_not_end_when_configured():
    bz = [(105.0, 80.0, 150.0, 105.0)]
    out = one_step((100.0, 99.0), (0.7071, 0.7071), cfg={"terminate_on_collision": False}, bz=bz)
    assert ev(out, "bz_collision") and not out["done"].item()
    assert term(out, "crash") == 0.0


def test_nfz_entry_flags():
    out = one_step((95.0, 150.0), (1.0, 0.0), nfz=[(100.0, 100.0, 200.0, 200.0)])
    assert ev(out, "nfz_entry") and bool(out["terminated"].item())
    # inside the NFZ, distance 0 <= d_min: r4 = -sigma4 * 1
    assert term(out, "r4") == pytest.approx(-0.4)


def test_ou_crossing_mid_slot_collides():
    # DCU flies (200,200) -> (210,200); an OU flies (205,195) -> (205,205) and crosses its path
    # at t = 0.5 s, when both are at (205, 200). End points are 7.07 m apart.
    env = UAVEnv({"ou": {"p_turn": 0.0}}, batch_size=[1], seed=0, scenarios=[Scenario(
        start=(200.0, 200.0), ou_pos=[(205.0, 195.0)], ou_vel=[(0.0, 10.0)], **FAR_GE)])
    td = env.reset()
    td["action"] = torch.tensor([[1.0, 0.0]])
    out = env.step(td)["next"]
    assert ev(out, "ou_collision") and bool(out["terminated"].item())


def test_energy_exhaustion_ends_the_episode():
    # E_limit 300 J < one hover slot (336.97 J)
    out = one_step((250.0, 250.0), (0.0, 0.0), cfg={"energy": {"e_limit": 300.0}})
    assert ev(out, "energy_exhausted") and bool(out["terminated"].item())
    assert float(out["state", "energy_left"].item()) == pytest.approx(300.0 - 336.97, abs=0.01)


def test_data_collection_and_r1():
    # hover right above a GE with 2 units: SNR 36, rate log2(37) = 5.209 > 2, so TD = 2 in one slot
    out = one_step((300.0, 300.0), (0.0, 0.0), ge_pos=[(300.0, 300.0)], ge_data=[2.0])
    assert float(out["state", "slot_data"].item()) == pytest.approx(2.0)
    assert float(out["state", "data_collected"].item()) == pytest.approx(2.0)
    assert term(out, "r1") == pytest.approx(8.0)
    assert term(out, "r9") == pytest.approx(-0.01)
