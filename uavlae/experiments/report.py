"""``uavlae-report RUNS_DIR [--out DIR]`` (``python -m uavlae.experiments.report``): the paper's
tables and figures from the runs of the sweeps (uavlae/conf/sweep/, uavlae/experiments/README.md).

It collects every run under ``RUNS_DIR``: training runs (``uavlae.train``: ``config.json``,
``meta.json``, ``final_metrics.json``, ``logs/scalars/``) and evaluations (``uavlae.evaluate``:
``evaluation.json``). A run without its final file is listed as unfinished, one whose files do
not parse as broken; neither enters a table. Over the seeds of each (sweep, setting, method) it
gives the metric and its 95% interval: the stratified bootstrap over seeds x evaluation scenarios
of :mod:`uavlae.experiments.advice_stats` where every run kept its final evaluation's episodes
(the interval stays inside the metric's range however few the seeds), else the interval of the
mean over seeds (Student's t, n - 1 degrees of freedom; none for one seed, marked "t" in the
tables); and writes to ``--out`` (default ``RUNS_DIR/report``):

- ``runs.csv`` (every collected run: its metrics, commit and command), ``skipped.csv``;
- one CSV and one Markdown table per figure, PNG and PDF figures (Fig. 3 training curves with
  95% bands, Figs. 5-9 metric against count, Fig. 10 radar, Figs. 11-14 sensitivity);
- ``learned.csv``: whether each method's DCR and SLR beat the uniform-random policy's with
  non-overlapping 95% intervals;
- ``report.md``: all of it with the sweep commands, the commits and the package versions.

Nothing is cached: adding seeds or methods to ``RUNS_DIR`` and running this again re-aggregates
everything from the run files.
"""

from __future__ import annotations

import argparse
import json
import math
import shlex
import sys
from collections import defaultdict
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import yaml

from uavlae.envs.metrics import aggregate, load_records
from uavlae.experiments.advice_stats import METHOD_NAME, Grid, grid_from_rows, mean_interval
from uavlae.experiments.advice_stats import interval as bootstrap_interval
from uavlae.experiments.reporting import (  # noqa: F401  (read_scalar: re-exported, readers of runs found it here)
    fmt_interval,
    markdown_table,
    read_json,
    read_rows,
    read_scalar,
    save_figure,
    write_csv,
    write_text,
)
from uavlae.files import dump_json, train_eval_dir

METRICS = ("DCR", "CR", "SLR", "RVR", "ECR")
# Higher is better for these; lower for the others (the radar chart flips those).
HIGHER_BETTER = ("DCR", "SLR")
METHOD_ORDER = ("sac_llm", "sac_heuristic", "sac_heuristic_planner", "sac", "ppo", "ddpg", "cpo", "wang", "theile", "llm",
                "heuristic", "heuristic_planner", "random")
SCENARIO_SWEEPS = {  # sweep -> (count, figure)
    "scenario_n_ou": ("N_OU", "fig5"),
    "scenario_n_ge": ("N_GE", "fig6"),
    "scenario_n_nfz": ("N_NFZ", "fig7"),
    "scenario_n_bz": ("N_BZ", "fig8"),
    "scenario_n_rz": ("N_RZ", "fig9"),
}
# The sensitivity axes (conf/sweep/sens_*.yaml): (name, dotted config key, figure, label).
SENSITIVITY_AXES = (
    ("actor_lr", "algo.actor_lr", "fig11", "actor_lr"),
    ("critic_lr", "algo.critic_lr", "fig11", "critic_lr"),
    ("batch_size", "trainer.batch_size", "fig11", "batch_size"),
    ("r1", "env.reward.sigma.0", "fig12", "r1"),
    ("r2", "env.reward.sigma.1", "fig12", "r2"),
    ("r5", "env.reward.sigma.4", "fig12", "r5"),
    ("r8", "env.reward.sigma.7", "fig12", "r8"),
)
# The LLM sweeps' axes (conf/sweep/llm_dth.yaml, llm_prompt.yaml): one folder per setting, like
# the sensitivity sweeps; (name, dotted config key, figure, label).
LLM_AXES = (
    ("d_th", "advisor.d_th", "fig13", "d_th (m)"),
    ("prompt", "llm.prompt_ablation", "fig14", "prompt"),
)
MARKERS = ("o", "s", "^", "D", "v", "P", "X", "*", "<", ">", "h", "p")
LINESTYLES = ("-", "--", "-.", ":")
FIGURE_DPI = 150  # the report's figures: sharp enough to read a legend in a PNG


# ---------------------------------------------------------------------------- statistics


def t_quantile(p: float, dof: int) -> float:
    """The ``p`` quantile of Student's t with ``dof`` degrees of freedom (p > 0.5): bisection on
    the CDF, which is 1/2 plus the density's integral from 0 (Simpson's rule)."""
    if dof < 1 or not 0.5 < p < 1:
        raise ValueError(f"t_quantile needs dof >= 1 and 0.5 < p < 1, got dof={dof}, p={p}")
    c = math.exp(math.lgamma((dof + 1) / 2) - math.lgamma(dof / 2)) / math.sqrt(dof * math.pi)

    def pdf(t: float) -> float:
        return c * (1 + t * t / dof) ** (-(dof + 1) / 2)

    def cdf(x: float, n: int = 4000) -> float:
        h = x / n
        s = pdf(0) + pdf(x) + sum((4 if i % 2 else 2) * pdf(i * h) for i in range(1, n))
        return 0.5 + s * h / 3

    lo, hi = 0.0, 1.0
    while cdf(hi) < p:
        lo, hi = hi, hi * 2
    for _ in range(60):
        mid = (lo + hi) / 2
        lo, hi = (mid, hi) if cdf(mid) < p else (lo, mid)
    return (lo + hi) / 2


_T975: dict[int, float] = {}


def mean_ci(xs: list[float]) -> tuple[float, float, float, int]:
    """``(mean, low, high, n)``: the 95% interval of the mean over ``xs`` (NaNs dropped); the
    interval is NaN for fewer than two values."""
    xs = [float(x) for x in xs if x is not None and not math.isnan(float(x))]
    n = len(xs)
    if n == 0:
        return math.nan, math.nan, math.nan, 0
    m = sum(xs) / n
    if n < 2:
        return m, math.nan, math.nan, 1
    sd = math.sqrt(sum((x - m) ** 2 for x in xs) / (n - 1))
    if n - 1 not in _T975:
        _T975[n - 1] = t_quantile(0.975, n - 1)
    half = _T975[n - 1] * sd / math.sqrt(n)
    return m, m - half, m + half, n


fmt_ci = fmt_interval  # the name the report and its tests use


# ---------------------------------------------------------------------------- collection


@dataclass
class Run:
    kind: str  # train | eval
    path: Path
    sweep: str
    point: str
    method: str
    seed: int
    metrics: dict[str, float]
    config: dict[str, Any]
    frames: int = 0
    episodes: int = 0
    updates: int = 0
    commit: str = ""
    dirty: bool | None = None
    command: str = ""
    packages: dict[str, Any] = field(default_factory=dict)
    profile: str = ""
    world: str = ""
    machine: str = ""  # "CPU, N cores" from the run's metadata; "" where it was not recorded
    extra: dict[str, Any] = field(default_factory=dict)


def machine_label(meta: dict[str, Any]) -> str:
    m = meta.get("machine") or {}
    if not m:
        return ""
    label = f"{m.get('cpu', 'unknown CPU')}, {m.get('logical_cores', '?')} cores"
    return label + (f", {m['gpu']}" if m.get("gpu") else "")


def world_label(env: dict[str, Any]) -> str:
    """SPEC's world, or which learning aids (SPEC §10) a run's env had on."""
    reward = env.get("reward", {}) or {}
    aids = []
    if float(reward.get("progress_weight", 0) or 0) > 0:
        aids.append(f"progress reward ({reward.get('progress_metric', 'euclidean')})")
    if env.get("ego_features"):
        aids.append("ego features")
    if env.get("obs_frame", "world") == "ego":
        aids.append("ego frame")
    return "SPEC world" if not aids else "learning-aid world: " + ", ".join(aids)


def _select(d: dict[str, Any], dotted: str) -> Any:
    cur: Any = d
    for part in dotted.split("."):
        if isinstance(cur, list):
            try:
                cur = cur[int(part)]
            except (ValueError, IndexError):
                return None
        elif isinstance(cur, dict) and part in cur:
            cur = cur[part]
        else:
            return None
    return cur


def _metrics_of(d: dict[str, Any], prefix: str = "") -> dict[str, float]:
    out = {}
    for k, v in d.items():
        if k.startswith(prefix) and isinstance(v, (int, float)) and not isinstance(v, bool):
            out[k[len(prefix):]] = float(v)
    missing = [m for m in METRICS if m not in out]
    if missing:
        raise ValueError(f"no {', '.join(missing)} in the final metrics")
    return out


def _provenance(meta: dict[str, Any]) -> dict[str, Any]:
    """What a run's ``meta.json`` says produced it: the commit (short), whether the code differed
    from it, the package versions and the machine. Train and evaluation runs record it alike. A
    run of an installed package has no commit: its uavlae version stands in its place."""
    git = meta.get("git") or {}
    packages = meta.get("packages") or {}
    commit = str(git.get("commit") or "")[:10]
    if not commit and packages.get("uavlae"):
        commit = f"uavlae {packages['uavlae']}"
    return {"commit": commit, "dirty": git.get("dirty"), "packages": packages, "machine": machine_label(meta)}


_PROGRESS_KEYS = ("eval/episodes_scored", "eval/episodes_total", "llm/calls", "llm/http_calls", "llm/fallbacks")


def _train_run(d: Path, partial: bool = False) -> Run:
    """A finished train run; with ``partial``, also the LLM alone paused by its call budget (its
    metrics cover the episodes it has scored)."""
    cfg = read_json(d / "config.json")
    meta = read_json(d / "meta.json") if (d / "meta.json").is_file() else {}
    final_file = d / "final_metrics.json"
    if not final_file.is_file():
        ckpt = d / "checkpoints" / "last.pt"
        raise LookupError("unfinished: no final_metrics.json" + (" (a checkpoint to resume from)" if ckpt.is_file() else ""))
    final = read_json(final_file)
    tr = cfg.get("trainer", {})
    frames, episodes = int(final.get("frames", 0)), int(final.get("episodes", 0))
    if final.get("eval/complete", 1) == 0 and not partial:  # the LLM alone, paused by its call budget
        raise LookupError(f"unfinished: {int(final.get('eval/episodes_scored', 0))} of "
                          f"{int(final.get('eval/episodes_total', 0))} episodes scored (call budget; the same command continues)")
    if cfg.get("controller", "learner") == "learner":
        budget_frames = frames >= int(tr.get("total_frames", 0))
        budget_episodes = tr.get("total_episodes") is not None and episodes >= int(tr["total_episodes"])
        if not (budget_frames or budget_episodes):
            raise LookupError(f"unfinished: {frames} of {tr.get('total_frames')} frames")
    ex = cfg.get("experiment") or {}
    return Run(
        kind="train", path=d, sweep=str(ex.get("sweep") or "none"), point=str(ex.get("point") or "default"),
        method=str(ex.get("method") or cfg.get("name")), seed=int(cfg.get("seed", 0)),
        metrics=_metrics_of(final, "eval/"), config=cfg, frames=frames, episodes=episodes,
        updates=int(final.get("updates", 0)), command=str(meta.get("command") or shlex.join(meta.get("argv", []))),
        profile=str(ex.get("profile") or ""), world=world_label(cfg.get("env", {})), **_provenance(meta),
        extra={"wall_s": final.get("wall_s", final.get("llm/wall_s")),
               # the LLM alone's progress and advisor counts, for llm_alone_rows
               **{key.split("/")[1]: int(final[key]) for key in _PROGRESS_KEYS if key in final},
               "advisor_calls": int(final["llm/http_calls"]) if "llm/http_calls" in final else _advisor_calls(d, final)},
    )


def _advisor_calls(run_dir: Path, final: dict[str, Any]) -> str | None:
    """The advisor's calls over the run (the sum of every logged window's ``override/**/calls``),
    and where the run logged them, the rows it answered and how many of those came from the
    answer cache: ``"59 (100 rows, 43 cached)"``."""
    scalars = run_dir / "logs" / "scalars"

    def total(name: str) -> int | None:
        files = sorted((scalars / "override").rglob(f"{name}.csv"))
        return int(sum(v for f in files for _, v in read_scalar(run_dir, str(f.relative_to(scalars))[:-4]))) if files else None

    calls, cached = total("calls"), total("cache_hits")
    if calls is None:
        return None
    if "override/advised" not in final or cached is None:
        return str(calls)
    return f"{calls} ({int(final['override/advised'])} rows, {cached} cached)"


def _eval_run(d: Path) -> Run:
    rec = read_json(d / "evaluation.json")
    try:
        spec, ex, meta = rec["spec"], rec.get("experiment") or {}, rec.get("meta") or {}
        metrics = _metrics_of(rec["metrics"])
    except (KeyError, TypeError) as err:
        raise ValueError(f"evaluation.json lacks {err}") from None
    la = rec.get("llm_alone") or {}
    if not la.get("complete", True):
        raise LookupError(f"unfinished: {la.get('episodes_scored')} of {la.get('episodes_total')} episodes scored "
                          "(call budget; the same command continues)")
    return Run(
        kind="eval", path=d, sweep=str(ex.get("sweep") or "none"), point=str(ex.get("point") or "default"),
        method=str(spec.get("method") or rec.get("name")), seed=int(spec.get("seed", 0)), metrics=metrics,
        config={"env": rec.get("env", {})}, frames=int(spec.get("frames", 0)), episodes=int(rec.get("episodes_trained", 0)),
        updates=int(rec.get("updates", 0)), command=str(meta.get("command") or ""),
        profile=str(ex.get("profile") or ""), world=world_label(rec.get("env", {})), **_provenance(meta),
        extra={"n_scenarios": rec.get("n_scenarios"), "wall_s": rec.get("wall_s")},
    )


def machines_line(runs: list[Run]) -> str:
    """The machines the runs record, and how many runs record none (those made before runs did)."""
    names = sorted({r.machine for r in runs if r.machine})
    missing = sum(1 for r in runs if not r.machine)
    return "; ".join(names + ([f"not recorded for {missing} of {len(runs)} runs"] if missing else [])) or "none"


def collect(root: Path) -> tuple[list[Run], list[tuple[str, str]]]:
    """Every finished run under ``root``, and ``(path, reason)`` for each one skipped."""
    runs: list[Run] = []
    skipped: list[tuple[str, str]] = []
    seen: set[Path] = set()
    for marker, reader in (("evaluation.json", _eval_run), ("config.json", _train_run)):
        for f in sorted(root.rglob(marker)):
            d = f.parent
            rel = d.relative_to(root)
            if any(p.startswith(".") for p in rel.parts) or "report" in rel.parts[:1] or d in seen:
                continue  # Hydra's multirun folders, this report's own folder
            if marker == "config.json" and not (d / "meta.json").is_file():
                continue  # not a uavlae.train run
            seen.add(d)
            try:
                runs.append(reader(d))
            except LookupError as err:
                skipped.append((str(rel), str(err.args[0])))
            except ValueError as err:
                skipped.append((str(rel), f"broken: {err}"))
    return runs, skipped


# ---------------------------------------------------------------------------- aggregation


def method_key(m: str) -> tuple[int, str]:
    base = m.split("_fp")[0] if m.startswith("sac_llm_fp") else m
    order = METHOD_ORDER.index(base) if base in METHOD_ORDER else len(METHOD_ORDER)
    return (order + (0.5 if m != base else 0), m)  # type: ignore[return-value]


def group(runs: list[Run]) -> dict[tuple[str, str, str], list[Run]]:
    out: dict[tuple[str, str, str], list[Run]] = defaultdict(list)
    for r in runs:
        out[(r.sweep, r.point, r.method)].append(r)
    return out


N_BOOT = 2000


def final_episode_rows(run: Run) -> list[dict[str, str]] | None:
    """The episodes of a run's final evaluation (``episodes.csv`` beside a train run's final
    metrics, or beside an evaluation's ``evaluation.json``), or None when it kept none."""
    f = (train_eval_dir(run.path, run.frames) if run.kind == "train" else run.path) / "episodes.csv"
    return read_rows(f) or None


def episode_grid(runs: list[Run], scenarios: list[int] | None = None) -> Grid | None:
    """The runs' final evaluations as one grid of episodes ``[seeds, scenarios]`` (only
    ``scenarios`` where given); None where a run kept no episodes (or not every column), two runs
    share a seed, or the seeds did not fly the same scenarios."""
    rows: list[dict[str, Any]] = []
    if len({r.seed for r in runs}) != len(runs):
        return None
    for r in runs:
        eps = final_episode_rows(r)
        if eps is None:
            return None
        rows += [{**e, "seed": r.seed, "scenario": e.get("row", i)} for i, e in enumerate(eps)]
    if scenarios is not None:
        keep = set(scenarios)
        rows = [e for e in rows if int(e["scenario"]) in keep]
    try:
        return grid_from_rows(rows)
    except (KeyError, ValueError):
        return None


def aggregate_rows(runs: list[Run], keys: dict[str, Any] | None = None,
                   scenarios: list[int] | None = None) -> dict[str, Any]:
    """One table row over the seeds of a (sweep, setting, method): each metric and its interval
    (the stratified bootstrap over seeds x scenarios where the episodes were kept, ``interval``
    "bootstrap"; else Student's t over the seeds' metrics, ``interval`` "t"). ``scenarios``: the
    evaluation scenarios the runs' metrics cover, where they are a subset of the set flown."""
    row: dict[str, Any] = dict(keys or {})
    row["n_seeds"] = len(runs)
    row["seeds"] = " ".join(str(r.seed) for r in sorted(runs, key=lambda r: r.seed))
    grid = episode_grid(runs, scenarios)
    row["interval"] = "bootstrap" if grid is not None else "t"
    for i, m in enumerate(METRICS):
        if grid is not None:
            mean, lo, hi = bootstrap_interval(grid, m, N_BOOT, i)
        else:
            mean, lo, hi, _ = mean_ci([r.metrics.get(m, math.nan) for r in runs])
        row[m], row[f"{m}_lo"], row[f"{m}_hi"] = mean, lo, hi
    row["frames"] = " ".join(sorted({str(r.frames) for r in runs}))
    row["episodes"] = " ".join(sorted({str(r.episodes) for r in runs}))
    row["commits"] = " ".join(sorted({r.commit + ("+dirty" if r.dirty else "") for r in runs}))
    walls = [float(r.extra["wall_s"]) for r in runs if r.extra.get("wall_s") is not None]
    row["wall_s"] = round(sum(walls) / len(walls), 1) if walls else ""
    calls = [str(r.extra["advisor_calls"]) for r in runs if r.extra.get("advisor_calls") is not None]
    row["advisor_calls"] = " ".join(calls)
    return row


def _md_table(rows: list[dict[str, Any]], first: list[str]) -> list[str]:
    calls = any(r.get("advisor_calls") for r in rows)
    head = first + list(METRICS) + ["seeds", "frames", "episodes", "wall s (mean)"] + (["advisor calls (rows answered, cached)"] if calls else []) + ["commits"]
    cells = []
    for r in rows:
        mark = " (t)" if r.get("interval") == "t" and not math.isnan(r[f"{METRICS[0]}_lo"]) else ""
        cells.append({**{k: r[k] for k in first}, **{m: fmt_ci(r[m], r[f"{m}_lo"], r[f"{m}_hi"]) + mark for m in METRICS},
                      "seeds": f"{r['n_seeds']} ({r['seeds']})", "frames": r["frames"], "episodes": r["episodes"],
                      "wall s (mean)": r.get("wall_s", ""), "advisor calls (rows answered, cached)": r.get("advisor_calls", ""),
                      "commits": r["commits"]})
    return markdown_table(cells, head)


def final_episodes(run: Run) -> dict[str, list[float]] | None:
    """The per-episode DCR and SLR of a train run's final evaluation (``eval/frames_<frames>/episodes.csv``:
    data collected over data held, landed), or None when that file is missing."""
    rows = final_episode_rows(run)
    if rows is None:
        return None
    return {"DCR": [float(r["data_collected"]) / float(r["data_total"]) if float(r["data_total"]) > 0 else 0.0
                    for r in rows],
            "SLR": [1.0 if r["landed"] == "True" else 0.0 for r in rows]}


def learned_rows(train_rows: list[dict[str, Any]], runs: dict[str, list[Run]] | None = None) -> list[dict[str, Any]]:
    """A method has learned when its DCR and SLR intervals lie above the random policy's: the
    tables' 95% intervals (the stratified bootstrap where both kept their episodes), or, where
    either has t intervals and one seed only, t intervals over the episodes of that seed's final
    evaluation (the same scenarios for both; per-episode DCR, so its mean can differ a little from
    the pooled one of the tables)."""
    rand = next((r for r in train_rows if r["method"] == "random"), None)
    runs = runs or {}

    def one_seed_episodes(method: str) -> dict[str, list[float]] | None:
        return final_episodes(runs[method][0]) if len(runs.get(method, [])) == 1 else None

    rand_eps = one_seed_episodes("random")
    out = []
    for r in train_rows:
        if r["method"] in ("random", "heuristic", "llm"):
            continue
        row = {"method": r["method"], "n_seeds": r["n_seeds"]}
        # rows with bootstrap intervals (this one's and random's) compare those; else, with one seed,
        # the t intervals over that seed's evaluation episodes
        bootstrap = r.get("interval") == "bootstrap" and rand is not None and rand.get("interval") == "bootstrap"
        eps = one_seed_episodes(r["method"]) if rand_eps is not None and not bootstrap else None
        episodes = eps is not None
        verdicts = []
        for m in ("DCR", "SLR"):
            if episodes:
                ours, theirs = mean_ci(eps[m]), mean_ci(rand_eps[m])
            else:
                ours = (r[m], r[f"{m}_lo"], r[f"{m}_hi"])
                theirs = (rand[m], rand[f"{m}_lo"], rand[f"{m}_hi"]) if rand else (math.nan,) * 3
            row[m] = fmt_ci(*ours[:3])
            row[f"random_{m}"] = fmt_ci(*theirs[:3]) if rand else "n/a"
            if rand is None or math.isnan(ours[1]) or math.isnan(theirs[1]):
                verdicts.append(None)
            else:
                verdicts.append(ours[1] > theirs[2])
        if None in verdicts:
            row["learned"] = "undetermined (needs 2+ seeds of it and of random, or one seed's evaluation episodes)"
        else:
            row["learned"] = ("yes" if all(verdicts) else "no") + (
                f" (one seed: intervals over its {len(eps['DCR'])} evaluation episodes)" if episodes else "")
        out.append(row)
    return out


# ---------------------------------------------------------------------------- curves


def training_curve(run: Run, x: str) -> list[tuple[float, float]]:
    """The run's training episode return against frames (``x="frames"``) or against the
    training episodes ended so far (``x="episodes"``, from ``train/episodes`` at each step)."""
    ret = read_scalar(run.path, "episode/mean_return")
    if x == "frames":
        return ret
    eps = dict(read_scalar(run.path, "train/episodes"))
    return [(eps[s], v) for s, v in ret if s in eps]


def band(curves: list[list[tuple[float, float]]], n_points: int = 60) -> tuple[list[float], list[float], list[float], list[float]]:
    """Mean and 95% band over curves, each interpolated onto a common grid up to the shortest's end."""
    curves = [c for c in curves if len(c) >= 2]
    if not curves:
        return [], [], [], []
    end = min(c[-1][0] for c in curves)
    start = max(c[0][0] for c in curves)
    if end <= start:
        return [], [], [], []
    grid = [start + (end - start) * i / (n_points - 1) for i in range(n_points)]
    xs, ms, los, his = [], [], [], []
    for g in grid:
        vals = [_interp(c, g) for c in curves]
        m, lo, hi, _ = mean_ci(vals)
        xs.append(g)
        ms.append(m)
        los.append(m if math.isnan(lo) else lo)
        his.append(m if math.isnan(hi) else hi)
    return xs, ms, los, his


def _interp(c: list[tuple[float, float]], x: float) -> float:
    for (x0, y0), (x1, y1) in zip(c, c[1:]):
        if x0 <= x <= x1:
            return y0 if x1 == x0 else y0 + (y1 - y0) * (x - x0) / (x1 - x0)
    return c[-1][1] if x >= c[-1][0] else c[0][1]


# ---------------------------------------------------------------------------- figures


class Style:
    """One colour, marker and line style per method, fixed across figures (in greyscale the
    markers and dashes tell methods apart)."""

    def __init__(self, methods: list[str]):
        import matplotlib

        cmap = matplotlib.colormaps["tab10"]
        self.of = {m: (cmap(i % 10), MARKERS[i % len(MARKERS)], LINESTYLES[i % len(LINESTYLES)])
                   for i, m in enumerate(sorted(set(methods), key=method_key))}

    def kw(self, m: str) -> dict[str, Any]:
        c, mk, ls = self.of[m]
        return {"color": c, "marker": mk, "linestyle": ls, "markersize": 5, "label": m}


def fig_training(runs: list[Run], style: Style, out: Path, note: str) -> list[str]:
    import matplotlib.pyplot as plt

    by_method: dict[str, list[Run]] = defaultdict(list)
    for r in runs:
        by_method[r.method].append(r)
    files = []
    for x in ("episodes", "frames"):
        fig, ax = plt.subplots(figsize=(6.5, 4))
        drawn = 0
        for m in sorted(by_method, key=method_key):
            xs, ms, los, his = band([training_curve(r, x) for r in by_method[m]])
            if not xs:
                continue
            kw = style.kw(m)
            ax.plot(xs, ms, markevery=max(1, len(xs) // 8), **kw)
            ax.fill_between(xs, los, his, color=kw["color"], alpha=0.2, linewidth=0)
            drawn += 1
        if not drawn:
            plt.close(fig)
            continue
        ax.set_xlabel("training episodes" if x == "episodes" else "environment frames")
        ax.set_ylabel("episode return (training)")
        ax.set_title("Fig. 3: training curves (mean, 95% band over seeds)")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7, ncol=2)
        files += save_figure(fig, out, f"fig3_training_curves_{x}", note=note, dpi=FIGURE_DPI, tight=True)
    return files


def fig_lines(rows: list[dict[str, Any]], xkey: str, xlabel: str, title: str, style: Style, out: Path, stem: str,
              note: str, logx: bool = False, categorical: bool = False) -> list[str]:
    """Five panels (DCR, CR, SLR, RVR, ECR) against ``xkey``, one line per method, 95% bars."""
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(METRICS), figsize=(3.0 * len(METRICS), 3.2))
    cats = list(dict.fromkeys(r[xkey] for r in rows)) if categorical else []
    methods = sorted({r["method"] for r in rows}, key=method_key)
    for ax, metric in zip(axes, METRICS):
        for j, m in enumerate(methods):
            rs = [r for r in rows if r["method"] == m]
            if not categorical:
                rs.sort(key=lambda r: float(r[xkey]))
            xs = [cats.index(r[xkey]) + 0.08 * (j - len(methods) / 2) if categorical else float(r[xkey]) for r in rs]
            ys = [r[metric] for r in rs]
            err = [[0 if math.isnan(r[f"{metric}_lo"]) else r[metric] - r[f"{metric}_lo"] for r in rs],
                   [0 if math.isnan(r[f"{metric}_hi"]) else r[f"{metric}_hi"] - r[metric] for r in rs]]
            kw = style.kw(m)
            if categorical:
                kw["linestyle"] = "none"
            ax.errorbar(xs, ys, yerr=err, capsize=2, **kw)
        if categorical:
            ax.set_xticks(range(len(cats)), [str(c) for c in cats], rotation=30, fontsize=7)
        if logx:
            ax.set_xscale("log")
        ax.set_title(metric)
        ax.set_xlabel(xlabel)
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=6)
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    return save_figure(fig, out, stem, note=note, dpi=FIGURE_DPI, tight=True)


def fig_radar(rows: list[dict[str, Any]], style: Style, out: Path, note: str) -> list[str]:
    """Fig. 10: the mean over every setting per method; CR, RVR and ECR drawn as 1 - value so
    that outward is better on every axis."""
    import matplotlib.pyplot as plt

    axes_names = [m if m in HIGHER_BETTER else f"1-{m}" for m in METRICS]
    angles = [2 * math.pi * i / len(METRICS) for i in range(len(METRICS))]
    fig = plt.figure(figsize=(5, 5))
    ax = fig.add_subplot(polar=True)
    for r in sorted(rows, key=lambda r: method_key(r["method"])):
        vals = [r[m] if m in HIGHER_BETTER else 1 - r[m] for m in METRICS]
        if any(math.isnan(v) for v in vals):
            continue
        ax.plot(angles + angles[:1], vals + vals[:1], **style.kw(r["method"]))
    ax.set_xticks(angles, axes_names)
    ax.set_ylim(0, 1)
    ax.set_title("Fig. 10: mean over all settings (outward is better)", fontsize=10)
    ax.legend(fontsize=6, loc="upper right", bbox_to_anchor=(1.35, 1.1))
    return save_figure(fig, out, "fig10_summary_radar", note=note, dpi=FIGURE_DPI, tight=True)


# ---------------------------------------------------------------------------- the report


def sweep_commands(root: Path) -> list[str]:
    """The multirun commands that wrote ``root`` (from Hydra's ``multirun.yaml`` of each)."""
    out = []
    for f in sorted(root.glob(".multirun/*/*/multirun.yaml"), key=lambda f: f.parent.name):  # in the order they ran
        try:
            hc = yaml.safe_load(f.read_text())["hydra"]
            out.append(shlex.join(["python", "-m", f"uavlae.{hc['job']['name']}", "-m", *hc["overrides"]["task"]]))
        except (OSError, KeyError, TypeError, yaml.YAMLError):
            continue
    return list(dict.fromkeys(out))


@dataclass
class _Writer:
    """What :func:`build` writes into ``out``: each table as CSV and Markdown, the Markdown body of
    ``report.md`` in order, and what it returns (tables, figures)."""

    out: Path
    style: Style
    note: str
    result: dict[str, Any]
    md: list[str] = field(default_factory=list)

    def table(self, name: str, rows: list[dict[str, Any]], first: list[str], heading: str, text: str = "") -> None:
        write_csv(self.out / f"{name}.csv", rows)
        self.result["tables"][name] = rows
        lines = [f"## {heading}", ""] + ([text, ""] if text else []) + _md_table(rows, first) + [""]
        write_text(self.out / f"{name}.md", "\n".join(lines))
        self.md.extend(lines)

    def figures(self, files: list[str], images: list[str] | None = None) -> None:
        """``files`` written; ``images``: the Markdown image lines for them (default: one per PNG)."""
        self.result["figures"] += files
        self.md += images if images is not None else [f"![{f}]({f})" for f in files if f.endswith(".png")]
        self.md.append("")


def build(root: Path, out: Path, command: str | None = None) -> dict[str, Any]:
    """Collect, aggregate and write everything; returns what it wrote (the tests read it).
    ``command``: the command line that wrote it, as the report should show it (default: this
    module on ``root``). The report names no absolute path of ``root``, so that it reads the same
    wherever it is regenerated."""
    runs, skipped = collect(root)
    out.mkdir(parents=True, exist_ok=True)
    worlds = sorted({r.world for r in runs})
    note = "; ".join(worlds) if worlds else ""
    if any(w != "SPEC world" for w in worlds):
        note = "NOTE " + note + " (beyond the paper, SPEC §10)"
    w = _Writer(out, Style([r.method for r in runs] or ["none"]), note,
                {"runs": len(runs), "skipped": skipped, "tables": {}, "figures": []})
    write_csv(out / "runs.csv", [
        {"kind": r.kind, "sweep": r.sweep, "point": r.point, "method": r.method, "seed": r.seed,
         **{m: r.metrics.get(m) for m in METRICS}, "frames": r.frames, "episodes": r.episodes, "updates": r.updates,
         "wall_s": r.extra.get("wall_s"), "advisor_calls": r.extra.get("advisor_calls"),
         "world": r.world, "commit": r.commit, "dirty": r.dirty, "path": str(r.path.relative_to(root)), "command": r.command}
        for r in sorted(runs, key=lambda r: (r.sweep, r.point, method_key(r.method), r.seed))
    ])
    write_csv(out / "skipped.csv", [{"path": p, "reason": why} for p, why in skipped], ["path", "reason"])
    groups = group(runs)
    _train_section(w, runs, groups)
    _scenario_sections(w, runs, groups)
    _one_factor_sections(w, runs)
    _llm_sections(w, root, runs)
    for r in (r for r in runs if r.sweep == "long"):  # the long run(s): one method, one seed
        w.table(f"long_{r.method}", [aggregate_rows([r], {"method": r.method})], ["method"],
                f"Long run: {r.method}, {r.world}, {r.frames} frames, {r.episodes} episodes")
        figs = _fig_long(r, w.style, out, note)
        w.figures(figs, [f"![long]({f})" for f in figs if f.endswith(".png")])
    shown = display_path(root)
    command = command or shlex.join(["python", "-m", "uavlae.experiments.report", shown])
    text = _header(runs, skipped, worlds, shown, command) + w.md + _footer(root, runs, skipped)
    write_text(out / "report.md", "\n".join(text))
    result = w.result
    dump_json(out / "report.json", {k: v for k, v in result.items() if k != "tables"} | {"tables": result["tables"]})
    return result


def _train_section(w: _Writer, runs: list[Run], groups: dict[tuple[str, str, str], list[Run]]) -> None:
    """Fig. 3 and the final evaluation on the default distribution, and the learned test."""
    train = [r for r in runs if r.sweep == "train" and r.kind == "train"]
    train_rows = [aggregate_rows(groups[k], {"method": k[2]}) for k in sorted(
        {k for k in groups if k[0] == "train"}, key=lambda k: method_key(k[2]))]
    if not train_rows:
        return
    w.table("train_final", train_rows, ["method"], "Final evaluation, default distribution (train sweep)",
            "The deterministic actor on the shared evaluation set, over its seeds [95% interval].")
    learned = learned_rows(train_rows, {k[2]: groups[k] for k in groups if k[0] == "train"})
    write_csv(w.out / "learned.csv", learned)
    w.result["tables"]["learned"] = learned
    w.md += ["## Learned? (DCR and SLR above the uniform-random policy's, non-overlapping 95% intervals)", "",
             "| method | DCR | random DCR | SLR | random SLR | learned |", "|---|---|---|---|---|---|"]
    w.md += [f"| {r['method']} | {r['DCR']} | {r['random_DCR']} | {r['SLR']} | {r['random_SLR']} | {r['learned']} |"
             for r in learned]
    w.md.append("")
    w.figures(fig_training([r for r in train if r.config.get("controller", "learner") == "learner"], w.style, w.out,
                           w.note))


def _scenario_sections(w: _Writer, runs: list[Run], groups: dict[tuple[str, str, str], list[Run]]) -> None:
    """Figs. 5-9 (metrics against each count) and Fig. 10 (each seed's mean over all of them)."""
    per_seed: dict[tuple[str, int, str], list[float]] = defaultdict(list)
    grids: dict[str, list[Grid | None]] = defaultdict(list)  # method -> one grid per setting
    for sweep, (count, fig) in SCENARIO_SWEEPS.items():
        keys = [k for k in groups if k[0] == sweep]
        if not keys:
            continue
        rows = []
        for k in sorted(keys, key=lambda k: (int(k[1].split("=")[-1]), method_key(k[2]))):
            rows.append(aggregate_rows(groups[k], {count: int(k[1].split("=")[-1]), "method": k[2]}))
            grids[k[2]].append(episode_grid(groups[k]))
            for r in groups[k]:
                for m in METRICS:
                    per_seed[(r.method, r.seed, m)].append(r.metrics[m])
        title = f"{fig.replace('fig', 'Fig. ')}: metrics against {count}"
        w.table(f"{fig}_{sweep}", rows, [count, "method"], title)
        w.figures(fig_lines(rows, count, count, f"{title} (95% intervals)", w.style, w.out, f"{fig}_{sweep}",
                            w.note), [f"![{fig}]({fig}_{sweep}.png)"])
    if not per_seed:
        return
    rows = []
    for method in sorted({k[0] for k in per_seed}, key=method_key):
        row: dict[str, Any] = {"method": method}
        seeds = sorted({k[1] for k in per_seed if k[0] == method})
        settings = grids[method]
        bootstrap = all(g is not None and g.seeds == seeds for g in settings)
        for i, m in enumerate(METRICS):
            if bootstrap:
                row[m], row[f"{m}_lo"], row[f"{m}_hi"] = mean_interval(settings, m, N_BOOT, i)
            else:
                vals = [sum(per_seed[(method, s, m)]) / len(per_seed[(method, s, m)]) for s in seeds]
                row[m], row[f"{m}_lo"], row[f"{m}_hi"], _ = mean_ci(vals)
        row.update({"interval": "bootstrap" if bootstrap else "t", "n_seeds": len(seeds), "seeds": " ".join(map(str, seeds)), "frames": "", "episodes": "",
                    "commits": " ".join(sorted({r.commit + ("+dirty" if r.dirty else "") for r in runs
                                                if r.method == method and r.kind == "eval"}))})
        rows.append(row)
    w.table("fig10_summary", rows, ["method"], "Fig. 10: mean over all scenario settings",
            "The mean over every setting of Figs. 5-9 [95% interval: the stratified bootstrap drawing the seeds once "
            "for all settings and each setting's scenarios on their own, or (t) Student's t over each seed's mean].")
    w.figures(fig_radar(rows, w.style, w.out, w.note), ["![fig10](fig10_summary_radar.png)"])


def _one_factor_sections(w: _Writer, runs: list[Run]) -> None:
    """Figs. 11-12 and 13-14: one factor at a time around the defaults."""
    for sweep, axes_ in (("sensitivity", SENSITIVITY_AXES), ("llm_setting", LLM_AXES)):
        for name, label, fig, rows in one_factor_rows([r for r in runs if r.sweep == sweep], axes_):
            categorical = any(isinstance(r[label], str) for r in rows)
            stem = f"{fig}_{sweep}_{name}"
            title = f"{fig.replace('fig', 'Fig. ')}: sensitivity to {label}"
            w.table(stem, rows, [label, "method"], title)
            w.figures(fig_lines(rows, label, label, title, w.style, w.out, stem, w.note, categorical=categorical,
                                logx=name.endswith("lr") or name == "batch_size"), [f"![{name}]({stem}.png)"])


def _llm_sections(w: _Writer, root: Path, runs: list[Run]) -> None:
    """The LLM runs beside plain SAC at equal frames, and the LLM alone on the scenarios it scored."""
    equal = equal_frames_rows(runs)
    if equal:
        w.table("llm_equal_frames", equal, ["method", "setting"], "The LLM runs beside plain SAC at equal frames",
                "Each LLM run's final evaluation, and the evaluation of the train sweep's plain SAC runs at the same "
                "frame count (their learning curve's point): what the LLM's transitions changed at that budget.")
    alone = llm_alone_rows(root, runs)
    if alone:
        w.table("llm_alone", alone, ["method", "scenarios"],
                "The LLM alone, and every method on the scenarios it has scored",
                "The LLM alone (`+exp=llm`) decides every slot; a call budget per invocation pauses it between "
                "scenarios and the same command continues it, so it may cover only the first scenarios of the "
                "evaluation set. Beside it, every method of the train sweep on those scenarios (the same rows of its "
                "final evaluation, over seeds [95% interval]). The LLM alone's env draws the OU turns of scenario i "
                "from eval_seed + i (one scenario a chunk), the others' from one generator for the whole set: same "
                "layouts, GEs and OU starts, other OU turns. Its cost: decisions asked, HTTP calls (the rest from the "
                "answer cache), failed answers flown by the heuristic, and the wall clock over every invocation.")


def _header(runs: list[Run], skipped: list[tuple[str, str]], worlds: list[str], shown: str, command: str) -> list[str]:
    profiles = sorted({r.profile for r in runs if r.profile})
    return [
        "# Experiments report",
        "",
        f"Runs directory: `{shown}`  ",
        f"Written by: `{command}`  ",
        f"Profile(s): {', '.join(profiles) or 'none'}  ",
        f"World(s): {'; '.join(worlds) or 'none'}  ",
        f"Runs: {len(runs)} collected, {len(skipped)} skipped (below)  ",
        f"Commits: {', '.join(sorted({r.commit + ('+dirty' if r.dirty else '') for r in runs})) or 'none'}  ",
        f"Machine(s): {machines_line(runs)}",
        "",
        f"Intervals (95%): {METHOD_NAME.format(n=N_BOOT)}, where every run of a row kept its final evaluation's "
        "episodes; elsewhere the interval of the mean over seeds (Student's t, marked (t)), none for a single seed. "
        "DCR and SLR: higher is better; CR, RVR and ECR: lower is better.",
        "",
    ]


def _footer(root: Path, runs: list[Run], skipped: list[tuple[str, str]]) -> list[str]:
    versions = defaultdict(set)
    for r in runs:
        for k, v in (r.packages or {}).items():
            versions[k].add(str(v))
    footer = ["## Package versions", "", "| package | version(s) |", "|---|---|"]
    footer += [f"| {k} | {', '.join(sorted(v))} |" for k, v in sorted(versions.items())]
    footer += ["", "## Commands", "", "The sweeps (from Hydra's multirun records under the runs directory):", ""]
    footer += [f"- `{c}`" for c in sweep_commands(root)] or ["- none recorded"]
    footer += ["", "Each run's own command (it reruns that run alone) is in `runs.csv`.", "",
               "## Skipped runs", ""]
    footer += [f"- `{p}`: {why}" for p, why in skipped] or ["none"]
    footer.append("")
    return footer


def one_factor_rows(runs: list[Run], axes: tuple[tuple[str, str, str, str], ...]
                    ) -> list[tuple[str, str, str, list[dict[str, Any]]]]:
    """The runs of a one-factor-at-a-time sweep, per axis: those with every other axis at its
    default (the value most runs share), aggregated per (value, method); axes with fewer than two
    values are left out. Returns (name, label, figure, rows) per axis."""
    if not runs:
        return []
    defaults = {}
    for _, key, _, _ in axes:
        vals = [json.dumps(_select(r.config, key)) for r in runs]
        defaults[key] = json.loads(max(set(vals), key=vals.count))
    out = []
    for name, key, fig, label in axes:
        on_axis = [r for r in runs if all(_select(r.config, k) == v for k, v in defaults.items() if k != key)]
        by: dict[tuple[Any, str], list[Run]] = defaultdict(list)
        for r in on_axis:
            by[(_select(r.config, key), r.method)].append(r)
        if len({x for x, _ in by}) < 2:
            continue
        numeric = all(isinstance(x, (int, float)) for x, _ in by)
        order = sorted(by.items(), key=lambda kv: ((float(kv[0][0]) if numeric else str(kv[0][0])), method_key(kv[0][1])))
        out.append((name, label, fig, [aggregate_rows(v, {label: x, "method": m}) for (x, m), v in order]))
    return out


def equal_frames_rows(runs: list[Run]) -> list[dict[str, Any]]:
    """Every run whose advisor is an LLM, and beside each frame count they stopped at, the train
    sweep's plain SAC runs evaluated at that count (``eval/frames_<n>/metrics.json`` of their
    curve), so a short LLM run is read against SAC at its own budget, not at SAC's end."""
    llm = [r for r in runs if r.kind == "train" and (r.config.get("advisor") or {}).get("kind") == "llm"
           and r.config.get("controller", "learner") == "learner"]
    sac = [r for r in runs if r.kind == "train" and r.sweep == "train" and r.method == "sac"]
    rows = []
    for frames in sorted({r.frames for r in llm}):
        at = []
        for r in sac:
            f = train_eval_dir(r.path, frames) / "metrics.json"
            if f.is_file():
                at.append(replace(r, metrics=_metrics_of(read_json(f)), frames=frames, episodes=0,
                                              extra={}))
        if at:
            rows.append(aggregate_rows(at, {"method": "sac", "setting": f"train sweep, its evaluation at {frames} frames"}))
            rows[-1]["episodes"] = ""
        here = group([r for r in llm if r.frames == frames])
        for sweep, point, method in sorted(here, key=lambda k: (method_key(k[2]), k[0], k[1])):
            rows.append(aggregate_rows(here[(sweep, point, method)], {"method": method, "setting": f"{sweep}/{point}"}))
    return rows


def _spans(rows: list[int]) -> str:
    """Sorted scenario indices as runs: [0, 1, 2, 4] -> "0-2, 4"."""
    out: list[str] = []
    for i in rows:
        if out and int(out[-1].split("-")[-1]) == i - 1:
            out[-1] = f"{out[-1].split('-')[0]}-{i}"
        else:
            out.append(str(i))
    return ", ".join(out)


def llm_alone_rows(root: Path, runs: list[Run]) -> list[dict[str, Any]]:
    """The LLM alone of the train sweep (``+exp=llm``), finished or paused by its call budget, on
    the scenarios it has scored, and beside it every other method of the train sweep on those same
    scenarios: the rows of its final evaluation's ``episodes.csv`` (one episode per scenario, row i
    = scenario i), the metrics of that subset over the seeds [95% interval]. Which
    scenarios it has scored is the ``row`` column of its own ``episodes.csv`` (shards finish
    chunks out of order); without that file, the set's first ``eval/episodes_scored``."""
    import torch

    out = []
    for cfg_file in sorted((root / "train").glob("*/seed*/config.json")):
        d = cfg_file.parent
        if read_json(cfg_file).get("controller") != "llm" or not (d / "final_metrics.json").is_file():
            continue
        try:
            alone = _train_run(d, partial=True)
        except (LookupError, ValueError):
            continue  # collect() lists it as skipped
        k, n = alone.extra.get("episodes_scored", 0), alone.extra.get("episodes_total", 0)
        if k == 0:
            continue
        own = train_eval_dir(d, 0) / "episodes.csv"
        scored = sorted(int(i) for i in load_records(own)["row"].tolist()) if own.is_file() else list(range(k))
        scen = f"{_spans(scored)} ({k} of {n})"
        row = aggregate_rows([alone], {"method": alone.method, "scenarios": scen})
        row["episodes"] = str(k)
        row["advisor_calls"] = (f"{alone.extra.get('calls', 0)} decisions, {alone.extra.get('http_calls', 0)} HTTP, "
                                f"{alone.extra.get('fallbacks', 0)} fallbacks")
        out.append(row)
        others: dict[str, list[Run]] = defaultdict(list)
        for r in runs:
            if r.kind != "train" or r.sweep != "train" or r.path == d:
                continue
            f = train_eval_dir(r.path, r.frames) / "episodes.csv"
            if not f.is_file():
                continue
            rec = load_records(f)
            pick = torch.isin(rec["row"], torch.tensor(scored))
            if int(pick.sum()) != len(scored):
                continue  # not one episode per scenario
            others[r.method].append(replace(r, metrics=_metrics_of(aggregate({c: v[pick] for c, v in rec.items()}))))
        for method in sorted(others, key=method_key):
            out.append(aggregate_rows(others[method], {"method": method, "scenarios": scen}, scored))
    return out


def _fig_long(r: Run, style: Style, out: Path, note: str) -> list[str]:
    import matplotlib.pyplot as plt

    fig, (a, b) = plt.subplots(1, 2, figsize=(10, 3.5))
    c = training_curve(r, "frames")
    if c:
        a.plot([x for x, _ in c], [y for _, y in c], **{**style.kw(r.method), "marker": None})
    a.set_xlabel("environment frames")
    a.set_ylabel("episode return (training)")
    a.grid(alpha=0.3)
    for m in METRICS:
        e = read_scalar(r.path, f"eval/{m}")
        if e:
            b.plot([x for x, _ in e], [y for _, y in e], label=m, marker=MARKERS[METRICS.index(m)],
                   linestyle=LINESTYLES[METRICS.index(m) % len(LINESTYLES)])
    b.set_xlabel("environment frames")
    b.set_ylabel("evaluation metric")
    b.legend(fontsize=7)
    b.grid(alpha=0.3)
    fig.suptitle(f"Long run: {r.method} ({r.world}), seed {r.seed}", fontsize=10)
    fig.tight_layout()
    return save_figure(fig, out, f"long_{r.method}", note=note, dpi=FIGURE_DPI, tight=True)


def display_path(path: Path) -> str:
    """``path`` relative to the working directory when it lies inside it (a report names no
    folder of the machine that wrote it), else its last part alone."""
    path = Path(path).resolve()
    try:
        return path.relative_to(Path.cwd().resolve()).as_posix() or "."
    except ValueError:
        return path.name


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(prog="uavlae-report", description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("runs_dir", type=Path, help="a sweeps' experiment.root (e.g. runs/quick), or a folder of run "
                   "records (e.g. results/quick/runs)")
    p.add_argument("--out", type=Path, default=None, help="where to write (default RUNS_DIR/report)")
    a = p.parse_args(sys.argv[1:] if argv is None else argv)
    if not a.runs_dir.is_dir():
        p.error(f"{a.runs_dir} is not a directory")
    import matplotlib

    matplotlib.use("Agg")
    command = ["python", "-m", "uavlae.experiments.report", display_path(a.runs_dir)]
    command += ["--out", display_path(a.out)] if a.out else []
    res = build(a.runs_dir.resolve(), (a.out or a.runs_dir / "report").resolve(), shlex.join(command))
    print(f"{res['runs']} runs, {len(res['skipped'])} skipped, {len(res['figures'])} figure files -> "
          f"{(a.out or a.runs_dir / 'report') / 'report.md'}")
    for path, why in res["skipped"]:
        print(f"  skipped {path}: {why}", file=sys.stderr)


if __name__ == "__main__":
    main()
