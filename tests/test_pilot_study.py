"""The pilot study's records and report (uavlae/experiments/pilot.py) on hand-made records."""

import csv
import math

import pytest

from uavlae.experiments.advice import EPISODE_COLUMNS
from uavlae.experiments.pilot import CURVE_SCALARS, EPISODE_KEYS, build, meets, write_records


def _write(path, rows, fields):
    with path.open("w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=fields)
        w.writeheader()
        w.writerows(rows)


def test_floors():
    ok = {"DCR": 0.96, "SLR": 0.91, "CR": 0.0, "RVR": 0.0, "ECR": 0.07}
    assert meets(ok, 0.075) and not meets(ok, 0.06)  # ECR above the greedy heuristic's
    assert not meets({**ok, "CR": 0.03}, None) and not meets({**ok, "SLR": 0.89}, None)
    assert not meets({**ok, "RVR": float("nan")}, None)


def test_unfinished_runs_of_earlier_roots_stay_listed_until_recorded(tmp_path):
    """The records span several run folders: a run left unfinished under an earlier root stays in
    unfinished.csv, unless the records now hold it finished; this root's unfinished runs join it,
    once each however often the records are written."""
    out, root = tmp_path / "records", tmp_path / "runs"
    out.mkdir()
    _write(out / "unfinished.csv", [{"path": "pilot/screen/a/seed1"}, {"path": "pilot/screen/b/seed2"}], ["path"])
    _write(out / "runs.csv", [{"stage": "screen", "rung": "b", "seed": "2"}], ["stage", "rung", "seed"])
    (root / "pilot/screen/c/seed3").mkdir(parents=True)
    (root / "pilot/screen/c/seed3/config.json").write_text("{}")  # no final metrics: unfinished
    for _ in range(2):
        assert write_records(root, out)["unfinished"] == 2
    with (out / "unfinished.csv").open() as fh:
        assert [r["path"] for r in csv.DictReader(fh)] == ["pilot/screen/a/seed1", "pilot/screen/c/seed3"]
    with (out / "runs.csv").open() as fh:
        assert [(r["rung"], r["seed"]) for r in csv.DictReader(fh)] == [("b", "2")]


def test_report_from_records_alone(tmp_path):
    """Two rungs, seeds 100 and 101, two scenarios each (data 1 a scenario, E_total 10).
    Rung `plain` alone collects scenario 0 only and crashes in scenario 1: DCR 0.5, CR 0.5; its
    pilot (through the filter) collects both, lands in both and never crashes: DCR 1, SLR 1, CR 0.
    Rung `ego` alone collects and lands everywhere, and so does its pilot. So the ego actor alone
    gains ΔDCR +0.5 on plain's: the bootstrap draws the same scenarios for both, and plain's
    resampled DCR is 0 (both scenarios 1), 0.5 or 1 (both 0): the interval of the difference is
    [0, 1]. Energy 1 of 10 in every episode: ECR 0.1; the greedy heuristic's is 0.05, so neither
    pilot meets the ECR floor... except on the curves, where `ego` seed 100 meets every floor at
    its second evaluation (ECR 0.04), at 200,000 frames and 600 s of training (10 min)."""
    eps, runs, curves = [], [], []
    for rung, alone, pilot in (("plain", (1, 0), (1, 1)), ("ego", (1, 1), (1, 1))):
        for seed in (100, 101):
            runs.append({"stage": "screen", "rung": rung, "seed": seed, "frames": 1000, "wall_s": 1200.0,
                         "train_intervention": 0.25, "eval_intervention": 0.125})
            drawn = (("pilot_sample", (1, 0)),) if rung == "plain" else ()
            for ev, got in (("alone", alone), ("pilot", pilot), ("heuristic", (1, 1)), ("random", (0, 0)), *drawn):
                for n in (0, 1):
                    crash = ev == "alone" and got[n] == 0
                    eps.append({"stage": "screen", "rung": rung, "seed": seed, "evaluation": ev, "set": "selection",
                                "scenario": n, "data_collected": got[n], "data_total": 1, "collided": crash,
                                "landed": bool(got[n]), "rz_speeding": False,
                                "energy_used": 0.5 if ev == "heuristic" else 1.0, "energy_total": 10.0,
                                "boundary_exit": False, "length": 10})
            for step, ecr in ((100_000, 0.3), (200_000, 0.04)):
                curves.append({"stage": "screen", "rung": rung, "seed": seed, "frames": step,
                               "train_wall_s": 3 * step / 1000, "DCR": 1.0, "SLR": 1.0, "CR": 0.0, "RVR": 0.0,
                               "ECR": ecr if (rung, seed) == ("ego", 100) else 0.3})
    _write(tmp_path / "runs.csv", runs, list(runs[0]))
    _write(tmp_path / "episodes.csv", eps, [*EPISODE_KEYS, *EPISODE_COLUMNS])
    _write(tmp_path / "curves.csv", curves, ["stage", "rung", "seed", "frames", *[c for _, c in CURVE_SCALARS]])
    text = build(tmp_path).read_text()
    rows = {tuple(c.strip() for c in line.split("|")[1:4]): line for line in text.splitlines() if line.startswith("| ")}
    plain_alone = rows[("plain", "100 101", "actor alone")]
    assert "| 0.500 [0.000, 1.000] | 0.500 [0.000, 1.000] | 0.500 [0.000, 1.000] | 0.000 [0.000, 0.000] | 0.100" in plain_alone
    plain_pilot = rows[("plain", "100 101", "actor + filter")]
    assert "| 1.000 [1.000, 1.000] | 0.000 [0.000, 0.000] | 1.000 [1.000, 1.000] |" in plain_pilot
    assert "0.250 / 0.125" in plain_pilot and "| 20 |" in plain_pilot and "not reached (2 runs)" in plain_pilot
    assert "seed 100: 200,000 frames, 10 min" in rows[("ego", "100 101", "actor + filter")]
    # both evaluations score DCR + SLR - CR - RVR = 2: the earlier is the best on the way
    assert "seed 100: 1.000 / 1.000 at 100,000; seed 101: 1.000 / 1.000 at 100,000" in rows[("ego", "100 101", "actor + filter")]
    assert "| ego vs plain | actor alone | 0.500 [0.000, 1.000] |" in text
    assert "| ego vs plain | actor + filter | 0.000 [0.000, 0.000] |" in text
    assert "| heuristic | 1.000 [1.000, 1.000] |" in text and "| random | 0.000 [0.000, 0.000] |" in text
    with pytest.raises(KeyError):
        rows[("ego", "100 101", "held-out")]
    # plain's networks flown by draws collect and land in scenario 0 only: DCR 0.5, SLR 0.5, and
    # against their mean action (both everywhere) ΔDCR = ΔSLR = -0.5, resampled -1, -0.5 or 0
    assert "| 0.500 [0.000, 1.000] | 0.000 [0.000, 0.000] | 0.500 [0.000, 1.000] |" in rows[
        ("plain", "100 101", "actor (a draw) + filter")]
    drawn = rows[("plain", "100 101", "through the filter")]
    assert drawn.startswith("| plain | 100 101 | through the filter | -0.500 [-1.000, 0.000] | 0.000 [0.000, 0.000] | "
                            "-0.500 [-1.000, 0.000] |")
    assert ("ego", "100 101", "through the filter") not in rows


def test_a_rung_that_flies_draws_is_paired_with_its_parents_draws(tmp_path):
    """Rung `plain` flies its mean action (both scenarios collected and landed) and, flown by draws
    (make pilot-sampling), collects and lands in scenario 0 only. Rung `drawn` flies draws in its
    own evaluations (eval_actor sample) and collects and lands in both. Its difference from plain
    pairs draws with draws: ΔDCR = ΔSLR = +0.5 (resampled 0, 0.5 or 1: [0, 1]), not 0 against
    plain's mean; its rows say it flies draws."""
    eps, runs = [], []
    for rung, mode, cells in (("plain", "mean", (("pilot", (1, 1)), ("pilot_sample", (1, 0)))),
                              ("drawn", "sample", (("pilot", (1, 1)),))):
        for seed in (100, 101):
            runs.append({"stage": "screen", "rung": rung, "seed": seed, "frames": 1000, "wall_s": 60.0,
                         "eval_actor": mode})
            # and each run's kept pilot on the screening set: plain's lands in neither scenario
            wide = (("pilot", "screening", (0, 0) if rung == "plain" else (1, 1)),)
            for ev, which, got in (*((ev, "selection", got) for ev, got in cells), *wide):
                for n in (0, 1):
                    eps.append({"stage": "screen", "rung": rung, "seed": seed, "evaluation": ev, "set": which,
                                "scenario": n, "data_collected": got[n], "data_total": 1, "collided": False,
                                "landed": bool(got[n]), "rz_speeding": False, "energy_used": 1.0,
                                "energy_total": 10.0, "boundary_exit": False, "length": 10})
    _write(tmp_path / "runs.csv", runs, list(runs[0]))
    _write(tmp_path / "episodes.csv", eps, [*EPISODE_KEYS, *EPISODE_COLUMNS])
    _write(tmp_path / "curves.csv", [], ["stage", "rung", "seed", "frames", *[c for _, c in CURVE_SCALARS]])
    text = build(tmp_path).read_text()
    assert "| drawn vs plain | actor (a draw) + filter | 0.500 [0.000, 1.000] | 0.000 [0.000, 0.000] | " \
           "0.500 [0.000, 1.000] |" in text
    assert "| drawn | 100 101 | actor (a draw) + filter | 1.000 [1.000, 1.000] |" in text
    assert "| plain | 100 101 | actor + filter | 1.000 [1.000, 1.000] |" in text
    # the screening set has its own section, its pairs on its own scenarios: ΔDCR = ΔSLR = +1
    section = text.split("## screen: the screening set (results/pilot/screen_set_256.json), each run's kept pilot")[1]
    assert "| drawn vs plain | actor (a draw) + filter | 1.000 [1.000, 1.000] |" in section.split("\n## ")[0]


def test_model_card_from_records_alone(tmp_path):
    """The verdict's rung `pilot`, seeds 0 and 1, two held-out scenarios of data 1 each. Seed 0's
    pilot collects and lands in both: DCR = SLR = 1. Seed 1's collects and lands in scenario 0
    only: DCR = SLR = 0.5. Pooled: 3/4 = 0.75. The bootstrap draws seeds and scenarios: both
    draws of seed 1 and of scenario 1 (1/4 x 1/4 = 6.25% > 2.5%) give 0, either draw doubled on
    the 0 side (7/16) gives 1, so the interval is [0, 1]; seed 0 alone is 1 [1, 1]. Energy 2 of
    10 kJ everywhere: ECR 0.2. Runs of 50 and 70 min.
    The gate: the greedy heuristic (held-out, 1 of 10 kJ: ECR 0.1) collects and lands
    everywhere, uniform random nowhere (DCR 0 [0, 0]). Pooled DCR and SLR 0.75 miss their floors
    (0.95, 0.90), CR and RVR 0 meet theirs, ECR 0.2 misses greedy's 0.1, and the actor alone (as
    the pilot) has a DCR interval from 0, not above random's upper 0; two seeds of five make it
    provisional."""
    from uavlae.errors import InputError
    from uavlae.experiments.pilot import card

    eps, runs = [], []
    for seed, got in ((0, (1, 1)), (1, (1, 0))):
        runs.append({"stage": "verdict", "rung": "pilot", "seed": seed, "frames": 2500000,
                     "wall_s": 3000.0 + 1200.0 * seed, "commit": "abc123",
                     "best_frames": 2000000 + 100000 * seed})
        for ev in ("pilot", "alone"):
            for n in (0, 1):
                eps.append({"stage": "verdict", "rung": "pilot", "seed": seed, "evaluation": ev, "set": "heldout",
                            "scenario": n, "data_collected": got[n], "data_total": 1, "collided": False,
                            "landed": bool(got[n]), "rz_speeding": False, "energy_used": 2000.0,
                            "energy_total": 10000.0, "boundary_exit": False, "length": 10})
    for ref, got, energy in (("greedy", 1, 1000.0), ("random", 0, 3000.0)):
        for n in (0, 1):
            eps.append({"stage": "references", "rung": ref, "seed": 0, "evaluation": "alone", "set": "heldout",
                        "scenario": n, "data_collected": got, "data_total": 1, "collided": False,
                        "landed": bool(got), "rz_speeding": False, "energy_used": energy,
                        "energy_total": 10000.0, "boundary_exit": False, "length": 10})
    # the confirmation set: both seeds' pilots collect and land everywhere on 1.5 of 10 kJ (ECR
    # 0.15), greedy on 2 kJ (0.2): every floor met there (no actor alone or random flown on it)
    for who, seed, energy in (("pilot", 0, 1500.0), ("pilot", 1, 1500.0), ("greedy", 0, 2000.0)):
        for n in (0, 1):
            stage, ev = ("verdict", "pilot") if who == "pilot" else ("references", "alone")
            eps.append({"stage": stage, "rung": who, "seed": seed, "evaluation": ev, "set": "confirm",
                        "scenario": n, "data_collected": 1, "data_total": 1, "collided": False, "landed": True,
                        "rz_speeding": False, "energy_used": energy, "energy_total": 10000.0,
                        "boundary_exit": False, "length": 10})
    recipe = tmp_path / "pilot.yaml"
    recipe.write_text("# @package _global_\nsafety_filter:\n  mode: train_and_deploy\n")
    with pytest.raises(InputError, match="no finished run of stage 'verdict'"):
        _write(tmp_path / "runs.csv", [{**runs[0], "stage": "screen"}], list(runs[0]))
        _write(tmp_path / "episodes.csv", [], [*EPISODE_KEYS, *EPISODE_COLUMNS])
        card(tmp_path, recipe, rung="pilot")
    _write(tmp_path / "runs.csv", runs, list(runs[0]))
    _write(tmp_path / "episodes.csv", eps, [*EPISODE_KEYS, *EPISODE_COLUMNS])
    text = card(tmp_path, recipe, rung="pilot").read_text()
    assert "  mode: train_and_deploy" in text and "from commit abc123" in text and "50-70 min" in text
    assert "2,500,000 frames on seeds 0 1" in text and "seed 0: 2,000,000, seed 1: 2,100,000 frames" in text
    heldout = text.split("On the 256 scenarios of the confirmation set")[0]  # the held-out set's table comes first
    rows = {tuple(c.strip() for c in line.split("|")[1:3]): line for line in heldout.splitlines() if line.startswith("| pilot")}
    assert "| 0.750 [0.000, 1.000] | 0.000 [0.000, 0.000] | 0.750 [0.000, 1.000] | 0.000 [0.000, 0.000] | 0.200" in \
        rows[("pilot, actor + filter", "0 1")]
    assert "| 1.000 [1.000, 1.000] | 0.000 [0.000, 0.000] | 1.000 [1.000, 1.000] |" in rows[("pilot, actor + filter", "0")]
    assert ("pilot, actor alone", "0") in rows and "no RZ speeding" in text
    assert ("Judged on 2 of the 5 verdict seeds: provisional until all have run. **Gate not met**: DCR 0.750; "
            "SLR 0.750; ECR 0.200 against greedy's 0.100; the actor alone's DCR (lower 0.000, random's upper "
            "0.000); the actor alone's SLR (lower 0.000, random's upper 0.000).") in text
    assert "| pilot CR <= 0.02 | 0.000 | yes |" in text and "| pilot DCR >= 0.95 | 0.750 | no |" in text
    assert "| pilot ECR <= greedy's 0.100 | 0.200 | no |" in text
    # 2 kJ of 10 in each of 4 pilot episodes: ECR 0.2, 0.05 of it in the one of four that did not
    # land; 2 kJ a landed mission, greedy's 1 kJ
    assert ("Where the pilot's ECR (0.200) goes: 0.050 of it in the 25.0% of episodes that did not land; "
            "a landed mission used 2.0 kJ on average, the greedy heuristic's 1.0 kJ.") in text
    confirm = text.split("## The gate (confirmation set)")[1]
    assert "## The gate (held-out set)" in text.split("## The gate (confirmation set)")[0]
    assert confirm.lstrip().startswith("Judged on 2 of the 5 verdict seeds: provisional until all have run. **Gate met.**")
    assert "| pilot ECR <= greedy's 0.200 | 0.150 | yes |" in confirm
    assert "On the 256 scenarios of the confirmation set" in text


def test_mission_pace_by_hand():
    """chunk 2 slots, still 5 m. Row 0 lands after 4 slots from (0, 0), (0, 0), (0, 10), (0, 20):
    path 0 + 10 + 10 = 20 m; its chunks move 0 m (held) and 10 m: 2 held slots. Row 1 does not
    land (ignored). Row 2 lands after 3 slots from (0, 0), (3, 4), (6, 8): path 10 m; its one whole
    chunk moves 5 m, not below 5: none held (the last, one-slot chunk is not counted). Landed:
    (4 + 3) / 2 = 3.5 slots, (20 + 10) / 2 = 15 m, 30 m / 7 slots = 4.2857 m a slot, (2 + 0) / 2 = 1
    held slot."""
    import torch

    from uavlae.experiments.pilot import mission_pace

    positions = torch.tensor([
        [[0.0, 0.0], [0.0, 0.0], [0.0, 0.0]],
        [[0.0, 0.0], [0.0, 0.0], [3.0, 4.0]],
        [[0.0, 10.0], [0.0, 0.0], [6.0, 8.0]],
        [[0.0, 20.0], [0.0, 0.0], [100.0, 100.0]],
    ])
    found = mission_pace(positions, torch.tensor([4, 4, 3]), torch.tensor([True, False, True]), chunk=2, still=5.0)
    assert found == {"landed_slots_mean": 3.5, "landed_path_m_mean": pytest.approx(15.0),
                     "landed_m_per_slot": pytest.approx(30 / 7), "landed_held_slots_mean": 1.0, "chunk": 2}
    nobody = mission_pace(positions, torch.tensor([4, 4, 3]), torch.tensor([False, False, False]))
    assert math.isnan(nobody["landed_m_per_slot"])


def test_mission_pace_by_place_by_hand():
    """The flights of test_mission_pace_by_hand. Row 0's slots 2 and 3 (from (0, 10) and (0, 20))
    start over an RZ, its slots 1 and 2 near a wall: slot 2 goes to the first place named, the RZ.
    So RZ: 2 slots for row 0, none for row 2, (2 + 0) / 2 = 1 a landed mission; of their moves only
    slot 2's is recorded (slot 3 is row 0's last): 10 m a slot. Near a wall: slot 1 (10 m), 0.5 a
    mission, 10 m a slot. Elsewhere: row 0's slot 0 (0 m) and row 2's three slots, moves 5 and 5
    m: (1 + 3) / 2 = 2 a mission, 10 m / 3 moves. The unlanded row 1, marked everywhere, counts
    nowhere."""
    import torch

    from uavlae.experiments.pilot import landed_mean, mission_pace

    positions = torch.tensor([
        [[0.0, 0.0], [0.0, 0.0], [0.0, 0.0]],
        [[0.0, 0.0], [0.0, 0.0], [3.0, 4.0]],
        [[0.0, 10.0], [0.0, 0.0], [6.0, 8.0]],
        [[0.0, 20.0], [0.0, 0.0], [100.0, 100.0]],
    ])
    rz = torch.tensor([[False, True, False], [False, True, False], [True, True, False], [True, True, False]])
    wall = torch.tensor([[False, True, False], [True, True, False], [True, True, False], [False, True, False]])
    lengths, landed = torch.tensor([4, 4, 3]), torch.tensor([True, False, True])
    found = mission_pace(positions, lengths, landed, chunk=2, still=5.0, places={"rz": rz, "near_wall": wall})
    assert found["landed_rz_slots_mean"] == 1.0 and found["landed_rz_m_per_slot"] == pytest.approx(10.0)
    assert found["landed_near_wall_slots_mean"] == 0.5 and found["landed_near_wall_m_per_slot"] == pytest.approx(10.0)
    assert found["landed_elsewhere_slots_mean"] == 2.0
    assert found["landed_elsewhere_m_per_slot"] == pytest.approx(10 / 3)
    # every slot somewhere: the places add up to the mission
    assert sum(found[f"landed_{n}_slots_mean"] for n in ("rz", "near_wall", "elsewhere")) == found["landed_slots_mean"]
    # a speed a slot: row 0 flies 1, 2, 3, 4 m/s, row 2 (3 slots) 6 m/s, row 1 (unlanded) 100:
    # (1 + 2 + 3 + 4 + 6 + 6 + 6) / 7 = 4
    speeds = torch.tensor([[1.0, 100.0, 6.0], [2.0, 100.0, 6.0], [3.0, 100.0, 6.0], [4.0, 100.0, 100.0]])
    assert landed_mean(speeds, lengths, landed) == pytest.approx(4.0)
    assert math.isnan(landed_mean(speeds, lengths, torch.tensor([False, False, False])))
    nobody = mission_pace(positions, lengths, torch.tensor([False, False, False]), places={"rz": rz})
    assert math.isnan(nobody["landed_rz_m_per_slot"]) and math.isnan(nobody["landed_elsewhere_slots_mean"])


def test_stall_summary_by_hand():
    """Three rows, window 2. Row 0 lands after 2 slots, the filter changing its wish by 0.2 m/s
    each. Row 1 flies 4 slots, ends at (11, 10), 1 m west of the NFZ [12, 0, 20, 20], and does
    not move over its last 2 slots (net 0 m) while the filter changes its wish by 1 m/s: at an
    obstacle and held. Row 2 flies 30 m a slot far from every obstacle (net 30 m over its last
    2 slots), unchanged. So 2 unlanded, 1 at an obstacle and held; the median filter change over
    the unlanded rows' windows is (1 + 0) / 2 = 0.5; the landed row's mean over its flight 0.2."""
    import torch

    from uavlae.experiments.pilot import stall_summary

    positions = torch.tensor([
        [[0.0, 0.0], [10.0, 10.0], [100.0, 100.0]],
        [[1.0, 0.0], [10.0, 10.0], [130.0, 100.0]],
        [[9.0, 9.0], [11.0, 10.0], [160.0, 100.0]],
        [[9.0, 9.0], [11.0, 10.0], [190.0, 100.0]],
    ])
    changes = torch.tensor([[0.2, 0.0, 0.0], [0.2, 0.0, 0.0], [5.0, 1.0, 0.0], [5.0, 1.0, 0.0]])
    nfz = torch.tensor([[12.0, 0.0, 20.0, 20.0]]).expand(3, 1, 4)
    bz = torch.zeros(3, 1, 4)
    found = stall_summary(positions, changes, torch.tensor([2, 4, 4]), torch.tensor([True, False, False]),
                          [(bz, torch.zeros(3, 1, dtype=torch.bool)), (nfz, torch.ones(3, 1, dtype=torch.bool))],
                          window=2)
    assert found == {"episodes": 3, "unlanded": 2, "unlanded_at_obstacle": 1, "unlanded_held": 1,
                     "unlanded_filter_change_median": pytest.approx(0.5), "landed_filter_change_mean": pytest.approx(0.2),
                     "window": 2}


def test_the_cards_full_speed_line():
    """ECR 0.117 as flown, 0.092 at full speed, greedy 0.072: the wished speed costs
    (0.117 - 0.092) / (0.117 - 0.072) = 0.025 / 0.045 = 56% of the energy above greedy's."""
    from uavlae.experiments.pilot import _full_speed_line

    m = {"DCR": 0.975, "CR": 0.0, "SLR": 0.914, "RVR": 0.0}
    found = {"set": "s.json", "as_flown": {**m, "ECR": 0.117}, "at_full_speed": {**m, "SLR": 0.961, "ECR": 0.092}}
    line = _full_speed_line(found, 0.072)
    assert "ECR 0.117 as it flies, 0.092 at full speed" in line and "SLR 0.914 / 0.961" in line
    assert line.endswith("Greedy flies ECR 0.072 there: the wished speed costs 56% of the pilot's energy above greedy's.")
    assert _full_speed_line(found).endswith("CR 0.000 / 0.000.")  # no greedy on record: no share


def test_the_cards_stall_and_pace_lines():
    """The card's sentences from stalls.json: a pilot whose every episode landed says so (no
    median of nothing); the pace line rounds 330.09 slots to 330, 2356.6 m to 2357, 7.139 m a
    slot to 7.1 against greedy's 232.6 -> 233, 2137.7 -> 2138, 9.19 -> 9.2."""
    from uavlae.experiments.pilot import _pace_line, _stalls_line

    found = {"actor": "p.pt2", "scenario": "s.json", "episodes": 32, "unlanded": 0, "unlanded_at_obstacle": 0,
             "unlanded_held": 0, "unlanded_filter_change_median": math.nan, "landed_filter_change_mean": 0.19,
             "window": 200, "landed_slots_mean": 330.09, "landed_path_m_mean": 2356.6, "landed_m_per_slot": 7.139,
             "landed_held_slots_mean": 21.9, "chunk": 50, "greedy_landed": 30, "greedy_landed_slots_mean": 232.6,
             "greedy_landed_path_m_mean": 2137.7, "greedy_landed_m_per_slot": 9.19, "greedy_landed_held_slots_mean": 3.3}
    assert _stalls_line(found).endswith("nowhere; every one of its 32 episodes landed.")
    assert _pace_line(found).startswith(
        "Its landed missions took 330 slots on average (greedy's 233): a path of 2357 m (greedy's 2138) at 7.1 m a "
        "slot (greedy's 9.2), 22 slots of them held (chunks of 50 slots with under 20 m of net motion; greedy's 3).")
    assert "residential" not in _pace_line(found)  # a stalls.json written before the split says nothing of it
    split = {**found, "landed_rz_slots_mean": 37.74, "landed_rz_m_per_slot": 4.28, "landed_near_wall_slots_mean": 60.2,
             "landed_near_wall_m_per_slot": 5.16, "landed_elsewhere_slots_mean": 188.6,
             "landed_elsewhere_m_per_slot": 9.21, "greedy_landed_rz_slots_mean": 29.16,
             "greedy_landed_rz_m_per_slot": 4.70, "greedy_landed_near_wall_slots_mean": 0.0,
             "greedy_landed_near_wall_m_per_slot": math.nan, "greedy_landed_elsewhere_slots_mean": 197.9,
             "greedy_landed_elsewhere_m_per_slot": 9.73, "landed_wish_speed_mean": 8.57, "landed_speed_mean": 7.65}
    assert _pace_line(split).endswith(
        " Of those slots, 38 at 4.3 m a slot (greedy: 29 at 4.7 m a slot) start over a residential zone (limit 5 m/s), "
        "60 at "
        "5.2 m a slot (greedy: none) within 5 m of a building or no-fly zone, and 189 at 9.2 m a slot (greedy: "
        "198 at 9.7 m a slot) elsewhere. Its actor wishes 8.6 m/s on average over those slots and the filter lets it fly 7.7.")

    held = {**found, "unlanded": 4, "unlanded_at_obstacle": 3, "unlanded_held": 2, "unlanded_filter_change_median": 1.0}
    assert "of its 4 episodes of 32 that did not land, 3 ended within 3 m" in _stalls_line(held)
    assert _stalls_line(held).endswith("the filter keeps it out.")  # 1.0 > 2 x 0.19
