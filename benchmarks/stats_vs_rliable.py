"""Our statistics (uavlae/experiments/advice_stats.py) beside rliable's on the advice study's scores.

For every cell of the advice study (results/advice/episodes.csv, the actor alone), the pooled
DCR, SLR and CR with our stratified bootstrap over seeds x scenarios and with rliable's
``StratifiedBootstrap`` on the same episodes (runs = seeds, tasks = scenarios), both with the
tasks resampled (``task_bootstrap=True``, the analogue of ours) and without; and for every advised
cell against plain SAC in its world (on the seeds both ran), the probability of improvement on
the per-episode DCR and SLR, ours and rliable's (``metrics.probability_of_improvement`` with its
``StratifiedIndependentBootstrap``). 95% percentile intervals, ``--reps`` resamples each.

The two bootstraps differ in one place: rliable draws the runs of every task on their own (in
Atari, its field, each game trains its own agents, so a run of one task has nothing to do with
the same-numbered run of another), ours draws whole seeds (here one seed is one trained actor
flying all 32 scenarios, so its episodes move together). Where a grid has one seed, or one
scenario, the two are the same procedure; tests/test_stats_vs_rliable.py checks that, and that
the point estimates agree exactly.

Runs without torch or uavlae (advice_stats.py is loaded as a file), with numpy, scipy and
rliable (the ``dev`` extra):
    python benchmarks/stats_vs_rliable.py -> benchmarks/stats_vs_rliable.json
"""

from __future__ import annotations

import argparse
import csv
import importlib.metadata
import importlib.util
import json
import sys
import time
from collections import defaultdict
from pathlib import Path

import numpy as np
from rliable import library as rly
from rliable import metrics as rly_metrics

ROOT = Path(__file__).resolve().parents[1]


def load_advice_stats():
    """uavlae/experiments/advice_stats.py by its path: numpy is all it needs."""
    spec = importlib.util.spec_from_file_location("advice_stats", ROOT / "uavlae" / "experiments" / "advice_stats.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # its dataclasses look their module up there
    spec.loader.exec_module(module)
    return module


ST = load_advice_stats()
# the pooled metrics as functions of a resampled grid's fields (advice_stats' definitions)
POOLED = {
    "DCR": lambda c, t, col, land: np.array([c.sum() / t.sum()]),
    "SLR": lambda c, t, col, land: np.array([land.mean()]),
    "CR": lambda c, t, col, land: np.array([col.mean()]),
}


def cells(episodes_csv: Path) -> dict[tuple[str, str, str], object]:
    """(world, transfer, method) -> the Grid of its actor-alone episodes."""
    rows = defaultdict(list)
    with episodes_csv.open(newline="") as fh:
        for r in csv.DictReader(fh):
            if r["evaluation"] == "alone":
                rows[(r["world"], r["transfer"], r["method"])].append(r)
    return {k: ST.grid_from_rows(v) for k, v in sorted(rows.items())}


def rliable_pooled(g, metric: str, reps: int, task_bootstrap: bool, seed: int) -> tuple[float, float, float]:
    """rliable's StratifiedBootstrap of the pooled metric (runs = seeds, tasks = scenarios)."""
    np.random.seed(seed)  # rliable draws its indices from numpy's global generator
    bs = rly.StratifiedBootstrap(g.collected, g.total, g.collided, g.landed, task_bootstrap=task_bootstrap)
    lo, hi = bs.conf_int(POOLED[metric], reps=reps, size=0.95, method="percentile")[:, 0]
    return float(POOLED[metric](g.collected, g.total, g.collided, g.landed)[0]), float(lo), float(hi)


def rliable_poi(x, y, metric: str, reps: int, seed: int) -> tuple[float, float, float]:
    """rliable's probability of improvement of X over Y on the per-episode scores, and its interval."""
    np.random.seed(seed)
    sx, sy = ST.episode_scores(x, metric), ST.episode_scores(y, metric)
    point, interval = rly.get_interval_estimates(
        {"x_over_y": [sx, sy]}, lambda a, b: np.array([rly_metrics.probability_of_improvement(a, b)]), reps=reps)
    return float(point["x_over_y"][0]), float(interval["x_over_y"][0, 0]), float(interval["x_over_y"][1, 0])


def rounded(v: tuple[float, float, float]) -> list[float]:
    return [round(x, 4) for x in v]


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--reps", type=int, default=2000, help="bootstrap resamples of each interval (the reports' 2000)")
    p.add_argument("--poi-reps", type=int, default=2000, help="for rliable's probability of improvement (slow: a "
                   "Mann-Whitney U per scenario per resample)")
    p.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "stats_vs_rliable.json")
    a = p.parse_args()
    t0 = time.perf_counter()
    grids = cells(ROOT / "results" / "advice" / "episodes.csv")
    pooled = []
    for i, ((world, transfer, method), g) in enumerate(grids.items()):
        for metric in POOLED:
            ours = ST.interval(g, metric, a.reps, i)
            both = rliable_pooled(g, metric, a.reps, True, i)
            runs_only = rliable_pooled(g, metric, a.reps, False, i)
            pooled.append({"cell": f"{world}/{transfer}/{method}", "seeds": len(g.seeds), "scenarios": g.shape[1],
                           "metric": metric, "ours": rounded(ours), "rliable_runs_and_tasks": rounded(both),
                           "rliable_runs_only": rounded(runs_only),
                           "width_ours_over_rliable": round((ours[2] - ours[1]) / (both[2] - both[1]), 3)
                           if both[2] > both[1] else None})
    poi = []
    for i, ((world, transfer, method), g) in enumerate(grids.items()):
        base = grids.get((world, "override", "sac"))
        if method == "sac" or base is None or transfer == "tune":
            continue
        shared = ST.on_shared_seeds(g, base)
        if shared is None:
            continue
        x, y = shared
        for metric in ("DCR", "SLR"):
            ours = ST.probability_of_improvement(x, y, metric, a.reps, i)
            theirs = rliable_poi(x, y, metric, a.poi_reps, i)
            poi.append({"cell": f"{world}/{transfer}/{method}", "against": f"{world}/override/sac",
                        "seeds": x.seeds, "metric": metric, "ours": rounded(ours), "rliable": rounded(theirs),
                        "point_difference": abs(ours[0] - theirs[0])})
    out = {"what": __doc__.split("\n\n")[0], "command": "python benchmarks/stats_vs_rliable.py", "reps": a.reps,
           "poi_reps": a.poi_reps, "rliable": importlib.metadata.version("rliable"),
           "numpy": np.__version__, "wall_s": round(time.perf_counter() - t0, 1), "pooled": pooled,
           "probability_of_improvement": poi}
    a.out.write_text(json.dumps(out, indent=1) + "\n")
    print(f"{len(pooled)} pooled intervals, {len(poi)} probabilities of improvement -> {a.out}")


if __name__ == "__main__":
    main()
