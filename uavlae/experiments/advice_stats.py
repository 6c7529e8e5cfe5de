"""Statistics fit for few seeds: a stratified bootstrap over seeds x evaluation scenarios.

Every run of a cell flies the same evaluation scenarios, so a cell's results form a grid
``[seeds, scenarios]`` of episodes. A paper metric is a pooled statistic of such a grid (DCR:
data collected over data held; CR, SLR, RVR: the fraction of episodes; ECR: energy used over
energy held). Its interval is the 2.5 and 97.5 percentiles of the statistic over bootstrap
replicates that resample the seeds and, independently, the scenarios (each with replacement):
the two sources of variation, each resampled on its own. A resampled pooled statistic of values
in a metric's range stays in that range, so the intervals do too, however few the seeds (a
Student's t interval on three seeds does not).

This is rliable's stratified bootstrap (Agarwal et al. 2021) with one change: rliable draws every
task's runs on their own (in Atari each game trains its own agents), here a seed is drawn whole,
because one seed is one trained actor flying every scenario and its episodes move together;
drawn per scenario, a seed's luck would average out and the interval would be too narrow (on the
advice study's cells rliable's is up to 2.7 times narrower, median 1.25, for the pooled metrics;
for the probability of improvement, where rliable also keeps the scenarios fixed, 1.6 to 3.8
times: benchmarks/stats_vs_rliable.json). Where a grid has one seed or one scenario the two are
the same procedure, and the point estimates are the same everywhere: tests/test_stats_vs_rliable.py
checks both against rliable itself.

Comparisons between cells use the same scenario draw for both cells (the scenarios are shared)
and, for the difference of means, the same seed draw where both cells ran the same seeds
(paired seeds). The probability of improvement is rliable's: for each scenario, the chance that
a run of X scores above a run of Y (ties count a half), averaged over scenarios; its interval
resamples the scenarios and each cell's seeds.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from uavlae.experiments.reporting import cell_true

METRICS = ("DCR", "CR", "SLR", "RVR", "ECR")
HIGHER_BETTER = ("DCR", "SLR")
FIELDS = ("collected", "total", "collided", "landed", "rz", "energy", "energy_total")
METHOD_NAME = ("stratified bootstrap over seeds x evaluation scenarios (rliable's; 2.5-97.5 percentiles "
               "of {n} resamples), pooled metrics as the paper defines them")


@dataclass
class Grid:
    """One cell's episodes: each field ``[seeds, scenarios]``; ``seeds`` their seed numbers."""

    seeds: list[int]
    collected: np.ndarray
    total: np.ndarray
    collided: np.ndarray
    landed: np.ndarray
    rz: np.ndarray
    energy: np.ndarray
    energy_total: np.ndarray

    @property
    def shape(self) -> tuple[int, int]:
        return self.collected.shape  # type: ignore[return-value]

    def take(self, seeds: list[int]) -> "Grid":
        rows = [self.seeds.index(s) for s in seeds]
        return Grid(seeds, *(getattr(self, f)[rows] for f in FIELDS))


def on_shared_seeds(x: Grid, y: Grid) -> tuple[Grid, Grid] | None:
    """``x`` and ``y`` cut to the seeds both ran (in ``x``'s order), for a paired comparison;
    None when they share none."""
    both = [s for s in x.seeds if s in y.seeds]
    return (x.take(both), y.take(both)) if both else None


def grid_from_rows(rows: list[dict]) -> Grid:
    """Episode rows (``seed``, ``scenario``, ``data_collected``, ``data_total``, ``collided``,
    ``landed``, ``rz_speeding``, ``energy_used``, ``energy_total``) -> a Grid. Every seed must
    hold the same scenarios."""
    seeds = sorted({int(r["seed"]) for r in rows})
    scenarios = sorted({int(r["scenario"]) for r in rows})
    index = {(int(r["seed"]), int(r["scenario"])): r for r in rows}
    missing = [(s, n) for s in seeds for n in scenarios if (s, n) not in index]
    if missing:
        raise ValueError(f"seeds do not share their evaluation scenarios (missing seed, scenario: {missing[:5]})")

    def arr(col: str, cast=float) -> np.ndarray:
        return np.array([[cast(index[(s, n)][col]) for n in scenarios] for s in seeds], dtype=float)

    def flag(v) -> float:
        return 1.0 if cell_true(v) else 0.0

    return Grid(seeds, arr("data_collected"), arr("data_total"), arr("collided", flag), arr("landed", flag),
                arr("rz_speeding", flag), arr("energy_used"), arr("energy_total"))


def _pooled(g: dict[str, np.ndarray], metric: str) -> np.ndarray:
    """The metric over the last two axes (seeds, scenarios) of every field."""
    ax = (-2, -1)
    if metric == "DCR":
        return g["collected"].sum(ax) / g["total"].sum(ax)
    if metric == "ECR":
        return g["energy"].sum(ax) / g["energy_total"].sum(ax)
    return {"CR": g["collided"], "SLR": g["landed"], "RVR": g["rz"]}[metric].mean(ax)


def _fields(grid: Grid) -> dict[str, np.ndarray]:
    return {f: getattr(grid, f) for f in FIELDS}


def point(grid: Grid, metric: str) -> float:
    return float(_pooled(_fields(grid), metric))


def _resample(grid: Grid, seed_idx: np.ndarray, scen_idx: np.ndarray) -> dict[str, np.ndarray]:
    """Fields at ``[B, S', N']``: seed rows ``seed_idx`` [B, S'] and scenario columns ``scen_idx`` [B, N']."""
    return {f: getattr(grid, f)[seed_idx[:, :, None], scen_idx[:, None, :]] for f in FIELDS}


def interval(grid: Grid, metric: str, n_boot: int = 2000, seed: int = 0) -> tuple[float, float, float]:
    """(point, lo, hi): the pooled metric and its stratified-bootstrap 95% interval."""
    rng = np.random.default_rng(seed)
    S, N = grid.shape
    reps = _pooled(_resample(grid, rng.integers(S, size=(n_boot, S)), rng.integers(N, size=(n_boot, N))), metric)
    reps = reps[np.isfinite(reps)]
    lo, hi = (np.percentile(reps, [2.5, 97.5]) if reps.size else (math.nan, math.nan))
    return point(grid, metric), float(lo), float(hi)


def mean_interval(grids: list[Grid], metric: str, n_boot: int = 2000, seed: int = 0) -> tuple[float, float, float]:
    """(point, lo, hi) of the mean over several settings (one grid each, the same seeds, each its
    own scenarios) of the pooled metric: each replicate draws the seeds once for every setting (a
    seed is one run of each) and each setting's scenarios on their own."""
    if not grids or any(g.seeds != grids[0].seeds for g in grids):
        raise ValueError("the settings' grids must hold the same seeds")
    rng = np.random.default_rng(seed)
    S = grids[0].shape[0]
    seeds = rng.integers(S, size=(n_boot, S))
    reps = np.mean([_pooled(_resample(g, seeds, rng.integers(g.shape[1], size=(n_boot, g.shape[1]))), metric)
                    for g in grids], axis=0)
    reps = reps[np.isfinite(reps)]
    lo, hi = (np.percentile(reps, [2.5, 97.5]) if reps.size else (math.nan, math.nan))
    return float(np.mean([point(g, metric) for g in grids])), float(lo), float(hi)


def difference(x: Grid, y: Grid, metric: str, n_boot: int = 2000, seed: int = 0) -> tuple[float, float, float]:
    """(point, lo, hi) of ``metric(x) - metric(y)``: the scenarios drawn once for both cells, the
    seeds drawn once for both where they ran the same seeds (paired), each its own otherwise."""
    rng = np.random.default_rng(seed)
    N = x.shape[1]
    if y.shape[1] != N:
        raise ValueError("the two cells were evaluated on different scenario sets")
    scen = rng.integers(N, size=(n_boot, N))
    if x.seeds == y.seeds:
        sx = sy = rng.integers(x.shape[0], size=(n_boot, x.shape[0]))
    else:
        sx, sy = rng.integers(x.shape[0], size=(n_boot, x.shape[0])), rng.integers(y.shape[0], size=(n_boot, y.shape[0]))
    reps = _pooled(_resample(x, sx, scen), metric) - _pooled(_resample(y, sy, scen), metric)
    reps = reps[np.isfinite(reps)]
    lo, hi = np.percentile(reps, [2.5, 97.5])
    return point(x, metric) - point(y, metric), float(lo), float(hi)


def episode_scores(grid: Grid, metric: str) -> np.ndarray:
    """Per-episode scores ``[seeds, scenarios]`` for the probability of improvement: DCR per
    episode (collected over held), and the 0/1 landed flag for SLR; sign-flipped for the
    lower-is-better metrics so that higher is always better."""
    if metric == "DCR":
        return np.divide(grid.collected, grid.total, out=np.zeros_like(grid.collected), where=grid.total > 0)
    if metric == "ECR":
        return -grid.energy / grid.energy_total
    flag = {"CR": grid.collided, "SLR": grid.landed, "RVR": grid.rz}[metric]
    return flag if metric in HIGHER_BETTER else -flag


def _prob_improvement(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """``x`` [..., Sx, N], ``y`` [..., Sy, N] -> P(X > Y) [...]: per scenario the fraction of run
    pairs where x beats y (ties a half), averaged over scenarios."""
    gt = (x[..., :, None, :] > y[..., None, :, :]).astype(float)
    eq = (x[..., :, None, :] == y[..., None, :, :]).astype(float)
    return (gt + 0.5 * eq).mean(axis=(-3, -2)).mean(-1)


def probability_of_improvement(x: Grid, y: Grid, metric: str, n_boot: int = 2000,
                               seed: int = 0) -> tuple[float, float, float]:
    """(point, lo, hi) of P(X > Y) on ``metric``'s per-episode scores (rliable's definition)."""
    sx_, sy_ = episode_scores(x, metric), episode_scores(y, metric)
    est = float(_prob_improvement(sx_, sy_))
    rng = np.random.default_rng(seed)
    (Sx, N), Sy = sx_.shape, sy_.shape[0]
    scen = rng.integers(N, size=(n_boot, N))
    ix, iy = rng.integers(Sx, size=(n_boot, Sx)), rng.integers(Sy, size=(n_boot, Sy))
    reps = _prob_improvement(sx_[ix[:, :, None], scen[:, None, :]], sy_[iy[:, :, None], scen[:, None, :]])
    lo, hi = np.percentile(reps, [2.5, 97.5])
    return est, float(lo), float(hi)
