"""Our statistics (uavlae/experiments/advice_stats.py) against the field's reference, rliable
(Agarwal et al. 2021), on the same scores. Needs the ``dev`` extra (rliable); skipped without it.

What must agree, and does:

- the point estimates, exactly: the pooled metrics, and the probability of improvement (ours is
  rliable's definition, written as one array expression where rliable runs a Mann-Whitney U
  per scenario), on every cell of the committed advice study;
- the intervals, to Monte-Carlo tolerance, where the two bootstraps are the same procedure: a
  grid of one seed (both resample the scenarios: rliable's ``task_bootstrap=True``), and a grid
  of one scenario (both resample each cell's seeds).

Where a grid has several seeds and several scenarios they differ by design, and no tolerance
would hide it: rliable draws every task's runs on their own (in Atari each game trains its own
agents), ours draws whole seeds, because here one seed is one trained actor flying every
scenario and its episodes move together (benchmarks/stats_vs_rliable.json: on the study's cells
ours is up to 2.7 times as wide, median 1.25, for the pooled metrics, and 1.6 to 3.8 times for
the probability of improvement, where rliable also keeps the scenarios fixed).

Monte-Carlo tolerance: with B resamples, a 2.5% or 97.5% percentile of a bootstrap distribution
of spread sigma has a Monte-Carlo standard error of about sqrt(0.025 * 0.975 / B) / phi(1.96)
* sigma = 2.67 sigma / sqrt(B) (the quantile's asymptotic error, normal density at the
quantile); two independent runs of the same procedure differ by sqrt(2) times that. The tests
allow five of those standard errors, 5 * 3.78 sigma / sqrt(B), with sigma read off our interval
(its width over 2 * 1.96): a false alarm once in about two million endpoints.
"""

from __future__ import annotations

import csv
import importlib.util
import math
import sys
from collections import defaultdict
from pathlib import Path

import numpy as np
import pytest

rliable_library = pytest.importorskip("rliable.library", reason="rliable is a dev extra: pip install -e '.[dev]'")
rliable_metrics = pytest.importorskip("rliable.metrics")

ROOT = Path(__file__).resolve().parents[1]
B = 20_000  # resamples per interval: a Monte-Carlo error of 0.027 sigma per endpoint


def _advice_stats():
    """advice_stats.py by its path: it needs numpy alone, so this runs where torch does not."""
    spec = importlib.util.spec_from_file_location("advice_stats_under_test",
                                                  ROOT / "uavlae" / "experiments" / "advice_stats.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # its dataclasses look their module up there
    spec.loader.exec_module(module)
    return module


ST = _advice_stats()


def tolerance(lo: float, hi: float) -> float:
    """Five Monte-Carlo standard errors of the difference of two endpoints (module doc)."""
    sigma = (hi - lo) / (2 * 1.96)
    return 5 * 2.67 * math.sqrt(2) * sigma / math.sqrt(B)


def study_cells() -> dict[tuple[str, str, str], object]:
    """The advice study's cells (results/advice/episodes.csv), the actor alone."""
    rows = defaultdict(list)
    with (ROOT / "results" / "advice" / "episodes.csv").open(newline="") as fh:
        for r in csv.DictReader(fh):
            if r["evaluation"] == "alone":
                rows[(r["world"], r["transfer"], r["method"])].append(r)
    return {k: ST.grid_from_rows(v) for k, v in sorted(rows.items())}


def grid(collected: np.ndarray, landed: np.ndarray) -> object:
    """A grid of per-episode data collected (of 1 held) and landing flags."""
    zeros = np.zeros_like(collected)
    return ST.Grid(list(range(collected.shape[0])), collected, np.ones_like(collected), zeros, landed, zeros,
                   zeros + 1.0, zeros + 4.0)


def pooled_dcr(collected: np.ndarray, total: np.ndarray) -> np.ndarray:
    return np.array([collected.sum() / total.sum()])


def rliable_dcr(g, task_bootstrap: bool, seed: int) -> tuple[float, float]:
    np.random.seed(seed)  # rliable draws its indices from numpy's global generator
    bs = rliable_library.StratifiedBootstrap(g.collected, g.total, task_bootstrap=task_bootstrap)
    lo, hi = bs.conf_int(pooled_dcr, reps=B, size=0.95, method="percentile")[:, 0]
    return float(lo), float(hi)


def rliable_poi(x, y, seed: int) -> tuple[float, float, float]:
    np.random.seed(seed)
    sx, sy = ST.episode_scores(x, "DCR"), ST.episode_scores(y, "DCR")
    point, iv = rliable_library.get_interval_estimates(
        {"xy": [sx, sy]}, lambda a, b: np.array([rliable_metrics.probability_of_improvement(a, b)]), reps=B)
    return float(point["xy"][0]), float(iv["xy"][0, 0]), float(iv["xy"][1, 0])


def test_point_estimates_are_rliables_on_every_cell_of_the_study():
    cells = study_cells()
    compared = 0
    for (world, transfer, method), g in cells.items():
        assert ST.point(g, "DCR") == pytest.approx(pooled_dcr(g.collected, g.total)[0], abs=1e-12)
        base = cells.get((world, "override", "sac"))
        shared = None if base is None or method == "sac" else ST.on_shared_seeds(g, base)
        if shared is None:  # plain SAC itself, or the tuning runs (seeds apart)
            continue
        x, y = shared
        compared += 1
        for metric in ("DCR", "SLR", "CR"):
            ours = ST.probability_of_improvement(x, y, metric, n_boot=10)[0]
            theirs = rliable_metrics.probability_of_improvement(ST.episode_scores(x, metric), ST.episode_scores(y, metric))
            assert ours == pytest.approx(theirs, abs=1e-12), (world, transfer, method, metric)
    assert compared >= 10  # every advised cell of both worlds


def test_one_seed_both_resample_the_scenarios():
    """One seed, 64 scenarios: ours and rliable's StratifiedBootstrap with its tasks resampled."""
    rng = np.random.default_rng(3)
    g = grid(rng.beta(2.0, 1.0, size=(1, 64)), (rng.random((1, 64)) < 0.7).astype(float))
    _, lo, hi = ST.interval(g, "DCR", n_boot=B, seed=1)
    r_lo, r_hi = rliable_dcr(g, task_bootstrap=True, seed=2)
    tol = tolerance(lo, hi)
    assert abs(lo - r_lo) <= tol and abs(hi - r_hi) <= tol, (lo, hi, r_lo, r_hi, tol)


def test_one_scenario_both_resample_the_seeds():
    """One scenario, 64 seeds: the pooled DCR's interval; and the probability of improvement of
    X (24 seeds) over Y (20 seeds), each cell's seeds resampled on their own by both."""
    rng = np.random.default_rng(4)
    g = grid(rng.beta(2.0, 1.0, size=(64, 1)), np.ones((64, 1)))
    _, lo, hi = ST.interval(g, "DCR", n_boot=B, seed=1)
    r_lo, r_hi = rliable_dcr(g, task_bootstrap=False, seed=2)
    tol = tolerance(lo, hi)
    assert abs(lo - r_lo) <= tol and abs(hi - r_hi) <= tol, (lo, hi, r_lo, r_hi, tol)

    x = grid(rng.beta(2.5, 1.0, size=(24, 1)), np.ones((24, 1)))
    y = grid(rng.beta(2.0, 1.0, size=(20, 1)), np.ones((20, 1)))
    p, lo, hi = ST.probability_of_improvement(x, y, "DCR", n_boot=B, seed=1)
    r_p, r_lo, r_hi = rliable_poi(x, y, seed=2)
    tol = tolerance(lo, hi)
    assert p == pytest.approx(r_p, abs=1e-12)
    assert abs(lo - r_lo) <= tol and abs(hi - r_hi) <= tol, (lo, hi, r_lo, r_hi, tol)
