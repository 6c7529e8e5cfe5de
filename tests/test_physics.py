"""Unit tests of uavlae.envs.physics against hand-computed numbers (docs/model.md §2-§7).

Defaults used throughout: H = 10 m, alpha = 0.36, TP = 0.01 W, N = 1e-6, tau = 3.6,
v_max = 10 m/s, t_fly = t_hover = 1 s, d_min = 5 m, d_safe = 15 m, sigma = [8, .4, .4, .4, .6, .4, .6, 1, .01].
"""

from __future__ import annotations

import math

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from uavlae.envs import physics as ph
from uavlae.envs.config import CostConfig, EnvConfig, OUConfig, make_env_config

CFG = EnvConfig()
E, M, CH = CFG.energy, CFG.motion, CFG.channel
D_MIN, D_SAFE = CFG.safety.d_min, CFG.safety.d_safe
X, Y = CFG.area.x_size, CFG.area.y_size
INF = math.inf

fast = settings(max_examples=60, deadline=None)
finite = st.floats(-1e3, 1e3, allow_nan=False, allow_infinity=False)


def t(*v, dtype=torch.float64):
    return torch.tensor(v, dtype=dtype)


# ----------------------------------------------------------------------------- ramp


def test_ramp_hand_values():
    # (15 - d) / (15 - 5) clipped to [0, 1]: d=0,5 -> 1; 10 -> 0.5; 12.5 -> 0.25; 15, 20, inf -> 0
    d = t(0.0, 5.0, 10.0, 12.5, 15.0, 20.0, INF)
    assert torch.allclose(ph.ramp(d, D_MIN, D_SAFE), t(1.0, 1.0, 0.5, 0.25, 0.0, 0.0, 0.0))


@fast
@given(st.floats(0, 1e6))
def test_ramp_in_unit_interval(d):
    r = ph.ramp(t(d), D_MIN, D_SAFE)
    assert 0.0 <= float(r) <= 1.0


# ----------------------------------------------------------------------------- motion


def test_action_to_velocity_hand_values():
    # (0.3,-0.4) -> (3,-4); (1,1) -> (10,10) with norm 14.142 -> scaled to (7.0711, 7.0711);
    # (2, 0) clamps to (1, 0) -> (10, 0); (0.6, 0.8) -> (6, 8), norm exactly 10, unchanged
    a = torch.tensor([[0.3, -0.4], [1.0, 1.0], [2.0, 0.0], [0.6, 0.8], [0.0, 0.0]], dtype=torch.float64)
    s = 10.0 / math.sqrt(2.0)
    want = torch.tensor([[3.0, -4.0], [s, s], [10.0, 0.0], [6.0, 8.0], [0.0, 0.0]], dtype=torch.float64)
    assert torch.allclose(ph.action_to_velocity(a, M.v_max), want)


@fast
@given(finite, finite)
def test_action_to_velocity_norm_bounded(ax, ay):
    v = ph.action_to_velocity(t(ax, ay), M.v_max)
    assert float(torch.linalg.vector_norm(v)) <= M.v_max * (1 + 1e-12)


# ----------------------------------------------------------------------------- energy


def test_propulsion_power_hand_values():
    # P0 = 0.012/8 * 1.225 * 0.05 * 0.503 * 300^3 * 0.4^3 = 79.856 W
    # Pi = 1.1 * 20^1.5 / sqrt(2 * 1.225 * 0.503) = 98.387 / 1.1101 = 88.628 W
    # P(0) = P0 + Pi = 168.48 W
    # P(10): a = 100 / (2 * 4.03^2) = 3.07865; sqrt(sqrt(1 + a^2) - a) = sqrt(3.23698 - 3.07865) = 0.39792
    #   blade 79.856 * (1 + 300/14400) = 81.520; induced 88.628 * 0.39792 = 35.266;
    #   parasite 0.5 * 0.6 * 1.225 * 0.05 * 0.503 * 1000 = 9.243 -> 126.03 W
    p = ph.propulsion_power(t(0.0, 10.0), E)
    assert float(p[0]) == pytest.approx(168.48, abs=0.005)
    assert float(p[1]) == pytest.approx(126.03, abs=0.005)


@fast
@given(st.floats(0, 200))
def test_propulsion_power_positive(v):
    assert float(ph.propulsion_power(t(v), E)) > 0
    assert float(ph.propulsion_power(t(v, dtype=torch.float32), E)) > 0


def test_slot_energy_hand_values():
    # hover: P(0)*1 + P(0)*1 = 2 * 168.484 = 336.97 J; at 10 m/s: 126.029 + 168.484 = 294.51 J
    e = ph.slot_energy(t(0.0, 10.0), E, M)
    assert float(e[0]) == pytest.approx(336.97, abs=0.005)
    assert float(e[1]) == pytest.approx(294.51, abs=0.005)


def test_min_return_energy_hand_values():
    # ceil(d / (10 * 1)) * 294.513: d=0 -> 0; d=10 -> 1 slot; d=10.5 -> 2; d=25 -> 3 -> 883.54 J
    e = ph.min_return_energy(t(0.0, 10.0, 10.5, 25.0), E, M)
    assert torch.allclose(e, t(0.0, 294.513, 589.027, 883.540), atol=0.01)


# ----------------------------------------------------------------------------- channel and TDMA


def test_channel_hand_values():
    # SNR = TP * alpha / d^2 / N = 0.01 * 0.36 / 1e-6 / d^2 = 3600 / d^2, d^2 = g^2 + 10^2
    # g=0: d^2=100 -> G=0.0036, SNR=36, B=log2(37)=5.20945
    # g=10: d^2=200 -> SNR=18, B=log2(19)=4.24793
    # g=20: d^2=500 -> SNR=7.2, B=log2(8.2)=3.03562
    # g=30: d^2=1000 -> SNR=3.6 (= tau, served), B=log2(4.6)=2.20163
    # g=31: d^2=1061 -> SNR=3.3930 < 3.6, not served
    dcu = t(100.0, 100.0)
    ge = torch.tensor([[100.0, 100.0], [110.0, 100.0], [100.0, 80.0], [130.0, 100.0], [100.0, 131.0]],
                      dtype=torch.float64)
    snr, rate = ph.channel(dcu, ge, CFG.area.altitude, CFG.ge.tx_power, CH)
    assert torch.allclose(snr, t(36.0, 18.0, 7.2, 3.6, 3.393025), atol=1e-5)
    assert torch.allclose(rate, t(5.20945, 4.24793, 3.03562, 2.20163, math.log2(1 + 3600 / 1061)), atol=1e-5)
    assert (snr >= CH.snr_threshold).tolist() == [True, True, True, True, False]


def test_channel_gain_at_zero_ground_distance_float32():
    dcu = torch.tensor([0.0, 0.0])
    snr, rate = ph.channel(dcu, torch.zeros(1, 2), 10.0, 0.01, CH)
    # G = 0.36 / 100 = 0.0036; SNR = 0.01 * 0.0036 / 1e-6 = 36
    assert float(snr[0]) == pytest.approx(36.0, rel=1e-6)
    assert float(rate[0]) == pytest.approx(math.log2(37.0), rel=1e-6)
    # the 30 m edge must stay served in float32 too
    snr30, _ = ph.channel(dcu, torch.tensor([[30.0, 0.0]]), 10.0, 0.01, CH)
    assert bool(snr30[0] >= CH.snr_threshold)


def _serve_case(dv):
    # GE0 at 0 m (best rate 5.209) has no data -> skipped; GE1 at 10 m (rate 4.248) has data;
    # GE2 at 0 m with data but absent -> skipped; GE3 at 20 m (rate 3.036) has data; GE4 at 31 m out of range
    dcu = t(200.0, 200.0)
    ge = torch.tensor([[200.0, 200.0], [210.0, 200.0], [200.0, 200.0], [200.0, 220.0], [231.0, 200.0]],
                      dtype=torch.float64)
    snr, rate = ph.channel(dcu, ge, CFG.area.altitude, CFG.ge.tx_power, CH)
    remaining = t(0.0, dv, 2.0, 1.0, 3.0)
    mask = torch.tensor([True, True, False, True, True])
    noise = t(0.1, 0.2, 0.3, 0.4, 0.5)
    return ph.serve_ge(snr, rate, remaining, mask, CH.snr_threshold, M.t_hover, noise)


def test_serve_ge_data_limited():
    # GE1 has DV=3 < B*t_hover = 4.248 -> TD = 3, DV1 -> 0
    td, served, rem = _serve_case(3.0)
    assert int(served) == 1
    assert float(td) == pytest.approx(3.0)
    assert torch.allclose(rem, t(0.0, 0.0, 2.0, 1.0, 3.0))


def test_serve_ge_rate_limited():
    # GE1 has DV=5 > B*t_hover = log2(19) = 4.24793 -> TD = 4.24793, DV1 -> 0.75207
    td, served, rem = _serve_case(5.0)
    assert int(served) == 1
    assert float(td) == pytest.approx(4.24793, abs=1e-5)
    assert torch.allclose(rem, t(0.0, 0.75207, 2.0, 1.0, 3.0), atol=1e-5)


def test_serve_ge_none_in_range():
    # only a GE at 31 m (SNR 3.393 < 3.6) has data -> no service, nothing changes
    dcu = t(0.0, 0.0)
    snr, rate = ph.channel(dcu, torch.tensor([[31.0, 0.0]], dtype=torch.float64), 10.0, 0.01, CH)
    rem = t(2.0)
    td, served, rem_new = ph.serve_ge(snr, rate, rem, torch.tensor([True]), CH.snr_threshold, M.t_hover, t(0.5))
    assert int(served) == -1 and float(td) == 0.0
    assert torch.equal(rem_new, rem)


def test_serve_ge_ties_broken_by_noise():
    # two GEs at the same distance (same rate): the one with the larger tie noise is served
    snr, rate = t(18.0, 18.0, 36.0), t(math.log2(19), math.log2(19), math.log2(37))
    rem = t(1.0, 1.0, 0.0)
    mask = torch.tensor([True, True, True])
    _, s1, _ = ph.serve_ge(snr, rate, rem, mask, 3.6, 1.0, t(0.9, 0.1, 0.99))
    _, s2, _ = ph.serve_ge(snr, rate, rem, mask, 3.6, 1.0, t(0.1, 0.9, 0.99))
    assert (int(s1), int(s2)) == (0, 1)


def test_serve_ge_batched_and_empty():
    snr = torch.full((2, 3, 4), 10.0)
    rate = torch.arange(24, dtype=torch.float32).reshape(2, 3, 4) / 10
    rem = torch.ones(2, 3, 4)
    mask = torch.ones(2, 3, 4, dtype=torch.bool)
    td, served, rem_new = ph.serve_ge(snr, rate, rem, mask, 3.6, 1.0, torch.zeros(2, 3, 4))
    assert td.shape == (2, 3) and served.shape == (2, 3) and served.dtype == torch.int64
    assert (served == 3).all()  # the last GE has the highest rate everywhere
    assert torch.allclose(td, torch.minimum(torch.ones(2, 3), rate[..., 3]))
    # G = 0
    e = torch.zeros(2, 0)
    td, served, rem_new = ph.serve_ge(e, e, e, e.bool(), 3.6, 1.0, e)
    assert td.shape == (2,) and (served == -1).all() and rem_new.shape == (2, 0)


# ----------------------------------------------------------------------------- rectangles

RECT = torch.tensor([[10.0, 10.0, 20.0, 20.0]], dtype=torch.float64)
ON = torch.tensor([True])


def test_point_in_rects_and_distance_hand_values():
    # rect [10,20]^2: (15,15) inside -> 0; (25,15) -> 5; (23,24) -> hypot(3,4) = 5; (20,20) corner -> inside, 0
    p = torch.tensor([[15.0, 15.0], [25.0, 15.0], [23.0, 24.0], [20.0, 20.0], [5.0, 15.0]], dtype=torch.float64)
    assert ph.point_in_rects(p, RECT, ON).squeeze(-1).tolist() == [True, False, False, True, False]
    assert torch.allclose(ph.point_rect_distance(p, RECT, ON).squeeze(-1), t(0.0, 5.0, 5.0, 0.0, 5.0))
    off = torch.tensor([False])
    assert not ph.point_in_rects(p, RECT, off).any()
    assert torch.isinf(ph.point_rect_distance(p, RECT, off)).all()


@fast
@given(st.floats(-50, 80), st.floats(-50, 80))
def test_distance_zero_iff_inside(x, y):
    p = t(x, y)
    d = ph.point_rect_distance(p, RECT, ON)
    inside = ph.point_in_rects(p, RECT, ON)
    assert bool(d[0] == 0) == bool(inside[0])


def test_nearest_distance():
    assert float(ph.nearest_distance(t(3.0, INF, 1.0))) == 1.0
    empty = ph.nearest_distance(torch.zeros(2, 3, 0))
    assert empty.shape == (2, 3) and torch.isinf(empty).all()
    assert torch.isinf(ph.nearest_distance(t(INF, INF)))


def _hit(p0, p1, rect=RECT, mask=ON):
    return bool(ph.segment_hits_rects(t(*p0), t(*p1), rect, mask)[0])


def test_segment_clips_corner_between_end_points():
    # y = x + 9 from (0,9) to (20,29): both ends outside, passes (10,19)-(11,20) inside the rect
    assert _hit((0.0, 9.0), (20.0, 29.0))
    assert not ph.point_in_rects(t(0.0, 9.0), RECT, ON).any()
    assert not ph.point_in_rects(t(20.0, 29.0), RECT, ON).any()
    # y = x + 11 passes the corner (10,20) at 1/sqrt(2) = 0.707 m: no hit
    assert not _hit((0.0, 11.0), (20.0, 31.0))
    # y = x + 10 touches the corner (10,20) exactly: touching counts
    assert _hit((0.0, 10.0), (20.0, 30.0))


def test_segment_axis_aligned_short_and_zero_length():
    assert _hit((0.0, 15.0), (30.0, 15.0))  # horizontal crossing (dy = 0)
    assert not _hit((0.0, 25.0), (30.0, 25.0))  # horizontal miss
    assert _hit((15.0, 0.0), (15.0, 30.0))  # vertical crossing (dx = 0)
    assert not _hit((0.0, 15.0), (9.0, 15.0))  # stops 1 m short
    assert _hit((0.0, 15.0), (10.0, 15.0))  # ends on the edge
    assert _hit((15.0, 15.0), (15.0, 15.0))  # zero length inside = point test
    assert not _hit((5.0, 5.0), (5.0, 5.0))
    assert _hit((20.0, 15.0), (20.0, 15.0))  # zero length on the edge
    assert not _hit((0.0, 15.0), (30.0, 15.0), mask=torch.tensor([False]))  # absent


@fast
@given(finite, finite, finite, finite)
def test_segment_hit_agrees_with_sampling(x0, y0, x1, y1):
    p0, p1 = t(x0, y0), t(x1, y1)
    hit = bool(ph.segment_hits_rects(p0, p1, RECT, ON)[0])
    s = torch.linspace(0, 1, 2001, dtype=torch.float64).unsqueeze(-1)
    pts = p0 + s * (p1 - p0)
    sampled = bool(ph.point_in_rects(pts, RECT, ON).any())
    if sampled:  # a sampled point inside implies a hit; a hit implies a point within a sample step
        assert hit
    if hit:
        step = float(torch.linalg.vector_norm(p1 - p0)) / 2000
        assert float(ph.point_rect_distance(pts, RECT, ON).min()) <= step + 1e-9


def test_segment_hits_broadcast_over_many_rects():
    rects = torch.tensor([[10.0, 10.0, 20.0, 20.0], [40.0, 0.0, 50.0, 5.0], [0.0, 0.0, 1.0, 1.0]])
    mask = torch.tensor([True, True, False])
    hits = ph.segment_hits_rects(torch.tensor([0.0, 2.0]), torch.tensor([60.0, 2.0]), rects, mask)
    assert hits.tolist() == [False, True, False]


# ----------------------------------------------------------------------------- area


def test_boundary_outside_clip():
    # A = [0,500]^2: (100,30) -> 30; (490,250) -> 10; (0,250) on the edge -> 0, inside; (-5,100) -> 0, outside
    p = torch.tensor([[100.0, 30.0], [490.0, 250.0], [0.0, 250.0], [-5.0, 100.0], [510.0, -3.0]])
    assert torch.allclose(ph.boundary_distance(p, X, Y), torch.tensor([30.0, 10.0, 0.0, 0.0, 0.0]))
    assert ph.outside_area(p, X, Y).tolist() == [False, False, False, True, True]
    want = torch.tensor([[100.0, 30.0], [490.0, 250.0], [0.0, 250.0], [0.0, 100.0], [500.0, 0.0]])
    assert torch.equal(ph.clip_to_area(p, X, Y), want)


# ----------------------------------------------------------------------------- OU closest approach


def test_closest_approach_crossing_mid_slot():
    # DCU (0,0) at (10,0); OU (5,-5) at (0,10). At s=0.5 both are at (5,0): distance 0.
    # Ends: s=0 |(-5,5)| = 7.07; s=1 DCU (10,0), OU (5,5) -> 7.07
    d = ph.closest_approach(t(0.0, 0.0), t(10.0, 0.0), t(5.0, -5.0).unsqueeze(0), t(0.0, 10.0).unsqueeze(0), 1.0)
    assert float(d[0]) == pytest.approx(0.0, abs=1e-9)
    assert math.hypot(5, 5) > 7


def test_closest_approach_parallel_and_receding():
    q0 = torch.tensor([[0.0, 3.0], [-4.0, 0.0], [30.0, 0.0]], dtype=torch.float64)
    u = torch.tensor([[10.0, 0.0], [-10.0, 0.0], [0.0, 0.0]], dtype=torch.float64)
    # same velocity, 3 m apart -> 3; receding from 4 m behind -> min at s=0 -> 4;
    # static OU 30 m ahead, DCU flies 10 m -> min at s=1 -> 20
    d = ph.closest_approach(t(0.0, 0.0), t(10.0, 0.0), q0, u, 1.0)
    assert torch.allclose(d, t(3.0, 4.0, 20.0))


@fast
@given(finite, finite, finite, finite, st.floats(-10, 10), st.floats(-10, 10))
def test_closest_approach_below_end_points(px, py, qx, qy, vx, uy):
    p0, v = t(px, py), t(vx, 0.0)
    q0, u = t(qx, qy).unsqueeze(0), t(0.0, uy).unsqueeze(0)
    d = float(ph.closest_approach(p0, v, q0, u, 1.0)[0])
    start = float(torch.linalg.vector_norm(p0 - q0[0]))
    end = float(torch.linalg.vector_norm(p0 + v - q0[0] - u[0]))
    assert d <= min(start, end) + 1e-9


# ----------------------------------------------------------------------------- OU motion

BLOCKED = torch.tensor([[100.0, 100.0, 250.0, 200.0], [300.0, 300.0, 400.0, 450.0], [0.0, 0.0, 0.0, 0.0]])
BLOCKED_MASK = torch.tensor([True, True, False])


def _ou_init(batch, k, seed):
    g = torch.Generator().manual_seed(seed)
    pos = torch.stack([torch.rand(batch, k, generator=g) * 90 + 5, torch.rand(batch, k, generator=g) * 400 + 50], -1)
    heading = torch.rand(batch, k, generator=g) * 2 * math.pi
    speed = torch.rand(batch, k, generator=g) * M.v_max
    vel = torch.stack([speed * heading.cos(), speed * heading.sin()], -1)
    return pos, vel


def _run_ous(seed, steps, ou=CFG.ou):
    pos, vel = _ou_init(8, 5, 0)
    mask = torch.ones(8, 5, dtype=torch.bool)
    mask[:, -1] = False
    blocked = BLOCKED.expand(8, -1, -1)
    bmask = BLOCKED_MASK.expand(8, -1)
    g = torch.Generator().manual_seed(seed)
    traj = [(pos, vel)]
    for _ in range(steps):
        new_pos, new_vel = ph.ou_step(pos, vel, mask, blocked, bmask, X, Y, ou, M, g)
        assert not ph.segment_hits_rects(pos, new_pos, blocked.unsqueeze(-3), bmask.unsqueeze(-2)).any()
        pos, vel = new_pos, new_vel
        traj.append((pos, vel))
    return traj, mask


def test_ou_step_stays_free_and_inside():
    traj, mask = _run_ous(seed=1, steps=300)
    blocked = BLOCKED.expand(8, -1, -1)
    bmask = BLOCKED_MASK.expand(8, -1)
    for pos, vel in traj:
        assert not ph.outside_area(pos, X, Y).any()
        assert not ph.point_in_rects(pos, blocked.unsqueeze(-3), bmask.unsqueeze(-2)).any()
        assert (torch.linalg.vector_norm(vel, dim=-1) <= M.v_max + 1e-4).all()
    # absent OUs never move; present ones do
    assert torch.equal(traj[-1][0][:, -1], traj[0][0][:, -1])
    assert torch.equal(traj[-1][1][:, -1], traj[0][1][:, -1])
    assert not torch.equal(traj[-1][0][:, :-1], traj[0][0][:, :-1])


def test_ou_step_deterministic_for_equal_seeds():
    a, _ = _run_ous(seed=7, steps=40)
    b, _ = _run_ous(seed=7, steps=40)
    c, _ = _run_ous(seed=8, steps=40)
    assert all(torch.equal(pa, pb) and torch.equal(va, vb) for (pa, va), (pb, vb) in zip(a, b))
    assert not torch.equal(a[-1][0], c[-1][0])


def test_ou_step_hovers_when_boxed_in():
    # in a 2 x 2 m area every move at 10 m/s leaves A: all tries fail -> hover, velocity 0
    ou = OUConfig(p_turn=0.0)
    g = torch.Generator().manual_seed(0)
    pos, vel = torch.tensor([[1.0, 1.0]]), torch.tensor([[10.0, 0.0]])
    e = torch.zeros(0, 4)
    new_pos, new_vel = ph.ou_step(pos, vel, torch.tensor([True]), e, e[:, 0].bool(), 2.0, 2.0, ou, M, g)
    assert torch.equal(new_pos, pos) and torch.equal(new_vel, torch.zeros(1, 2))


def test_ou_step_free_move_and_turn():
    # p_turn = 0, nothing in the way: L' = L + v * t_fly exactly, velocity kept
    g = torch.Generator().manual_seed(0)
    pos, vel = torch.tensor([[100.0, 100.0]]), torch.tensor([[3.0, -4.0]])
    e = torch.zeros(0, 4)
    p, v = ph.ou_step(pos, vel, torch.tensor([True]), e, e[:, 0].bool(), X, Y, OUConfig(p_turn=0.0), M, g)
    assert torch.equal(p, torch.tensor([[103.0, 96.0]])) and torch.equal(v, vel)
    # p_turn = 1: a fresh speed in [0, v_max]
    p, v = ph.ou_step(pos, vel, torch.tensor([True]), e, e[:, 0].bool(), X, Y, OUConfig(p_turn=1.0), M, g)
    assert not torch.equal(v, vel) and float(torch.linalg.vector_norm(v)) <= M.v_max + 1e-5


def test_ou_step_redirects_before_a_wall():
    # OU heading east at 10 m/s, 5 m west of a building: the move is blocked, it turns (same speed) or hovers
    g = torch.Generator().manual_seed(3)
    pos, vel = torch.tensor([[95.0, 150.0]]), torch.tensor([[10.0, 0.0]])
    p, v = ph.ou_step(pos, vel, torch.tensor([True]), BLOCKED, BLOCKED_MASK, X, Y, OUConfig(p_turn=0.0), M, g)
    speed = float(torch.linalg.vector_norm(v))
    assert speed == pytest.approx(10.0, abs=1e-4) or speed == 0.0
    assert not ph.segment_hits_rects(pos, p, BLOCKED.unsqueeze(-3), BLOCKED_MASK.unsqueeze(-2)).any()


# ----------------------------------------------------------------------------- reward and cost


def _terms(cfg, **kw):
    base = dict(
        collected=torch.tensor(True), d_ou=t(10.0), d_bz=t(INF), d_nfz=t(5.0),
        rz_speeding_excess=t(0.5), d_boundary=t(12.5), outside=torch.tensor(False), d_la=t(70.7),
        all_collected=torch.tensor(False), energy_left=t(1000.0), e_min=t(2000.0),
        landed=torch.tensor(False), crashed=torch.tensor(True),
    )
    base.update(kw)
    return {k: float(v) for k, v in ph.reward_terms(**base, cfg=cfg).items()}


def test_reward_terms_hand_made_situation():
    r = _terms(CFG)
    # r1 = 8 (data collected); r2 = -0.4 * ramp(10) = -0.4 * 0.5 = -0.2; r3 = -0.4 * ramp(inf) = 0
    # r4 = -0.4 * ramp(5) = -0.4; r5 = -0.6 * 0.5 = -0.3; r6 = -0.4 * ramp(12.5) = -0.4 * 0.25 = -0.1
    # r7 corrected (E=1000 < E_min=2000): -0.6 * 70.7 / 707 = -0.06
    # r8 = -1 * (2000 - 1000) / 2000 = -0.5; r9 = -0.01; landing 0; crash -10
    want = dict(r1=8.0, r2=-0.2, r3=0.0, r4=-0.4, r5=-0.3, r6=-0.1, r7=-0.06, r8=-0.5, r9=-0.01,
                landing=0.0, crash=-10.0)
    assert r.keys() == want.keys()
    for k, v in want.items():
        assert r[k] == pytest.approx(v, abs=1e-9), k


def test_reward_r7_as_printed():
    cfg = make_env_config(reward={"r7_variant": "as_printed"})
    # -0.6 * (1 - 70.7/707) = -0.6 * 0.9 = -0.54, whatever the energy or the data
    assert _terms(cfg)["r7"] == pytest.approx(-0.54)
    assert _terms(cfg, energy_left=t(5000.0))["r7"] == pytest.approx(-0.54)
    # d_LA >= d_tar -> 0
    assert _terms(cfg, d_la=t(800.0))["r7"] == 0.0


def test_reward_r7_corrected_gating():
    # enough energy and data left -> 0; all collected at d_LA = 1000 -> -0.6 * min(1000, 707)/707 = -0.6
    assert _terms(CFG, energy_left=t(5000.0))["r7"] == 0.0
    assert _terms(CFG, energy_left=t(5000.0), all_collected=torch.tensor(True), d_la=t(1000.0))["r7"] == pytest.approx(-0.6)
    assert _terms(CFG, energy_left=t(5000.0), all_collected=torch.tensor(True), d_la=t(0.0))["r7"] == 0.0


def test_reward_outside_landing_and_no_flags():
    r = _terms(CFG, outside=torch.tensor(True), d_boundary=t(0.0), collected=torch.tensor(False),
               energy_left=t(2000.0), landed=torch.tensor(True), crashed=torch.tensor(False))
    # r6 = -sigma6 = -0.4 outside; r1 = 0; E = E_min -> r8 = 0; landing +10; crash 0
    assert r["r6"] == pytest.approx(-0.4) and r["r1"] == 0.0 and r["r8"] == 0.0
    assert r["landing"] == 10.0 and r["crash"] == 0.0
    # E_min = 0 (at LA) with E < 0: no division by zero
    r = _terms(CFG, energy_left=t(-5.0), e_min=t(0.0))
    assert r["r8"] == 0.0


def test_reward_terms_batched_shapes():
    b = (2, 3)
    kw = dict(
        collected=torch.zeros(b, dtype=torch.bool), d_ou=torch.full(b, INF), d_bz=torch.full(b, 3.0),
        d_nfz=torch.full(b, INF), rz_speeding_excess=torch.zeros(b), d_boundary=torch.full(b, 100.0),
        outside=torch.zeros(b, dtype=torch.bool), d_la=torch.full(b, 300.0),
        all_collected=torch.zeros(b, dtype=torch.bool), energy_left=torch.full(b, 8e5),
        e_min=torch.full(b, 1e4), landed=torch.zeros(b, dtype=torch.bool), crashed=torch.zeros(b, dtype=torch.bool),
    )
    r = ph.reward_terms(**kw, cfg=CFG)
    assert all(v.shape == b and v.dtype == torch.float32 for v in r.values())
    assert torch.allclose(r["r3"], torch.full(b, -0.4)) and torch.allclose(r["r9"], torch.full(b, -0.01))
    total = sum(r.values())
    assert torch.allclose(total, torch.full(b, -0.41))


def test_cost_weighted_sum():
    c = CostConfig(boundary_exit=1.0, ou_collision=2.0, bz_collision=3.0, nfz_entry=4.0)
    ev = {
        "boundary_exit": torch.tensor([True, False, False, True]),
        "ou_collision": torch.tensor([False, True, False, True]),
        "bz_collision": torch.tensor([False, False, False, True]),
        "nfz_entry": torch.tensor([False, True, False, True]),
        "rz_speeding": torch.tensor([True, True, True, True]),  # weight 0 by default: not in the paper's cost
    }
    # 1; 2 + 4 = 6; 0; 1 + 2 + 3 + 4 = 10
    assert torch.equal(ph.cost(ev, c), torch.tensor([1.0, 6.0, 0.0, 10.0]))
    assert torch.equal(ph.cost(ev, CostConfig()), torch.tensor([1.0, 2.0, 0.0, 4.0]))


def test_cost_counts_rz_speeding_only_with_a_weight():
    ev = {
        "boundary_exit": torch.tensor([True, False, False]),
        "ou_collision": torch.tensor([False, False, True]),
        "bz_collision": torch.tensor([False, False, False]),
        "nfz_entry": torch.tensor([False, False, False]),
        "rz_speeding": torch.tensor([True, True, False]),
    }
    assert CostConfig().rz_speeding == 0.0
    # the paper's cost: 1; 0; 1 (speeding ignored)
    assert torch.equal(ph.cost(ev, CostConfig()), torch.tensor([1.0, 0.0, 1.0]))
    # weight 0.5: 1 + 0.5 = 1.5; 0.5; 1
    assert torch.equal(ph.cost(ev, CostConfig(rz_speeding=0.5)), torch.tensor([1.5, 0.5, 1.0]))
    with pytest.raises(ValueError, match="rz_speeding"):
        make_env_config({"cost": {"rz_speeding": -1.0}})


# ----------------------------------------------------------------------------- batch shapes


@pytest.mark.parametrize("batch", [(), (3,), (2, 3)])
@pytest.mark.parametrize("z,k,g", [(2, 3, 4), (0, 0, 0)])
def test_batch_shapes(batch, z, k, g):
    gen = torch.Generator().manual_seed(0)
    p = torch.rand(*batch, 2) * 100
    v = ph.action_to_velocity(torch.rand(*batch, 2) * 2 - 1, M.v_max)
    assert v.shape == (*batch, 2)
    speed = torch.linalg.vector_norm(v, dim=-1)
    for f in (ph.propulsion_power(speed, E), ph.slot_energy(speed, E, M), ph.min_return_energy(speed, E, M),
              ph.ramp(speed, D_MIN, D_SAFE), ph.boundary_distance(p, X, Y), ph.outside_area(p, X, Y)):
        assert f.shape == batch
    assert ph.clip_to_area(p, X, Y).shape == (*batch, 2)

    ge = torch.rand(*batch, g, 2) * 100
    snr, rate = ph.channel(p, ge, 10.0, 0.01, CH)
    assert snr.shape == rate.shape == (*batch, g)
    td, served, rem = ph.serve_ge(snr, rate, torch.ones(*batch, g), torch.ones(*batch, g, dtype=torch.bool),
                                  3.6, 1.0, torch.rand(*batch, g))
    assert td.shape == served.shape == batch and rem.shape == (*batch, g)

    lo = torch.rand(*batch, z, 2) * 80
    rects = torch.cat([lo, lo + 10], -1)
    rmask = torch.ones(*batch, z, dtype=torch.bool)
    assert ph.point_in_rects(p, rects, rmask).shape == (*batch, z)
    dist = ph.point_rect_distance(p, rects, rmask)
    assert dist.shape == (*batch, z) and ph.nearest_distance(dist).shape == batch
    assert ph.segment_hits_rects(p, p + v, rects, rmask).shape == (*batch, z)

    q = torch.rand(*batch, k, 2) * 100
    u = torch.rand(*batch, k, 2)
    assert ph.closest_approach(p, v, q, u, 1.0).shape == (*batch, k)
    kmask = torch.ones(*batch, k, dtype=torch.bool)
    np_, nv = ph.ou_step(q, u, kmask, rects, rmask, X, Y, CFG.ou, M, gen)
    assert np_.shape == nv.shape == (*batch, k, 2)


def test_float64_dtype_preserved():
    p = torch.tensor([[10.0, 10.0]], dtype=torch.float64)
    gen = torch.Generator().manual_seed(0)
    e = torch.zeros(1, 0, 4, dtype=torch.float64)
    np_, nv = ph.ou_step(p.unsqueeze(1), p.unsqueeze(1) * 0, torch.ones(1, 1, dtype=torch.bool), e,
                         torch.zeros(1, 0, dtype=torch.bool), X, Y, CFG.ou, M, gen)
    assert np_.dtype == nv.dtype == torch.float64
    assert ph.point_rect_distance(p, e, torch.zeros(1, 0, dtype=torch.bool)).dtype == torch.float64
    assert ph.propulsion_power(p[..., 0], E).dtype == torch.float64


def test_observation_lists_visible_ous_nearest_first():
    from uavlae.envs import UAVEnv

    env = UAVEnv(batch_size=[1], seed=0)
    td = env.reset()
    s = {k: td["state", k].clone() for k in env.raw_state_keys}
    k, pr = env.layout.n_ou, env.cfg.safety.perception_radius
    s["position"] = torch.tensor([[100.0, 100.0]])
    pos = torch.full((1, k, 2), 400.0)  # far away: not visible
    pos[0, :5] = torch.tensor([[115.0, 100.0], [110.0, 100.0], [100.0, 120.0], [100.0, 90.0], [130.0, 100.0]])
    s["ou_pos"], s["ou_vel"] = pos, torch.arange(2.0 * k).view(1, k, 2)
    s["ou_mask"] = torch.ones(1, k, dtype=torch.bool)
    s["ou_mask"][0, 3] = False  # the one 10 m south is absent
    obs = env.layout.build(s)[0]
    start = 5 * env.layout.n_ge + 5 * sum(env.layout.n_zone)
    rel, vel, vis = obs[start : start + 2 * k], obs[start + 2 * k : start + 4 * k], obs[start + 4 * k : start + 5 * k]
    # by hand, within the 20 m radius: 10 m east (OU 1), 15 m east (OU 0), 20 m north (OU 2);
    # not 30 m east (OU 4); the rest zero
    assert pr == 20.0
    want_rel = [10.0, 0.0, 15.0, 0.0, 0.0, 20.0] + [0.0] * (2 * k - 6)
    torch.testing.assert_close(rel * pr, torch.tensor(want_rel), rtol=0, atol=1e-4)
    v_max = env.cfg.motion.v_max
    torch.testing.assert_close(vel * v_max, torch.tensor([2.0, 3.0, 0.0, 1.0, 4.0, 5.0] + [0.0] * (2 * k - 6)))
    assert vis.tolist() == [1.0, 1.0, 1.0] + [0.0] * (k - 3)
