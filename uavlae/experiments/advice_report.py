"""``python -m uavlae.experiments.advice report results/advice``: the advice study's tables, figures and
``report.md``, from the CSV records alone (``runs.csv``, ``episodes.csv``, ``curves.csv``,
``claims_runs.csv``, ``claims_episodes.csv``; :mod:`uavlae.experiments.advice` writes them).

Cells are (world, transfer, method). Every interval is the stratified bootstrap of
:mod:`uavlae.experiments.advice_stats` over seeds x the 32 evaluation scenarios. The report has:
the design and what of it is done; each cell's actor alone and actor with its advisor; the
dependence on the advisor (advised fraction, trigger rate early and late, agreement); the
difference and the probability of improvement of each advised cell against plain SAC in its
world; the "learned" test against the uniform-random policy; the tuning of the cloning weight;
the quick profile's SAC+Heuristic rows against their rerun with the per-row greedy advisor;
and one verdict per claim of the paper.
"""

from __future__ import annotations

import math
import zlib
from collections import defaultdict
from pathlib import Path
from typing import Any

from uavlae.experiments.advice_stats import (
    METHOD_NAME,
    METRICS,
    Grid,
    difference,
    grid_from_rows,
    interval,
    on_shared_seeds,
    point,
    probability_of_improvement,
)
from uavlae.experiments.reporting import fmt_interval, markdown_table, read_rows, save_figure, write_text

N_BOOT = 2000
NONE_YET = "(none yet)"  # a table without rows
WORLDS = {"aid": "learning-aid world (env=shaped_geodesic, 400k frames)", "spec": "SPEC's world (env=default, 1M frames)"}
TRANSFERS = {"override": "the paper's override", "teach": "override + cloning + phase-out", "aid": "no advisor, one learning aid",
             "tune": "tuning (seeds apart)"}
ADVISORS = {"sac": "none", "sac_heuristic": "greedy heuristic", "sac_heuristic_planner": "planner", "sac_hover": "hover",
            "sac_random_advice": "uniform random", "sac_llm": "local LLM (SmolLM2-135M)",
            "sac_llm_amortized": "local LLM (SmolLM2-135M) through the student",
            "sac_ego_only": "none (ego-centric columns only)", "sac_progress_only": "none (progress reward only)"}
# the study's design: (world, transfer, method, seeds)
DESIGN = (
    *[("aid", "override", m, 5) for m in ("sac", "sac_heuristic", "sac_heuristic_planner", "sac_hover",
                                          "sac_random_advice")],
    *[("aid", "teach", m, 5) for m in ("sac_heuristic", "sac_heuristic_planner", "sac_hover", "sac_random_advice")],
    *[("spec", "override", m, 3) for m in ("sac", "sac_heuristic")],
    ("spec", "teach", "sac_heuristic", 3),
    *[("spec", "aid", m, 3) for m in ("sac_ego_only", "sac_progress_only")],
    # the LLM at every trigger, through the student at its stated budget (+exp=sac_llm_amortized)
    *[("aid", t, "sac_llm_amortized", 3) for t in ("override", "teach")],
)


def _num(v: Any) -> float:
    try:
        return float(v)
    except (TypeError, ValueError):
        return math.nan


class Records:
    """The study's records, grouped by cell."""

    def __init__(self, d: Path):
        self.runs = read_rows(d / "runs.csv")
        self.episodes = read_rows(d / "episodes.csv")
        self.curves = read_rows(d / "curves.csv")
        self.claim_runs = read_rows(d / "claims_runs.csv")
        self.claim_episodes = read_rows(d / "claims_episodes.csv")
        self.unfinished = [r["path"] for r in read_rows(d / "unfinished.csv")]
        self.by_cell: dict[tuple[str, str, str, str], list[dict[str, str]]] = defaultdict(list)
        for e in self.episodes:
            self.by_cell[(e["world"], e["transfer"], e["method"], e["evaluation"])].append(e)
        self.claims: dict[tuple[str, str, str], list[dict[str, str]]] = defaultdict(list)
        for e in self.claim_episodes:
            self.claims[(e["transfer"], e["method"], e["evaluation"])].append(e)

    def grid(self, world: str, transfer: str, method: str, evaluation: str = "alone") -> Grid | None:
        rows = self.by_cell.get((world, transfer, method, evaluation))
        return grid_from_rows(rows) if rows else None

    def baseline(self, world: str, who: str) -> Grid | None:
        """The heuristic or random baseline of a world: the same policy and scenarios in every
        run, so one run's episodes (seed 0 of its grid)."""
        for (w, _, _, ev), rows in sorted(self.by_cell.items()):
            if w == world and ev == who:
                first = min(int(r["seed"]) for r in rows)
                return grid_from_rows([{**r, "seed": 0} for r in rows if int(r["seed"]) == first])
        return None

    def cells(self) -> list[tuple[str, str, str]]:
        order = {(w, t, m): i for i, (w, t, m, _) in enumerate(DESIGN)}
        found = {(w, t, m) for (w, t, m, ev) in self.by_cell if ev == "alone"}
        return sorted(found, key=lambda c: (order.get(c, len(order)), c))

    def run_rows(self, world: str, transfer: str, method: str) -> list[dict[str, str]]:
        return [r for r in self.runs if (r["world"], r["transfer"], r["method"]) == (world, transfer, method)]


def cell_label(method: str, transfer: str) -> str:
    return f"{method} / {transfer}"


def cell_seed(world: str, transfer: str, method: str) -> int:
    """The bootstrap's random seed for one cell, from its name: a cell added to the study leaves
    every other cell's intervals as they were (a seed from the cell's position would not)."""
    return zlib.crc32(f"{world}/{transfer}/{method}".encode())


def metric_cells(g: Grid | None, seed: int) -> dict[str, str]:
    if g is None:
        return {m: "" for m in METRICS}
    return {m: fmt_interval(*interval(g, m, N_BOOT, seed)) for m in METRICS}


def cells_table(rec: Records, world: str) -> list[dict[str, Any]]:
    rows = []
    for w, t, m in (c for c in rec.cells() if c[0] == world):
        alone = rec.grid(w, t, m)
        row = {"cell": cell_label(m, t), "advisor": ADVISORS.get(m.split("_w")[0], m), "transfer": TRANSFERS.get(t, t),
               "seeds": " ".join(map(str, alone.seeds)) if alone else ""}
        row.update(metric_cells(alone, seed=cell_seed(w, t, m)))
        rows.append(row)
    return rows


def _mean(runs: list[dict[str, str]], key: str) -> float:
    """The mean of ``key`` over the runs that recorded it (NaN where none did)."""
    xs = [_num(r.get(key)) for r in runs]
    xs = [x for x in xs if math.isfinite(x)]
    return sum(xs) / len(xs) if xs else math.nan


def dependence_table(rec: Records, world: str) -> list[dict[str, Any]]:
    """Per advised cell: the advised fraction of stored transitions and the trigger rate (means
    over seeds), the trigger rate over the first and the last fifth of training, the agreement
    of the actor with executed advice, and DCR / SLR alone and with the advisor."""
    rows = []
    for w, t, m in (c for c in rec.cells() if c[0] == world):
        i = cell_seed(w, t, m)
        runs = rec.run_rows(w, t, m)
        if not runs or all(r.get("advisor", "none") == "none" for r in runs):
            continue

        early, late = trigger_phases(rec, w, t, m)
        alone, withadv = rec.grid(w, t, m), rec.grid(w, t, m, "with_advisor")
        row = {"cell": cell_label(m, t), "advised fraction": f"{_mean(runs, 'override/advised_fraction'):.3f}",
               "trigger rate": f"{_mean(runs, 'override/trigger_rate'):.3f}",
               "trigger, first / last fifth": f"{early:.3f} / {late:.3f}",
               "actor within tol of advice": f"{_mean(runs, 'override/actor_agree'):.3f}",
               "actor-advice gap": f"{_mean(runs, 'override/actor_gap'):.3f}"}
        for metric in ("DCR", "SLR", "CR"):
            row[f"{metric} alone"] = fmt_interval(*interval(alone, metric, N_BOOT, i)) if alone else ""
            row[f"{metric} with advisor"] = fmt_interval(*interval(withadv, metric, N_BOOT, i)) if withadv else ""
        # with a row budget at that evaluation, the actor answered the rest: what "with advisor" means
        triggered = _mean(runs, "advised/override/triggered")
        row["triggered rows advised, with advisor"] = (f"{_mean(runs, 'advised/override/advised') / triggered:.3f}"
                                                       if triggered > 0 else "–")
        calls = [r.get("max_calls") for r in runs if r.get("max_calls") not in (None, "", "None")]
        row["advisor budget"] = f"max_calls {calls[0]}" if calls else "none"
        if any(str(r.get("amortize")) == "True" for r in runs):  # who answered the advised rows
            llm, student = _mean(runs, "override/source/llm"), _mean(runs, "override/source/student")
            row["advisor budget"] = f"student; LLM {llm / (llm + student):.1%} of advised rows" \
                if llm + student > 0 else "student"
            ev_llm, ev_student = _mean(runs, "advised/override/source/llm"), _mean(runs, "advised/override/source/student")
            if ev_llm + ev_student > 0:  # recorded by runs made since the evaluation counts who answered
                row["advisor budget"] += f" ({ev_llm / (ev_llm + ev_student):.1%} with advisor)"
        rows.append(row)
    return rows


def trigger_phases(rec: Records, world: str, transfer: str, method: str) -> tuple[float, float]:
    """The logged trigger rate averaged over the first and the last fifth of training (over seeds)."""
    early, late = [], []
    by_seed: dict[str, list[tuple[int, float]]] = defaultdict(list)
    for c in rec.curves:
        if (c["world"], c["transfer"], c["method"]) == (world, transfer, method) and c.get("trigger_rate") not in ("", None):
            by_seed[c["seed"]].append((int(c["frames"]), float(c["trigger_rate"])))
    for pts in by_seed.values():
        end = max(f for f, _ in pts)
        early += [v for f, v in pts if f <= end / 5]
        late += [v for f, v in pts if f > 4 * end / 5]
    avg = lambda xs: sum(xs) / len(xs) if xs else math.nan  # noqa: E731
    return avg(early), avg(late)


def against_plain(rec: Records, world: str) -> list[tuple[int, str, str, Grid, Grid]]:
    """Every advised or aided cell of ``world`` with plain SAC (``sac / override``), both on the
    seeds both ran: (bootstrap seed, transfer, method, cell, plain SAC). A cell with fewer seeds is not
    set against plain SAC's other seeds, whose luck it did not share."""
    base = rec.grid(world, "override", "sac")
    if base is None:
        return []
    out = []
    for w, t, m in (c for c in rec.cells() if c[0] == world):
        if (t, m) == ("override", "sac") or t == "tune":
            continue
        pair = on_shared_seeds(rec.grid(w, t, m), base)
        if pair is not None:
            out.append((cell_seed(w, t, m), t, m, *pair))
    return out


def comparison_table(rec: Records, world: str) -> list[dict[str, Any]]:
    """Each cell against plain SAC (``sac / override``) in the same world, on the seeds both ran:
    DCR, SLR and CR differences (paired bootstrap) and the probability of improvement."""
    rows = []
    for i, t, m, g, base in against_plain(rec, world):
        row = {"cell": cell_label(m, t), "seeds": " ".join(map(str, g.seeds))}
        for metric in ("DCR", "SLR", "CR"):
            row[f"Δ{metric}"] = fmt_interval(*difference(g, base, metric, N_BOOT, i))
            row[f"P(better) {metric}"] = fmt_interval(*probability_of_improvement(g, base, metric, N_BOOT, i), digits=2)
        rows.append(row)
    return rows


def learned_table(rec: Records, world: str) -> list[dict[str, Any]]:
    """Learned: DCR and SLR intervals wholly above the uniform-random policy's on the same scenarios."""
    rnd = rec.baseline(world, "random")
    if rnd is None:
        return []
    r_dcr, r_slr = interval(rnd, "DCR", N_BOOT, 99), interval(rnd, "SLR", N_BOOT, 98)
    rows = []
    for w, t, m in (c for c in rec.cells() if c[0] == world):
        g = rec.grid(w, t, m)
        i = cell_seed(w, t, m)
        dcr, slr = interval(g, "DCR", N_BOOT, i), interval(g, "SLR", N_BOOT, i)
        learned = dcr[1] > r_dcr[2] and slr[1] > r_slr[2]
        rows.append({"cell": cell_label(m, t), "DCR": fmt_interval(*dcr), "SLR": fmt_interval(*slr), "random DCR": fmt_interval(*r_dcr),
                     "random SLR": fmt_interval(*r_slr), "learned": "yes" if learned else "no"})
    return rows


def wall_ratio(rec: Records, world: str, transfer: str, method: str) -> float:
    """A cell's mean training wall clock per run over plain SAC's in the same world."""
    base = _mean(rec.run_rows(world, "override", "sac"), "wall_s")
    return _mean(rec.run_rows(world, transfer, method), "wall_s") / base if base > 0 else math.nan


def cost_table(rec: Records, world: str) -> list[dict[str, Any]]:
    """Per cell, means per run: the training wall clock (and its ratio to plain SAC's), the rows
    an advisor answered, and for the LLM the rows it answered, the tokens and the time waited."""
    rows = []
    for w, t, m in (c for c in rec.cells() if c[0] == world):
        runs = rec.run_rows(w, t, m)
        if not runs:
            continue
        llm = _mean(runs, "cost/rows_llm")
        dash = lambda v, f: f.format(v) if math.isfinite(v) else "–"  # noqa: E731
        rows.append({"cell": cell_label(m, t), "runs": len(runs),
                     "training wall clock per run": dash(_mean(runs, "wall_s") / 60, "{:.0f} min"),
                     "x plain SAC": dash(wall_ratio(rec, w, t, m), "{:.2f}"),
                     "advised rows per run": dash(_mean(runs, "override/advised"), "{:,.0f}"),
                     "LLM rows per run": dash(llm, "{:,.0f}"),
                     "asked live / from the answer cache": (f"{_mean(runs, 'cost/llm_calls'):,.0f} / "
                                                            f"{_mean(runs, 'cost/llm_cache_hits'):,.0f}")
                     if math.isfinite(llm) else "–",
                     "LLM tokens in / out per run": (f"{_mean(runs, 'cost/tokens_in'):,.0f} / "
                                                     f"{_mean(runs, 'cost/tokens_out'):,.0f}") if math.isfinite(llm) else "–",
                     "waiting for the LLM per run": dash(_mean(runs, "cost/wait_s") / 60, "{:.0f} min")})
    return rows


def tuning_table(rec: Records) -> list[dict[str, Any]]:
    rows = []
    for w, t, m in (c for c in rec.cells() if c[1] == "tune"):
        g = rec.grid(w, t, m)
        i = cell_seed(w, t, m)
        w_ = [r.get("clone_weight") for r in rec.run_rows(w, t, m)]
        score = (point(g, "DCR") + point(g, "SLR")) / 2
        rows.append({"clone_weight": w_[0] if w_ else "", "seeds": " ".join(map(str, g.seeds)),
                     "DCR": fmt_interval(*interval(g, "DCR", N_BOOT, i)), "SLR": fmt_interval(*interval(g, "SLR", N_BOOT, i)),
                     "mean of DCR and SLR (the choice)": f"{score:.3f}"})
    return sorted(rows, key=lambda r: _num(r["clone_weight"]))


def claims_grid(rec: Records, transfer: str, method: str, evaluation: str = "alone") -> Grid | None:
    rows = rec.claims.get((transfer, method, evaluation))
    return grid_from_rows(rows) if rows else None


def rerun_table(rec: Records) -> list[dict[str, Any]]:
    """The quick profile's committed SAC+Heuristic (its advisor forgot each row's memory when the
    triggered set changed) against the study's rerun with the per-row greedy advisor, same seeds
    and settings."""
    old = claims_grid(rec, "default", "sac_heuristic")
    new = rec.grid("aid", "override", "sac_heuristic")
    rows = []
    for label, g in (("quick profile, committed (advisor memory reset per call)", old),
                     ("rerun, greedy advisor per env row", new.take([s for s in new.seeds if s in (old.seeds if old else [])])
                      if new is not None and old is not None else new)):
        if g is None or not g.seeds:
            continue
        rows.append({"sac_heuristic": label, "seeds": " ".join(map(str, g.seeds)), **metric_cells(g, seed=7)})
    return rows


def claim_rows(rec: Records) -> list[dict[str, Any]]:
    """One row per claim of the paper, judged on the quick profile's runs and the study."""
    out: list[dict[str, Any]] = []
    llm = claims_grid(rec, "default", "sac_llm")
    quick = "`make quick` and `make quick-llm` (results/quick), records in results/advice/claims_*.csv"

    def row(claim: str, verdict: str, evidence: str, command: str = quick) -> None:
        out.append({"claim": claim, "verdict": verdict, "evidence": evidence, "command": command})

    if llm is None:
        row("the quick profile's claims", "untestable here", "the quick profile's SAC+LLM records are missing")
        rung_claim(rec, row)
        return out
    learners = {m: claims_grid(rec, "default", m) for m in ("sac_llm", "sac_heuristic", "sac", "ppo")}
    heur = claims_grid(rec, "default", "sac", "heuristic")
    dcr = {m: interval(g, "DCR", N_BOOT, 1) for m, g in learners.items() if g is not None}
    if heur is not None:
        dcr["heuristic (greedy, alone)"] = interval(heur, "DCR", N_BOOT, 1)
    above = [m for m in dcr if m != "sac_llm" and dcr[m][1] > dcr["sac_llm"][2]]
    wins = all(dcr["sac_llm"][1] > v[2] for m, v in dcr.items() if m != "sac_llm")
    row("SAC+LLM is best on DCR", "holds" if wins else ("does not hold" if above else "not shown (intervals overlap)"),
        "DCR " + "; ".join(f"{m} {fmt_interval(*v)}" for m, v in dcr.items()))
    cr = interval(llm, "CR", N_BOOT, 2)
    row("SAC+LLM's CR is near 0", "holds" if cr[2] <= 0.05 else "does not hold",
        f"CR {fmt_interval(*cr)} (near 0: the interval within [0, 0.05])")
    rvr = interval(llm, "RVR", N_BOOT, 3)
    row("SAC+LLM's RVR is 0", "holds" if rvr[2] == 0 else "does not hold", f"RVR {fmt_interval(*rvr)}")
    slr = interval(llm, "SLR", N_BOOT, 4)
    row("SAC+LLM's SLR is near 100%", "holds" if slr[1] >= 0.95 else "does not hold",
        f"SLR {fmt_interval(*slr)} (near 100%: the interval within [0.95, 1])")
    dth = {}
    for key in rec.claims:
        t, m, ev = key
        if m == "sac_llm" and ev == "alone" and t.startswith("d_th=") and t.endswith("prompt=none"):
            dth[float(t.split("=")[1].split("_")[0])] = claims_grid(rec, t, m)
    if dth:
        iv = {d: interval(g, "DCR", N_BOOT, 5) for d, g in sorted(dth.items())}
        others_below = all(iv[d][2] < iv[15.0][1] for d in iv if d != 15.0) if 15.0 in iv else False
        some_above = any(iv[d][1] > iv[15.0][2] for d in iv if d != 15.0) if 15.0 in iv else False
        verdict = "holds" if others_below else ("does not hold" if some_above else "not shown (intervals overlap)")
        row("d_th = 15 m is best", verdict, "DCR by d_th: " + "; ".join(f"{d:g} m {fmt_interval(*v)}" for d, v in iv.items()),
            "`make quick-llm` (the d_th sweep, 50k frames, 100 LLM rows a run)")
    prompts = {t.split("prompt=")[1]: claims_grid(rec, t, m) for (t, m, ev) in rec.claims
               if m == "sac_llm" and ev == "alone" and t.startswith("d_th=15.0_prompt=")}
    if "none" in prompts:
        full = prompts.pop("none")
        diffs = {p: difference(full, g, "DCR", N_BOOT, 6) for p, g in sorted(prompts.items())}
        matters = [p for p, d in diffs.items() if d[1] > 0]
        hurts = [p for p, d in diffs.items() if d[2] < 0]
        verdict = ("holds" if len(matters) == len(diffs) else "holds in part" if matters
                   else "does not hold" if hurts else "not shown (every interval holds 0)")
        row("each prompt guideline matters", verdict,
            "DCR of the complete prompt minus each ablation: " + "; ".join(f"{p} {fmt_interval(*d)}" for p, d in diffs.items()),
            "`make quick-llm` (the prompt sweep, 50k frames, 100 LLM rows a run)")
    sh = learners.get("sac_heuristic")
    fps = {m: claims_grid(rec, "default", m) for m in ("sac_llm_fp0.3", "sac_llm_fp0.4", "sac_llm_fp0.5", "sac_llm_fp1.0")}
    parts = []
    better = []
    if sh is not None:
        d = difference(llm, sh, "DCR", N_BOOT, 7)
        parts.append(f"SAC+LLM - SAC+Heuristic DCR {fmt_interval(*d)}")
        better.append(1 if d[1] > 0 else -1 if d[2] < 0 else 0)
    fp_iv = {m: interval(g, "DCR", N_BOOT, 8) for m, g in fps.items() if g is not None}
    if fp_iv:
        parts.append("fp variants DCR " + "; ".join(f"{m} {fmt_interval(*v)}" for m, v in fp_iv.items())
                     + " (at 50k frames, 100 LLM rows: not the same budget as SAC+LLM's 400k)")
    row("SAC+LLM is better than SAC+Heuristic and the fixed-probability variants",
        "holds" if better and all(b > 0 for b in better) else "does not hold" if any(b < 0 for b in better)
        else "not shown", "; ".join(parts))
    rung_claim(rec, row)
    row("DeepSeek-R1's advice is what makes SAC+LLM work", "untestable here",
        "the local model is SmolLM2-135M (flown alone: DCR 0.08, as uniform random); the study's ladder of advisors "
        "of known quality (hover, random, greedy, planner, the local LLM) shows instead what advice of a given quality "
        "does to the actor", "`make advice-study`")
    return out


def rung_claim(rec: Records, row: Any) -> None:
    """SAC+LLM against SAC+Heuristic with the LLM at every trigger (the study's LLM rung, through
    the student), on the seeds both ran, under each transfer."""
    claim = "SAC+LLM is better than SAC+Heuristic, the LLM advising at every trigger (the study's LLM rung)"
    command = "`make advice-llm` from a checkout with the student (uavlae/experiments/README.md)"
    parts, signs = [], []
    for i, transfer in enumerate(("override", "teach")):
        llm, heur = rec.grid("aid", transfer, "sac_llm_amortized"), rec.grid("aid", transfer, "sac_heuristic")
        pair = on_shared_seeds(llm, heur) if llm is not None and heur is not None else None
        if pair is None:
            continue
        x, y = pair
        both = x.seeds
        d = {metric: difference(x, y, metric, N_BOOT, 20 + i) for metric in ("DCR", "SLR")}
        parts.append(f"{TRANSFERS[transfer]}, seeds {' '.join(map(str, both))}: ΔDCR {fmt_interval(*d['DCR'])}, "
                     f"ΔSLR {fmt_interval(*d['SLR'])}")
        signs += [1 if v[1] > 0 else -1 if v[2] < 0 else 0 for v in d.values()]
    if not parts:
        row(claim, "pending", "the LLM rung has no finished run yet", command)
        return
    verdict = ("does not hold" if any(s < 0 for s in signs) else "holds" if all(s > 0 for s in signs)
               else "not shown (intervals hold 0)")
    rung = [r for r in progress_rows(rec) if (r["world"], r["method"]) == ("aid", "sac_llm_amortized")]
    if any(r["state"] != "done" for r in rung):
        verdict += " so far (seeds done: " + ", ".join(f"{r['transfer']} {r['seeds done']} of {r['seeds wanted']}"
                                                       for r in rung) + ")"
    row(claim, verdict, "learning-aid world, the actor alone, LLM rung minus greedy heuristic: " + "; ".join(parts),
        command)


def findings(rec: Records) -> list[str]:
    """Sentences that read the tables: per world, which cells beat plain SAC alone on DCR or SLR."""
    lines = []
    for world in WORLDS:
        if rec.grid(world, "override", "sac") is None:
            continue
        better, worse = [], []
        for i, t, m, g, base in against_plain(rec, world):
            ratio = wall_ratio(rec, world, t, m)
            cost = f"; {ratio:.2f}x plain SAC's training wall clock" if math.isfinite(ratio) else ""
            for metric in ("DCR", "SLR"):
                d = difference(g, base, metric, N_BOOT, i)
                if d[1] > 0:
                    better.append(f"{cell_label(m, t)} on {metric} ({fmt_interval(*d)}{cost})")
                elif d[2] < 0:
                    worse.append(f"{cell_label(m, t)} on {metric} ({fmt_interval(*d)}{cost})")
        lines.append(f"- **{WORLDS[world]}**: the actor alone beats plain SAC's, with the difference's interval above 0: "
                     + ("; ".join(better) if better else "no cell") + ". Worse than plain SAC: "
                     + ("; ".join(worse) if worse else "no cell") + ".")
        learned = {r["cell"]: r["learned"] == "yes" for r in learned_table(rec, world)}
        if learned and not learned.get(cell_label("sac", "override"), True):
            found = [c for c, yes in learned.items() if yes and not c.endswith("/ tune")]
            lines.append(f"- **{WORLDS[world]}**: plain SAC did not learn (DCR and SLR not above random's). "
                         + ("Learned where it did not: " + ", ".join(found) if found else "No cell learned") + ".")
    return lines


def figures(rec: Records, out: Path) -> list[str]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    made = []
    for world in WORLDS:
        cells = [c for c in rec.cells() if c[0] == world and c[1] != "tune"]
        if not cells:
            continue
        fig, axes = plt.subplots(1, 2, figsize=(11, 0.45 * len(cells) + 1.8), sharey=True)
        labelled: set[str] = set()  # each evaluation named once (plain SAC, first, has no advisor)
        for ax, metric in zip(axes, ("DCR", "SLR")):
            for j, (w, t, m) in enumerate(cells):
                for k, (ev, colour) in enumerate((("alone", "tab:blue"), ("with_advisor", "tab:orange"))):
                    g = rec.grid(w, t, m, ev)
                    if g is None:
                        continue
                    p, lo, hi = interval(g, metric, N_BOOT, cell_seed(w, t, m))
                    y = j + (0.15 if k else -0.15)
                    ax.errorbar([p], [y], xerr=[[p - lo], [hi - p]], fmt="o", color=colour,
                                label=None if ev in labelled else ("actor alone" if ev == "alone"
                                                                   else "actor with its advisor"))
                    labelled.add(ev)
            ax.set_xlabel(f"{metric} (95% stratified bootstrap)")
            ax.set_xlim(-0.02, 1.02)
            ax.grid(alpha=0.3)
        axes[0].set_yticks(range(len(cells)), [cell_label(m, t) for _, t, m in cells])
        fig.legend(loc="upper right", ncol=2, fontsize=8)
        fig.suptitle(WORLDS[world], x=0.3)
        fig.tight_layout(rect=(0, 0, 1, 0.95))
        made += save_figure(fig, out, f"cells_{world}")
        # curves: the actor alone's DCR during training, and the trigger rate
        fig, axes = plt.subplots(1, 2, figsize=(11, 3.6))
        colours = plt.rcParams["axes.prop_cycle"].by_key()["color"]
        for i, (w, t, m) in enumerate(cells):  # one colour a cell in both panels
            for ax, col in zip(axes, ("DCR", "trigger_rate")):
                pts: dict[int, list[float]] = defaultdict(list)
                for c in rec.curves:
                    if (c["world"], c["transfer"], c["method"]) == (w, t, m) and c.get(col) not in ("", None):
                        pts[int(c["frames"])].append(float(c[col]))
                if pts and (col == "DCR" or m != "sac"):
                    xs = sorted(pts)
                    ax.plot(xs, [sum(pts[x]) / len(pts[x]) for x in xs], lw=1, color=colours[i % len(colours)],
                            label=cell_label(m, t) if ax is axes[0] else None)
        axes[0].set_title("actor alone, DCR during training (mean over seeds)")
        axes[1].set_title("trigger rate during training (mean over seeds)")
        for ax in axes:
            ax.set_xlabel("frames")
            ax.grid(alpha=0.3)
        if axes[0].get_legend_handles_labels()[0]:
            axes[0].legend(fontsize=7)
        fig.suptitle(WORLDS[world])
        fig.tight_layout()
        made += save_figure(fig, out, f"curves_{world}")
    return made


def progress_rows(rec: Records) -> list[dict[str, Any]]:
    have = defaultdict(set)
    for r in rec.runs:
        have[(r["world"], r["transfer"], r["method"])].add(int(r["seed"]))
    rows = []
    for w, t, m, n in DESIGN:
        done = len(have.get((w, t, m), ()))
        rows.append({"world": w, "transfer": t, "method": m, "seeds wanted": n, "seeds done": done,
                     "state": "done" if done >= n else "pending"})
    return rows


def compute_lines(rec: Records) -> list[str]:
    if not rec.runs:
        return ["No finished run yet."]
    wall = sum(_num(r.get("wall_s")) for r in rec.runs if math.isfinite(_num(r.get("wall_s"))))
    frames = sum(int(_num(r.get("frames"))) for r in rec.runs)
    commits = sorted({r.get("commit", "") for r in rec.runs})
    machines = sorted({r.get("machine", "") for r in rec.runs if r.get("machine")})
    def calls(r: dict[str, str]) -> float:  # the student's runs count the LLM's calls under cost/
        v = _num(r.get("cost/llm_calls"))
        v = v if math.isfinite(v) else _num(r.get("override/advisor/calls"))
        return v if math.isfinite(v) else 0.0

    llm_calls = sum(calls(r) for r in rec.runs)
    cached = sum(v for r in rec.runs if math.isfinite(v := _num(r.get("cost/llm_cache_hits"))))
    dirty = sum(1 for r in rec.runs if r.get("dirty") == "True")
    return [
        f"- Finished runs: {len(rec.runs)}, {frames:,} training frames, {wall / 3600:.1f} h of training wall clock "
        f"(evaluations not counted), each run on one core (one or two side by side) of: {'; '.join(machines) or 'not recorded'}.",
        f"- Code: commit {', '.join(commits)}" + (f" ({dirty} runs with uncommitted changes)" if dirty else " (clean)") + ".",
        f"- LLM HTTP calls over the study: {int(llm_calls):,} (and {int(cached):,} LLM rows answered from the answer "
        "cache).",
        "- Disk: a finished run keeps its networks and records, not its replay buffer (a few MB); a run in flight holds "
        "one checkpoint with its buffer, sized to the run (about 0.5 GB at 400k frames, 1.4 GB at 1M).",
    ]


def build(records_dir: Path) -> str:
    rec = Records(records_dir)
    out = records_dir
    md = ["# Does advice teach? The advice study", "",
          "Does an advisor that takes over near obstacles (the paper's SAC+LLM) make SAC better, and what must the "
          "advisor know? SAC is trained with advisors of known quality (none; the paper's greedy heuristic; a global "
          "planner; hovering; uniform-random actions; the local LLM), under the paper's override (the advisor's action "
          "is executed and stored; only the critic learns from it) and under *teach* (the override, plus a cloning "
          "term that pulls the actor's own action toward the executed advice, and a phase-out of the trigger so the "
          "actor flies alone for the second half of training). Every run is then evaluated twice on the same 32 "
          "scenarios (`results/eval_set_32.json`): the actor alone, as deployed, and the actor with its advisor.", "",
          "Regenerate: `make advice-study` (resumable; `ADVICE_JOBS=2` on two cores), then `make advice-records "
          "advice-report`; this page needs only the CSV files beside it.", "",
          f"Statistics: {METHOD_NAME.format(n=N_BOOT)}. Differences pair the scenarios, and are taken on the seeds "
          "both cells ran (a cell with fewer seeds is not set against the other's extra seeds); each cell's resamples are seeded from its name, so a cell added changes no other's interval; P(better) is rliable's probability of improvement on per-episode scores (ties "
          "count a half), with its bootstrap interval. Intervals stay inside each metric's range.", "",
          "## Design and progress", "", *markdown_table(progress_rows(rec), ["world", "transfer", "method", "seeds wanted",
                                                                    "seeds done", "state"], NONE_YET), "",
          "Tuning seeds (100, 101) are apart from the verdict seeds (0-4). Teach: cloning weight chosen on the tuning "
          "seeds, decayed linearly to 0 over the run; trigger (d_th) annealed to 0 over the first half. The LLM rung "
          "advises every triggered row: the LLM answers the student's warm-up and the rows it is least sure of, at "
          "`+exp=sac_llm_amortized`'s budget, and the student the rest (the share is in the dependence table).", "", "## Compute", "", *compute_lines(rec), ""]
    if rec.unfinished:
        md += [f"Runs in flight (not in any table): {', '.join(rec.unfinished)}.", ""]
    for world, title in WORLDS.items():
        table = cells_table(rec, world)
        if not table:
            continue
        md += [f"## {title}", "", "The actor alone at the end of training, every metric (lower is better for CR, RVR, ECR):",
               "", *markdown_table(table, ["cell", "advisor", "transfer", "seeds", *METRICS], NONE_YET), "",
               "Dependence on the advisor (means over seeds; the with-advisor evaluation uses the full trigger):", "",
               *markdown_table(dependence_table(rec, world), ["cell", "advised fraction", "trigger rate", "trigger, first / last fifth",
                                                   "actor within tol of advice", "actor-advice gap", "DCR alone",
                                                   "DCR with advisor", "SLR alone", "SLR with advisor", "CR alone",
                                                   "CR with advisor", "triggered rows advised, with advisor",
                                                   "advisor budget"], NONE_YET), "",
               "Against plain SAC in the same world (difference, and probability of improvement):", "",
               *markdown_table(comparison_table(rec, world), ["cell", "seeds", "ΔDCR", "P(better) DCR", "ΔSLR", "P(better) SLR", "ΔCR",
                                                   "P(better) CR"], NONE_YET), "",
               "What it cost (means per run; each run had one core, beside at most one other job, so the wall "
               "clock ratios carry that noise). An LLM row answered from the answer cache (a run repeated with "
               "the same seed asks the same questions) costs no call, no token and almost no wait: the wall "
               "clock of such a run is not the live cost.", "",
               *markdown_table(cost_table(rec, world), ["cell", "runs", "training wall clock per run", "x plain SAC",
                                             "advised rows per run", "LLM rows per run",
                                             "asked live / from the answer cache", "LLM tokens in / out per run",
                                             "waiting for the LLM per run"], NONE_YET), "",
               "Learned (DCR and SLR intervals above the uniform-random policy's on the same scenarios):", "",
               *markdown_table(learned_table(rec, world), ["cell", "DCR", "SLR", "random DCR", "random SLR", "learned"], NONE_YET), "",
               f"![cells](cells_{world}.png)", "", f"![curves](curves_{world}.png)", ""]
    md += ["## Tuning the cloning weight", "", *markdown_table(tuning_table(rec), ["clone_weight", "seeds", "DCR", "SLR",
                                                                        "mean of DCR and SLR (the choice)"], NONE_YET), "",
           "## SAC+Heuristic of the quick profile, rerun with the per-row greedy advisor", "",
           *markdown_table(rerun_table(rec), ["sac_heuristic", "seeds", *METRICS], NONE_YET), "",
           "## The paper's claims", "", *markdown_table(claim_rows(rec), ["claim", "verdict", "evidence", "command"], NONE_YET), "",
           "## Findings", "", *findings(rec), ""]
    made = figures(rec, out)
    write_text(out / "report.md", "\n".join(md))
    return f"wrote {out / 'report.md'} and {len(made)} figures"
