"""benchmarks/advice_quality.py's scoring: the env's own step from a saved state, numbers by hand."""

from __future__ import annotations

import sys
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))

import advice_quality as aq  # noqa: E402

from uavlae.envs import UAVEnv, make_env_config  # noqa: E402
from uavlae.envs.world import current_target  # noqa: E402


def _states(n: int = 40):
    state, meta, _ = aq.load_states(aq.STATES)
    return state[:n], meta


def test_saved_states_are_triggered_and_balanced():
    state, meta = _states(200)
    cfg = make_env_config(None)
    d = aq._distances(state, cfg.safety.perception_radius)
    assert state.batch_size[0] == 200 and bool((d.amin(-1) <= meta["d_th"]).all())
    assert {k: meta["kind"].count(k) for k in aq.KINDS} == {"bz": 50, "nfz": 50, "rz": 50, "ou": 50}


def test_hover_makes_no_progress_and_straight_at_the_target_gains_v_t():
    state, _ = _states()
    cfg = make_env_config(None)
    n = state.batch_size[0]
    env = UAVEnv(cfg, batch_size=n, seed=0)
    hover = aq.score(env, state, torch.zeros(n, 2), hold=3, seed=0)
    assert torch.equal(hover["progress_1_m"], torch.zeros(n)) and torch.equal(hover["progress_H_m"], torch.zeros(n))
    vec, d0, _ = current_target(dict(state.items()))
    toward = vec / d0.clamp(min=1e-9)[:, None]  # unit vector: |v| = v_max, a = v / v_max
    go = aq.score(env, state, toward, hold=1, seed=0)
    step = cfg.motion.v_max * cfg.motion.t_fly  # 10 m in one 1 s slot
    clear = (go["any_violation_1"] == 0) & (d0 > step)
    assert clear.sum() >= 10
    torch.testing.assert_close(go["progress_1_m"][clear], torch.full((int(clear.sum()),), step), atol=1e-3, rtol=0)


def test_the_same_seed_gives_every_advisor_the_same_draws():
    state, _ = _states()
    n = state.batch_size[0]
    env = UAVEnv(make_env_config(None), batch_size=n, seed=0)
    a = torch.rand(n, 2, generator=torch.Generator().manual_seed(1)) * 2 - 1
    one, two = aq.score(env, state, a, 3, seed=5), aq.score(env, state, a, 3, seed=5)
    assert all(torch.equal(one[k], two[k]) for k in one)


def test_parroting_counts_answers_equal_to_the_papers_example():
    # actions are v / v_max with v_max = 10: (0.42, 0.16) is the example's (4.2, 1.6) m/s
    acts = [[0.42, 0.16], [0.42, 0.16], [0.42, -0.16], [0.0, 0.0], [0.42, 0.16]]
    assert aq.paper_example_flags(acts, 10.0) == [1.0, 1.0, 0.0, 0.0, 1.0]
    assert aq.top_answer_share(acts) == 3 / 5
    assert aq.paper_example_flags([[0.84, 0.32]], 5.0) == [1.0]  # the same speed at another v_max


def test_paired_interval_is_of_the_difference_state_by_state():
    a = [0.0, 1.0, 2.0, 3.0]
    mean, lo, hi = aq.paired(a, [x + 0.5 for x in a])  # every state gains 0.5: no spread at all
    assert (mean, lo, hi) == (0.5, 0.5, 0.5)
    mean, lo, hi = aq.paired([0.0] * 4, [1.0, -1.0, 1.0, -1.0])
    assert mean == 0.0 and -1.0 <= lo < 0.0 < hi <= 1.0
