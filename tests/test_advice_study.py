"""The advice study's statistics and report, on numbers worked out by hand."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np
import pytest

from uavlae.experiments.advice_stats import (
    Grid,
    difference,
    grid_from_rows,
    interval,
    point,
    probability_of_improvement,
)


def _grid(landed, collected=None, total=None, seeds=None):
    landed = np.asarray(landed, dtype=float)
    S, N = landed.shape
    collected = np.asarray(collected if collected is not None else landed, dtype=float)
    total = np.asarray(total if total is not None else np.ones((S, N)), dtype=float)
    zeros = np.zeros((S, N))
    return Grid(seeds or list(range(S)), collected, total, zeros, landed, zeros, zeros + 1.0, zeros + 4.0)


def test_pooled_metrics_by_hand():
    """Two seeds x two scenarios: collected (1, 0 / 2, 1) of held (2, 2 / 2, 4): DCR = 4 / 10;
    landed 1, 0 / 1, 1: SLR = 3 / 4; energy 1 of 4 every episode: ECR = 0.25."""
    g = _grid([[1, 0], [1, 1]], collected=[[1, 0], [2, 1]], total=[[2, 2], [2, 4]])
    assert point(g, "DCR") == pytest.approx(0.4)
    assert point(g, "SLR") == pytest.approx(0.75)
    assert point(g, "ECR") == pytest.approx(0.25)
    assert point(g, "CR") == 0.0


def test_probability_of_improvement_by_hand():
    """x landed [[1, 0], [1, 1]], y [[0, 0], [1, 0]] (seeds x scenarios). Scenario 0: x {1, 1}
    against y {0, 1}: pairs 1, 0.5, 1, 0.5 -> 3/4. Scenario 1: x {0, 1} against y {0, 0}:
    0.5, 0.5, 1, 1 -> 3/4. P(X > Y) = 0.75; P(Y > X) = 0.25."""
    x, y = _grid([[1, 0], [1, 1]]), _grid([[0, 0], [1, 0]])
    p, lo, hi = probability_of_improvement(x, y, "SLR", n_boot=500)
    assert p == pytest.approx(0.75)
    assert 0.0 <= lo <= p <= hi <= 1.0
    assert probability_of_improvement(y, x, "SLR", n_boot=10)[0] == pytest.approx(0.25)
    # lower is better for CR: a cell that collides less is the better one
    a, b = _grid([[0, 0]]), _grid([[0, 0]])
    a.collided, b.collided = np.array([[0.0, 0.0]]), np.array([[1.0, 1.0]])
    assert probability_of_improvement(a, b, "CR", n_boot=10)[0] == 1.0


def test_intervals_stay_in_range_with_few_seeds():
    """Three seeds with SLR 1, 1, 0 on every scenario: a t interval would pass 1 and 0; the
    bootstrap's stays within [0, 1] and holds the point."""
    g = _grid([[1] * 8, [1] * 8, [0] * 8])
    p, lo, hi = interval(g, "SLR", n_boot=1000)
    assert p == pytest.approx(2 / 3)
    assert 0.0 <= lo < p < hi <= 1.0
    # nothing varies: the interval is the point
    assert interval(_grid([[1, 1], [1, 1]]), "SLR", n_boot=100) == (1.0, 1.0, 1.0)


def test_paired_difference_is_exact_when_cells_differ_by_a_constant():
    """y collects 0.1 of 1 less than x on every episode of the same seeds: every paired
    resample differs by exactly 0.1 in DCR, so the interval is [0.1, 0.1]."""
    rng = np.random.default_rng(0)
    c = rng.uniform(0.2, 0.8, size=(3, 10))
    x, y = _grid(np.zeros((3, 10)), collected=c), _grid(np.zeros((3, 10)), collected=c - 0.1)
    p, lo, hi = difference(x, y, "DCR", n_boot=300)
    assert (p, lo, hi) == pytest.approx((0.1, 0.1, 0.1))


def test_mean_over_settings_draws_the_seeds_once():
    """Two settings, one seed: landed on scenario 0 of 2 in the first, on both in the second. The
    mean SLR is (0.5 + 1) / 2 = 0.75; the first setting's replicate is 1, 0.5 or 0 (a quarter,
    a half, a quarter), the second's always 1, so the mean's interval is [0.5, 1]."""
    from uavlae.experiments.advice_stats import mean_interval

    p, lo, hi = mean_interval([_grid([[1, 0]]), _grid([[1, 1]])], "SLR")
    assert (p, lo, hi) == (0.75, 0.5, 1.0)
    with pytest.raises(ValueError, match="same seeds"):
        mean_interval([_grid([[1, 0]], seeds=[0]), _grid([[1, 1]], seeds=[1])], "SLR")


def test_grid_from_rows_needs_shared_scenarios():
    rows = [{"seed": s, "scenario": n, "data_collected": 1, "data_total": 2, "collided": "False", "landed": "True",
             "rz_speeding": "False", "energy_used": 1, "energy_total": 4} for s in (0, 1) for n in (0, 1)]
    g = grid_from_rows(rows)
    assert g.seeds == [0, 1] and point(g, "DCR") == 0.5 and point(g, "SLR") == 1.0
    with pytest.raises(ValueError, match="scenarios"):
        grid_from_rows(rows[:-1])


def _write(path, rows):
    with path.open("w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)


def test_report_from_records_alone(tmp_path):
    """Plain SAC neither collects nor lands; SAC+Heuristic (teach) collects everything and lands
    in both scenarios, on seeds 0 and 1: the differences are 1 whatever the resample, it beats
    plain SAC in every pair (P = 1), and it learned (random never collects); plain SAC did not.
    The LLM through the student answered 20 and 40 rows of 100 on its two seeds: 30% of the
    advised rows on average, 30 LLM rows a run, 2,000 / 200 tokens and 15 minutes of waiting a
    run; its runs took 40 minutes against plain SAC's 10: 4.00x. Against SAC+Heuristic under the
    override it collects scenario 0 only: ΔDCR -0.5, and the bootstrap draws both scenarios 1
    (-1) or both 0 (0) a quarter of the time each, so the interval is [-1, 0]: not shown.
    Plain SAC also ran seed 2, collecting and landing everywhere (its pooled DCR 1/3): against it
    the others are set on seeds 0 and 1 only, which they share, so the differences stay 1; against
    all three of plain SAC's seeds they would be 2/3."""
    eps, runs = [], []
    for method, transfer, landed in (("sac", "override", (0, 0)), ("sac_heuristic", "teach", (1, 1)),
                                     ("sac_heuristic", "override", (1, 1)), ("sac_llm_amortized", "override", (1, 0))):
        llm = method == "sac_llm_amortized"
        for seed in (0, 1, 2) if method == "sac" else (0, 1):
            runs.append({"world": "aid", "transfer": transfer, "method": method, "seed": seed, "sweep": "advice",
                         "frames": 1000, "wall_s": 2400.0 if llm else 600.0,
                         "override/advised": "" if method == "sac" else 100,
                         # the with-advisor evaluation: 500 of the LLM rung's 2,000 triggered rows advised
                         "advised/override/advised": 500 if llm else "", "advised/override/triggered": 2000 if llm else "",
                         # of those 500, the LLM answered 50 and the student 450: 10%
                         "advised/override/source/llm": 50 if llm else "",
                         "advised/override/source/student": 450 if llm else "",
                         "cost/rows_llm": 20 + 20 * seed if llm else "", "cost/wait_s": 600 + 600 * seed if llm else "",
                         "cost/llm_calls": 20 if llm else "", "cost/llm_cache_hits": 20 * seed if llm else "",
                         "cost/tokens_in": 1000 + 2000 * seed if llm else "",
                         "cost/tokens_out": 100 + 200 * seed if llm else "",
                         "advisor": {"sac": "none", "sac_heuristic": "heuristic/greedy",
                                     "sac_llm_amortized": "llm"}[method],
                         "clone_weight": 0.4, "commit": "abc", "dirty": "False", "machine": "cpu, 2 cores",
                         "override/advised_fraction": "" if method == "sac" else 0.25,
                         "override/trigger_rate": "" if method == "sac" else 0.3,
                         "amortize": str(method == "sac_llm_amortized"),
                         "override/source/llm": 20 + 20 * seed if method == "sac_llm_amortized" else "",
                         "override/source/student": 80 - 20 * seed if method == "sac_llm_amortized" else ""})
            for ev, land in (("alone", (1, 1) if seed == 2 else landed), ("random", (0, 0))):
                for n in (0, 1):
                    eps.append({"world": "aid", "transfer": transfer, "method": method, "seed": seed, "sweep": "advice",
                                "evaluation": ev, "scenario": n, "data_collected": land[n], "data_total": 1,
                                "collided": "False", "landed": str(bool(land[n])), "rz_speeding": "False",
                                "energy_used": 1, "energy_total": 4, "boundary_exit": "False", "length": 10})
    _write(tmp_path / "runs.csv", runs)
    _write(tmp_path / "episodes.csv", eps)
    from uavlae.experiments.advice_report import build

    build(tmp_path)
    text = (tmp_path / "report.md").read_text()
    assert "| sac_heuristic / teach | 0 1 | 1.000 [1.000, 1.000] | 1.00 [1.00, 1.00] | 1.000 [1.000, 1.000] |" in text
    learned = [line for line in text.splitlines() if line.startswith("| sac_heuristic / teach | 1.000")]
    assert learned and learned[-1].endswith("| yes |")
    assert [line for line in text.splitlines() if line.startswith("| sac / override | 0.333")][-1].endswith("| no |")
    assert [line for line in text.splitlines() if line.startswith("| sac_llm_amortized / override | 0.250")
            ][0].endswith("| 0.250 | student; LLM 30.0% of advised rows (10.0% with advisor) |")
    assert [line for line in text.splitlines() if line.startswith("| sac_heuristic / teach | 0.250")
            ][0].endswith("| – | none |")
    assert ("| sac_llm_amortized / override | 2 | 40 min | 4.00 | 100 | 30 | 20 / 10 | 2,000 / 200 | 15 min |"
            in text.splitlines())
    assert "| sac / override | 3 | 10 min | 1.00 | – | – | – | – | – |" in text.splitlines()
    assert "- LLM HTTP calls over the study: 40 (and 20 LLM rows answered from the answer cache)." in text
    assert ("LLM rung) | not shown (intervals hold 0) so far (seeds done: override 2 of 3, teach 0 of 3) | "
            "learning-aid world, the actor alone, LLM rung minus "
            "greedy heuristic: the paper's override, seeds 0 1: ΔDCR -0.500 [-1.000, 0.000]") in text
    assert ("plain SAC did not learn (DCR and SLR not above random's). Learned where it did not: "
            "sac_heuristic / override, sac_heuristic / teach.") in text
    assert "sac_heuristic / teach on DCR (1.000 [1.000, 1.000]; 1.00x plain SAC's training wall clock)" in text
    first = text
    build(tmp_path)
    assert (tmp_path / "report.md").read_text() == first  # the same records, the same report
    assert (tmp_path / "cells_aid.png").is_file() and (tmp_path / "curves_aid.png").is_file()


def test_records_restore_and_reuse_on_real_runs(tmp_path, monkeypatch):
    """Two tiny study runs (plain SAC, and SAC+Heuristic under teach) -> records -> restored
    into an empty runs folder, where the study's reuse counts them as done and the records
    step adds nothing twice; the tuning choice reads the restored runs."""
    import json

    from omegaconf import OmegaConf

    from uavlae.experiments.advice import choose, restore, write_records
    from tests.test_train import TINY, _cfg
    from uavlae.train import reuse_state, run

    # the study's runs sit at a relative root, as `make advice-study` puts them
    (tmp_path / "here").mkdir()
    monkeypatch.chdir(tmp_path / "here")
    root, out = Path("runs/advice"), tmp_path / "records"
    eval_set = tmp_path / "eval_set.json"
    common = [*TINY, "+sweep=advice", "experiment.root=runs", f"trainer.eval_set={eval_set}",
              "env=shaped_geodesic", "trainer.eval_with_advisor=true", "trainer.keep_replay_at_end=true"]
    cells = [("+exp=sac", "experiment.point=aid_override"),
             ("+exp=sac_heuristic", "experiment.point=aid_tune", "algo.clone_weight=0.4",
              "algo.clone_decay_frames=128", "advisor.phase_out_frames=64", "experiment.method=sac_heuristic_w0.4")]
    for cell in cells:
        run(_cfg(*common, *cell))
    # a run resumed by its absolute folder records that folder: the kept copy must not name it
    recorded = root / "aid_override" / "sac" / "seed0" / "config.json"
    as_run = json.loads(recorded.read_text())
    recorded.write_text(json.dumps({**as_run, "run_dir": str(recorded.parent.resolve())}))
    counts = write_records(root, out)
    kept = json.loads((out / "runs" / "aid_override" / "sac" / "seed0" / "config.json").read_text())
    assert kept["run_dir"] == "runs/advice/aid_override/sac/seed0"
    assert counts["runs"] == 2 and counts["unfinished"] == 0
    assert counts["episodes"] == 2 * 3 + 2 * 4  # 2 scenarios; plain SAC has no with-advisor evaluation
    runs = {r["method"]: r for r in csv.DictReader((out / "runs.csv").open())}
    assert float(runs["sac_heuristic_w0.4"]["clone_weight"]) == 0.4
    assert runs["sac_heuristic_w0.4"]["advisor"] == "heuristic/greedy"
    assert float(runs["sac_heuristic_w0.4"]["override/frames"]) == 128
    (tmp_path / "elsewhere").mkdir()
    monkeypatch.chdir(tmp_path / "elsewhere")  # another checkout, another machine
    fresh = Path("runs/advice")
    assert restore(out, fresh) == 2
    assert choose(fresh) == 0.4
    cfg = OmegaConf.create(json.loads((fresh / "aid_override" / "sac" / "seed0" / "config.json").read_text()))
    state, final = reuse_state(cfg)
    assert state == "done" and final["frames"] == 128
    assert write_records(fresh, out)["runs"] == 2  # the restored runs are not recorded again
    assert sum(1 for _ in csv.DictReader((out / "episodes.csv").open())) == counts["episodes"]


def test_readme_verdicts_are_the_reports():
    """The README's table of the paper's claims says what the committed report says, claim by claim."""
    root = Path(__file__).resolve().parents[1]

    def verdicts(text: str) -> dict[str, str]:
        section = text.split("## The paper's claims", 1)[-1] if "## The paper's claims" in text else text
        rows = [line.split(" | ") for line in section.splitlines() if line.startswith("| ") and " | " in line]
        return {r[0][2:]: r[1].rstrip(" |") for r in rows if r[0][2:] not in ("claim", "method", "path")}

    report = verdicts((root / "results" / "advice" / "report.md").read_text().split("## Findings")[0])
    readme = (root / "README.md").read_text().split("### Does advice teach?", 1)[1].split("What the study shows")[0]
    assert verdicts(readme) == report


def test_the_committed_report_regenerates_from_its_records(tmp_path):
    """``results/advice/report.md``, byte for byte, and its figures, from the CSV records beside it."""
    import shutil

    import matplotlib

    matplotlib.use("Agg")
    from uavlae.experiments.advice_report import build

    committed = Path(__file__).resolve().parents[1] / "results" / "advice"
    for f in committed.glob("*.csv"):
        shutil.copy(f, tmp_path / f.name)
    build(tmp_path)
    assert (tmp_path / "report.md").read_bytes() == (committed / "report.md").read_bytes()
    figures = {f.name for f in tmp_path.iterdir() if f.suffix in (".png", ".pdf")}
    assert figures and figures <= {f.name for f in committed.iterdir()}
