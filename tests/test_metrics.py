"""Episode metrics (SPEC §5): aggregates by hand, the tracker on hand-made steps and real rollouts."""

import math

import pytest
import torch
from tensordict import TensorDict
from torchrl.envs import TransformedEnv

from uavlae.envs.config import EnvConfig
from uavlae.envs.metrics import (
    RECORD_COLUMNS,
    EpisodeMetrics,
    EpisodeTracker,
    aggregate,
    format_metrics,
    load_records,
    records_to_rows,
    rollout_metrics,
    save_records,
)
from uavlae.envs.physics import slot_energy
from uavlae.envs.scenario import Scenario
from uavlae.envs.uav_env import UAVEnv
from uavlae.envs.world import EVENT_KEYS, REWARD_KEYS

CFG = EnvConfig()


def _record(**kw):
    base = {k: 0 for k in RECORD_COLUMNS}
    base.update({k: False for k in ("collided", "boundary_exit", "rz_speeding", "landed")})
    base.update(energy_total=1e6, length=10)
    base.update(kw)
    return base


HAND = [
    _record(data_collected=2.0, data_total=4.0, collided=True, energy_used=1e5, **{"return": -5.0}),
    _record(data_collected=3.0, data_total=3.0, landed=True, rz_speeding=True, energy_used=2e5, **{"return": 20.0}),
    _record(data_collected=0.0, data_total=5.0, boundary_exit=True, energy_used=3e5, length=30, **{"return": -1.0}),
    _record(data_collected=1.0, data_total=2.0, landed=True, energy_used=1e5, **{"return": 6.0}),
]


def test_aggregate_hand_computed():
    agg = aggregate(HAND)
    assert agg["n_episodes"] == 4
    assert agg["DCR"] == pytest.approx(6.0 / 14.0)  # Σ collected / Σ total
    assert agg["CR"] == pytest.approx(1 / 4)
    assert agg["SLR"] == pytest.approx(2 / 4)
    assert agg["RVR"] == pytest.approx(1 / 4)
    assert agg["ECR"] == pytest.approx(7e5 / 4e6)  # Σ used / Σ E_total
    assert agg["boundary_exit_rate"] == pytest.approx(1 / 4)
    assert agg["mean_return"] == pytest.approx(5.0)
    assert agg["mean_length"] == pytest.approx(15.0)
    assert "| " in format_metrics(agg)


def test_aggregate_columns_equal_rows_and_empty_is_nan():
    cols = {k: torch.tensor([r[k] for r in HAND]) for k in HAND[0]}
    assert aggregate(cols) == pytest.approx(aggregate(HAND), nan_ok=True)
    empty = aggregate([])
    assert empty["n_episodes"] == 0 and math.isnan(empty["DCR"]) and math.isnan(empty["CR"])


@pytest.mark.parametrize("suffix", [".csv", ".json"])
def test_records_file_round_trip(tmp_path, suffix):
    cols = {k: torch.tensor([r[k] for r in HAND]) for k in HAND[0]}
    path = save_records(cols, tmp_path / f"rec{suffix}")
    back = load_records(path)
    assert aggregate(back) == pytest.approx(aggregate(HAND), nan_ok=True)
    assert len(records_to_rows(back)) == 4


def _step_td(b, reward, done, events=None, terms=None, data=(0.0, 0.0), total=(1.0, 1.0), energy=(0.0, 0.0)):
    """One hand-made "next" tensordict of a B-row env."""
    ev = {k: torch.zeros(b, 1, dtype=torch.bool) for k in EVENT_KEYS}
    for k, rows in (events or {}).items():
        ev[k] = torch.tensor(rows).reshape(b, 1)
    rt = {k: torch.zeros(b, 1) for k in REWARD_KEYS}
    for k, rows in (terms or {}).items():
        rt[k] = torch.tensor(rows, dtype=torch.float32).reshape(b, 1)
    done = torch.tensor(done).reshape(b, 1)
    return TensorDict(
        {
            "reward": torch.tensor(reward, dtype=torch.float32).reshape(b, 1),
            "cost": torch.zeros(b, 1),
            "events": ev,
            "reward_terms": rt,
            "done": done,
            "terminated": done.clone(),
            "truncated": torch.zeros(b, 1, dtype=torch.bool),
            "state": {
                "data_collected": torch.tensor(data),
                "data_total": torch.tensor(total),
                "energy_used": torch.tensor(energy),
            },
        },
        batch_size=[b],
    )


def test_tracker_accumulates_and_restarts_finished_rows():
    tr = EpisodeTracker(2, CFG)
    tr.update(_step_td(2, [1.0, 2.0], [False, False], events={"rz_speeding": [True, False]}, terms={"r9": [-0.5, -1.0]}))
    tr.update(_step_td(2, [3.0, 4.0], [True, False], events={"nfz_entry": [True, False], "landed": [False, False]},
                       data=(0.5, 0.0), total=(2.0, 1.0), energy=(700.0, 0.0)))
    assert tr.records()["row"].tolist() == [0]
    # row 0 restarted: this step belongs to its second episode
    tr.update(_step_td(2, [10.0, 5.0], [False, True], events={"landed": [False, True]},
                       data=(0.0, 1.0), total=(2.0, 1.0), energy=(300.0, 900.0)))
    rec = tr.records()
    assert rec["row"].tolist() == [0, 1]
    assert rec["length"].tolist() == [2, 3]
    torch.testing.assert_close(rec["return"], torch.tensor([4.0, 11.0]))
    torch.testing.assert_close(rec["term_r9"], torch.tensor([-0.5, -1.0]))
    assert rec["collided"].tolist() == [True, False] and rec["nfz_entry"].tolist() == [True, False]
    assert rec["rz_speeding"].tolist() == [True, False]
    assert rec["landed"].tolist() == [False, True]
    torch.testing.assert_close(rec["energy_used"], torch.tensor([700.0, 900.0]))
    torch.testing.assert_close(rec["data_collected"], torch.tensor([0.5, 1.0]))
    assert set(rec) == set(RECORD_COLUMNS)


# ---------------------------------------------------------------- real rollouts on known layouts

FAR_GE = dict(ge_pos=[(250.0, 250.0)], ge_data=[2.0], ou_pos=[], ou_vel=[])
# 1.2 m west of LA (x0 = 475); at 0.5 m/s the DCU is inside LA after 3 slots, slow enough to land.
LANDING = Scenario(nfz=[], rz=[], bz=[], start=(473.8, 12.5), **FAR_GE)
# 5 m west of a building; at 10 m/s the second flight segment crosses its west wall.
CRASH = Scenario(nfz=[], rz=[], bz=[(110.0, 200.0, 150.0, 300.0)], start=(95.0, 250.0), **FAR_GE)
SLOW_EAST, FAST_EAST = (0.05, 0.0), (1.0, 0.0)


def _fixed_policy(actions):
    a = torch.tensor(actions, dtype=torch.float32)

    def policy(td):
        td.set("action", a.clone())
        return td

    return policy


def test_rollout_metrics_landing_and_crash():
    env = UAVEnv(CFG, batch_size=[2], seed=0, scenarios=[LANDING, CRASH])
    records, agg, trajs = rollout_metrics(env, _fixed_policy([SLOW_EAST, FAST_EAST]))
    assert records["row"].tolist() == [0, 1]
    assert records["length"].tolist() == [3, 2]
    assert records["landed"].tolist() == [True, False]
    assert records["collided"].tolist() == [False, True]
    assert records["bz_collision"].tolist() == [False, True]
    assert agg["SLR"] == 0.5 and agg["CR"] == 0.5 and agg["DCR"] == 0.0 and agg["RVR"] == 0.0
    # energy: 3 slots at 0.5 m/s and 2 at 10 m/s, SPEC §4
    e = 3 * slot_energy(torch.tensor(0.5), CFG.energy, CFG.motion) + 2 * slot_energy(
        torch.tensor(10.0), CFG.energy, CFG.motion
    )
    assert agg["ECR"] == pytest.approx(float(e) / 2e6, rel=1e-5)
    assert records["term_landing"].tolist() == [CFG.reward.landing_bonus, 0.0]
    assert records["term_crash"].tolist() == [0.0, -CFG.reward.crash_penalty]
    assert [t.shape[0] for t in trajs] == [4, 3]
    torch.testing.assert_close(trajs[0][-1], torch.tensor([475.3, 12.5]))


def test_rollout_metrics_single_outcome_sets():
    env = UAVEnv(CFG, batch_size=[3], seed=0, scenarios=[LANDING])
    _, agg, _ = rollout_metrics(env, _fixed_policy([SLOW_EAST] * 3))
    assert agg["SLR"] == 1.0 and agg["CR"] == 0.0 and agg["n_episodes"] == 3
    env = UAVEnv(CFG, batch_size=[3], seed=0, scenarios=[CRASH])
    _, agg, _ = rollout_metrics(env, _fixed_policy([FAST_EAST] * 3))
    assert agg["CR"] == 1.0 and agg["SLR"] == 0.0


def test_rollout_metrics_random_policy_budget_truncates():
    env = UAVEnv(CFG, batch_size=[4], seed=3)
    records, agg, trajs = rollout_metrics(env, None, max_steps=5, generator=torch.Generator().manual_seed(1))
    assert agg["n_episodes"] == 4
    assert records["row"].tolist() == [0, 1, 2, 3]
    finished_early = records["length"] < 5
    assert (records["truncated"] | finished_early).all()
    assert all(t.shape[0] == int(n) + 1 for t, n in zip(trajs, records["length"]))


def test_transform_follows_partial_resets():
    # Row 0 lands every 3 slots, row 1 crashes every 2: the env auto-resets each row on its own.
    env = TransformedEnv(UAVEnv(CFG, batch_size=[2], seed=0, scenarios=[LANDING, CRASH]), EpisodeMetrics(CFG))
    td = env.rollout(10, _fixed_policy([SLOW_EAST, FAST_EAST]), break_when_any_done=False)
    assert td["next", "reward"].shape == (2, 10, 1)  # the transform changes no data
    rec = env.transform.records()
    rows = rec["row"].tolist()
    assert rows.count(0) == 3 and rows.count(1) == 5
    assert set(rec["length"][rec["row"] == 0].tolist()) == {3}
    assert set(rec["length"][rec["row"] == 1].tolist()) == {2}
    agg = env.transform.aggregate()
    assert agg["SLR"] == pytest.approx(3 / 8) and agg["CR"] == pytest.approx(5 / 8)
    # a fresh reset drops unfinished episodes; records are kept until clear()
    env.reset()
    assert env.transform.records()["row"].numel() == 8
    env.transform.clear()
    assert env.transform.records()["row"].numel() == 0


def test_demo_smoke(tmp_path, capsys):
    from uavlae.demo import main

    agg = main(["--batch", "4", "--seed", "2", "--max-steps", "20", "--out", str(tmp_path)])
    assert agg["n_episodes"] == 4
    assert (tmp_path / "demo_scenario.png").stat().st_size > 10_000
    assert len(load_records(tmp_path / "demo_records.csv")["row"]) == 4
    assert "DCR" in capsys.readouterr().out
