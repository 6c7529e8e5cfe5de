"""The advice study (``make advice-study``; uavlae/experiments/README.md, "Does advice teach?").

Three steps, each a sub-command:

- ``records RUNS_DIR --out results/advice``: what the report needs of every finished run of the
  study, as plain CSV files that travel with the repository: ``runs.csv`` (one row a run: world,
  transfer, method, seed, frames, wall clock, commit, machine, the run's dependence counters),
  ``episodes.csv`` (one row per evaluation episode: the actor alone at the end, the actor with
  its advisor, and the heuristic and uniform-random baselines of the same evaluation set) and
  ``curves.csv`` (every evaluation during training, and the logged trigger rate, advised fraction
  and actor-advisor agreement over frames). No run archive, no checkpoint.
- ``restore results/advice RUNS_DIR``: the study outlives the machine it runs on. ``records``
  also keeps each finished run's ``config.json`` and ``final_metrics.json`` (a few kB) under
  ``results/advice/runs/``; ``restore`` puts them back into a fresh ``RUNS_DIR``, where the
  study's sweeps (``experiment.reuse``) then count those runs as done and run only the rest.
- ``choose RUNS_DIR``: the cloning weight for the verdict seeds, chosen on the tuning cell's own
  seeds (``aid_tune``): the weight whose actor alone scores the highest mean of DCR and SLR at
  the end (ties: the smaller weight). Prints the weight; writes nothing.
- ``report results/advice``: tables, figures and ``report.md`` from those CSV files alone
  (:mod:`uavlae.experiments.advice_report`).

A run's cell is its world (``aid``: ``env=shaped_geodesic``; ``spec``: ``env=default``), its
transfer (``override``: the paper's; ``teach``: override, cloning and phase-out; ``tune``: the
tuning runs) and its method (the ``+exp``, or the learning aid it isolates).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from collections import defaultdict
from pathlib import Path
from typing import Any

from uavlae.experiments.reporting import read_json, read_rows, read_scalar, write_csv
from uavlae.files import atomic_write, portable, train_eval_dir

EPISODE_COLUMNS = ("data_collected", "data_total", "collided", "landed", "rz_speeding", "energy_used", "energy_total",
                   "boundary_exit", "length")
RUN_COUNTERS = ("advised_fraction", "trigger_rate", "actor_gap", "actor_agree", "triggered", "advised",
                "budget_skipped", "frames", "source/fallback", "source/llm", "source/student")
# the LLM's cost that a run's final metrics carry (uavlae.llm's accounting), kept per run
COST_KEYS = ("rows_llm", "rows_student", "llm_calls", "llm_cache_hits", "tokens_in", "tokens_out", "wait_s")
# what the training curves keep: (scalar file under logs/scalars, column name)
CURVE_SCALARS = (("eval/DCR", "DCR"), ("eval/SLR", "SLR"), ("eval/CR", "CR"), ("eval/RVR", "RVR"),
                 ("override/trigger_rate", "trigger_rate"), ("override/advised_fraction", "advised_fraction"),
                 ("override/actor_gap", "actor_gap"), ("override/actor_agree", "actor_agree"),
                 ("override/phase", "phase"))


CURVE_EVERY = 8


def world_of(cfg: dict[str, Any]) -> str:
    """``aid`` for the learning-aid world (a progress reward or ego-centric columns), ``spec`` for SPEC's."""
    env = cfg.get("env", {})
    aided = float(env.get("reward", {}).get("progress_weight", 0.0)) > 0 or bool(env.get("ego_features"))
    point = str((cfg.get("experiment") or {}).get("point") or "")
    return point.split("_", 1)[0] if point.split("_", 1)[0] in ("aid", "spec") else ("aid" if aided else "spec")


def transfer_of(cfg: dict[str, Any]) -> str:
    """The study's transfer (``override``, ``teach``, ``tune``, ``aid``) from its point
    ``<world>_<transfer>``; any other sweep's point as it is."""
    point = str((cfg.get("experiment") or {}).get("point") or "")
    world, _, rest = point.partition("_")
    return rest if world in ("aid", "spec") and rest else point


def run_record(d: Path) -> tuple[dict[str, Any], list[dict[str, Any]], list[dict[str, Any]]] | None:
    """(run row, episode rows, curve rows) of a finished run in ``d``; None when unfinished."""
    final_file = d / "final_metrics.json"
    if not (final_file.is_file() and (d / "config.json").is_file()):
        return None
    cfg, final = read_json(d / "config.json"), read_json(final_file)
    meta = read_json(d / "meta.json") if (d / "meta.json").is_file() else {}
    frames = int(final.get("frames", 0))
    if frames < int(cfg["trainer"]["total_frames"]):
        return None
    ex = cfg.get("experiment") or {}
    key = {"world": world_of(cfg), "transfer": transfer_of(cfg), "method": str(ex.get("method") or cfg["name"]),
           "seed": int(cfg["seed"]), "sweep": str(ex.get("sweep") or "")}
    git = meta.get("git") or {}
    machine = meta.get("machine") or {}
    run = {**key, "frames": frames, "wall_s": final.get("wall_s"), "updates": final.get("updates"),
           "advisor": cfg["advisor"]["kind"] + ("/" + cfg["heuristic_kind"] if cfg["advisor"]["kind"] == "heuristic" else ""),
           "clone_weight": cfg["algo"].get("clone_weight", 0.0), "phase_out_frames": cfg["advisor"].get("phase_out_frames"),
           "max_calls": cfg["advisor"].get("max_calls"), "amortize": bool(cfg["advisor"].get("amortize", False)),
           "commit": str(git.get("commit") or "")[:10], "dirty": git.get("dirty"),
           "machine": f"{machine.get('cpu', '')}, {machine.get('logical_cores', '?')} cores" if machine else "",
           "path": str(d.name)}
    for k in RUN_COUNTERS:
        run[f"override/{k}"] = final.get(f"override/{k}")
        run[f"advised/override/{k}"] = final.get(f"advised/override/{k}")
    for k in ("advisor/calls", "advisor/prompt_tokens", "advisor/completion_tokens"):
        run[f"override/{k}"] = final.get(f"override/{k}")
    for k in COST_KEYS:  # what the LLM cost, in runs that asked it
        if f"cost/{k}" in final:
            run[f"cost/{k}"] = final[f"cost/{k}"]
    episodes = []
    sources = {"alone": train_eval_dir(d, frames), "with_advisor": d / "eval" / "with_advisor",
               "heuristic": d / "eval" / "baseline_heuristic", "random": d / "eval" / "baseline_random"}
    for evaluation, folder in sources.items():
        for i, row in enumerate(read_rows(folder / "episodes.csv")):
            episodes.append({**key, "evaluation": evaluation, "scenario": int(row.get("row", i)),
                             **{c: row.get(c) for c in EPISODE_COLUMNS}})
    curves: dict[int, dict[str, Any]] = defaultdict(dict)
    for name, col in CURVE_SCALARS:
        for step, value in read_scalar(d, name):
            curves[int(step)][col] = value  # a frame count: written as a whole number
    # every evaluation, and the logged counters every CURVE_EVERY-th batch (a curve, not a log)
    curve_rows = [{**key, "frames": step, **vals} for i, (step, vals) in enumerate(sorted(curves.items()))
                  if "DCR" in vals or i % CURVE_EVERY == 0]
    return run, episodes, curve_rows


def collect(root: Path, restored: bool = False
            ) -> tuple[list[dict[str, Any]], list[dict[str, Any]], list[dict[str, Any]], list[str]]:
    """Every finished run under ``root`` (``<point>/<method>/seed<k>``), and the unfinished ones'
    paths; with ``restored``, the runs put back by :func:`restore` too."""
    runs, episodes, curves, unfinished = [], [], [], []
    for cfg_file in sorted(root.rglob("config.json")):
        d = cfg_file.parent
        if any(p.startswith(".") for p in d.relative_to(root).parts) or not (d / "meta.json").is_file():
            continue
        if not restored and "restored_from" in read_json(d / "meta.json"):
            continue  # its records are already in the CSV files it was restored from
        rec = run_record(d)
        if rec is None:
            unfinished.append(str(d.relative_to(root)))
            continue
        run, eps, cur = rec
        run["path"] = str(d.relative_to(root))
        runs.append(run)
        episodes.extend(eps)
        curves.extend(cur)
    return runs, episodes, curves, unfinished


KEY_COLUMNS = ["world", "transfer", "method", "seed", "sweep"]
KEPT_FILES = ("config.json", "final_metrics.json")  # what restore needs to count a run as done


def _key(row: dict[str, Any]) -> tuple[str, str, str, int]:
    return (str(row["world"]), str(row["transfer"]), str(row["method"]), int(row["seed"]))


def _merged(old: list[dict[str, Any]], new: list[dict[str, Any]], fresh: set) -> list[dict[str, Any]]:
    """The rows already recorded of runs not collected again, then the new rows."""
    return [r for r in old if _key(r) not in fresh] + new


def checkout_of(path: Path) -> Path:
    """The checkout (a folder holding ``.git``, a worktree's file included) that ``path`` lies in;
    the working folder if none: what the kept files' paths are written relative to."""
    for d in (path.resolve(), *path.resolve().parents):
        if (d / ".git").exists():
            return d
    return Path.cwd()


def write_records(root: Path, out: Path) -> dict[str, int]:
    """Adds the finished runs under ``root`` to the records in ``out`` (a run recorded before and
    collected again is replaced; the records of runs not under ``root`` are kept)."""
    new_runs, episodes, curves, unfinished = collect(root)
    fresh = {_key(r) for r in new_runs}
    runs = _merged(read_rows(out / "runs.csv"), new_runs, fresh)
    episodes = _merged(read_rows(out / "episodes.csv"), episodes, fresh)
    curves = _merged(read_rows(out / "curves.csv"), curves, fresh)
    checkout = checkout_of(root)
    for run in new_runs:
        for name in KEPT_FILES:
            # a resumed run may record its folder absolute: committed records name no machine's folder
            data = portable((root / run["path"] / name).read_text(encoding="utf-8"), checkout).encode()
            target = out / "runs" / run["path"] / name
            target.parent.mkdir(parents=True, exist_ok=True)
            atomic_write(target, lambda fh, data=data: fh.write(data))
    run_fields = list(dict.fromkeys(k for r in runs for k in r)) or KEY_COLUMNS
    write_csv(out / "runs.csv", runs, run_fields)
    write_csv(out / "episodes.csv", episodes, [*KEY_COLUMNS, "evaluation", "scenario", *EPISODE_COLUMNS])
    write_csv(out / "curves.csv", curves, [*KEY_COLUMNS, "frames", *[c for _, c in CURVE_SCALARS]])
    write_csv(out / "unfinished.csv", [{"path": p} for p in unfinished], ["path"])
    return {"runs": len(runs), "episodes": len(episodes), "curve_rows": len(curves), "unfinished": len(unfinished)}


# the quick profile's runs that the paper's claims are judged on: (sweep folder, method folders)
CLAIM_RUNS = (("train", ("sac_llm", "sac_heuristic", "sac", "ppo", "sac_llm_fp0.3", "sac_llm_fp0.4", "sac_llm_fp0.5",
                         "sac_llm_fp1.0")),
              ("llm_setting", ("sac_llm",)))


def write_claim_records(quick_root: Path, out: Path) -> dict[str, int]:
    """The final evaluations' episodes of the quick profile's runs behind the paper's claims
    (SAC+LLM and what it is compared with, the d_th and prompt sweeps) -> ``claims_episodes.csv``
    and ``claims_runs.csv``, so the verdicts' intervals come from per-episode records too."""
    runs, episodes = [], []
    for sweep, methods in CLAIM_RUNS:
        for d in sorted((quick_root / sweep).rglob("seed*")):
            if d.parent.name not in methods or not d.is_dir():
                continue
            rec = run_record(d)
            if rec is None:
                continue
            run, eps, _ = rec
            run["path"] = str(d.relative_to(quick_root))
            runs.append(run)
            # the baselines fly the same set in every run: plain SAC's seed 0 keeps them
            keep_baselines = (sweep, d.parent.name, d.name) == ("train", "sac", "seed0")
            episodes.extend(e for e in eps if e["evaluation"] == "alone"
                            or (keep_baselines and e["evaluation"] in ("random", "heuristic")))
    write_csv(out / "claims_runs.csv", runs, list(dict.fromkeys(k for r in runs for k in r)) or KEY_COLUMNS)
    write_csv(out / "claims_episodes.csv", episodes, [*KEY_COLUMNS, "evaluation", "scenario", *EPISODE_COLUMNS])
    return {"runs": len(runs), "episodes": len(episodes)}


def restore(records: Path, root: Path) -> int:
    """Copy each kept run's files back under ``root`` where that run's folder lacks them, with
    its evaluations' episodes from ``episodes.csv`` (so choosing the cloning weight reads them as
    from the run itself); returns how many runs were restored. A finished run's folder is left
    alone; one with a run in flight is an error."""
    by_run: dict[tuple[str, str, str, int], list[dict[str, str]]] = defaultdict(list)
    for e in read_rows(records / "episodes.csv"):
        by_run[_key(e)].append(e)
    n = 0
    for cfg_file in sorted((records / "runs").rglob("config.json")):
        rel = cfg_file.parent.relative_to(records / "runs")
        target = root / rel
        if (target / "final_metrics.json").is_file():
            continue
        if target.is_dir() and any(target.iterdir()):
            raise SystemExit(f"{target} holds a run that is not finished; remove it to restore the finished one")
        target.mkdir(parents=True, exist_ok=True)
        for name in KEPT_FILES:
            data = (cfg_file.parent / name).read_bytes()
            atomic_write(target / name, lambda fh, data=data: fh.write(data))
        cfg, final = read_json(target / "config.json"), read_json(target / "final_metrics.json")
        ex = cfg.get("experiment") or {}
        key = (world_of(cfg), transfer_of(cfg), str(ex.get("method") or cfg["name"]), int(cfg["seed"]))
        folders = {"alone": train_eval_dir(target, int(final["frames"])), "with_advisor": target / "eval" / "with_advisor",
                   "heuristic": target / "eval" / "baseline_heuristic", "random": target / "eval" / "baseline_random"}
        for evaluation, folder in folders.items():
            rows = [{"row": e["scenario"], **{c: e[c] for c in EPISODE_COLUMNS}} for e in by_run.get(key, [])
                    if e["evaluation"] == evaluation]
            if rows:
                write_csv(folder / "episodes.csv", rows, ["row", *EPISODE_COLUMNS])
        (target / "meta.json").write_text(json.dumps({"restored_from": str(records / "runs" / rel)}))
        n += 1
    return n


def episode_dcr_slr(rows: list[dict[str, Any]]) -> tuple[float, float]:
    """The pooled DCR (collected over held) and the landing rate of some episode rows."""
    held = sum(float(r["data_total"]) for r in rows)
    dcr = sum(float(r["data_collected"]) for r in rows) / held if held > 0 else math.nan
    slr = sum(str(r["landed"]) == "True" for r in rows) / len(rows) if rows else math.nan
    return dcr, slr


def choose(root: Path, point: str = "aid_tune") -> float:
    """The tuning cell's weight with the best mean of DCR and SLR of the actor alone (module doc)."""
    runs, episodes, _, unfinished = collect(root / point, restored=True) if (root / point).is_dir() else ([], [], [], [])
    if not runs:
        raise SystemExit(f"no finished tuning run under {root / point}; run the tuning cell first")
    pending = [p for p in unfinished]
    if pending:
        raise SystemExit(f"tuning runs unfinished under {root / point}: {pending}")
    weight = {(r["method"], r["seed"]): float(r["clone_weight"]) for r in runs}
    score: dict[float, list[float]] = defaultdict(list)
    by_run: dict[tuple[str, int], list[dict[str, Any]]] = defaultdict(list)
    for e in episodes:
        if e["evaluation"] == "alone":
            by_run[(e["method"], int(e["seed"]))].append(e)
    for k, rows in by_run.items():
        dcr, slr = episode_dcr_slr(rows)
        score[weight[k]].append((dcr + slr) / 2)
    best = max(sorted(score), key=lambda w: sum(score[w]) / len(score[w]))
    return best


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(prog="python -m uavlae.experiments.advice", description=__doc__.split("\n\n")[0])
    sub = p.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("records", help="the study's runs -> CSV records")
    r.add_argument("runs", type=Path)
    r.add_argument("--out", type=Path, default=Path("results/advice"))
    q = sub.add_parser("claims", help="the quick profile's runs behind the paper's claims -> CSV records")
    q.add_argument("runs", type=Path, help="the quick profile's runs folder (e.g. runs/quick)")
    q.add_argument("--out", type=Path, default=Path("results/advice"))
    s = sub.add_parser("restore", help="put the finished runs' kept files back into a runs folder")
    s.add_argument("records", type=Path)
    s.add_argument("runs", type=Path)
    c = sub.add_parser("choose", help="print the tuned cloning weight")
    c.add_argument("runs", type=Path)
    c.add_argument("--point", default="aid_tune")
    rep = sub.add_parser("report", help="CSV records -> tables, figures, report.md")
    rep.add_argument("records", type=Path, nargs="?", default=Path("results/advice"))
    args = p.parse_args(argv)
    if args.cmd == "records":
        print(json.dumps(write_records(args.runs, args.out)))
    elif args.cmd == "claims":
        print(json.dumps(write_claim_records(args.runs, args.out)))
    elif args.cmd == "restore":
        print(f"restored {restore(args.records, args.runs)} finished runs into {args.runs}")
    elif args.cmd == "choose":
        print(choose(args.runs, args.point))
    else:
        from uavlae.experiments.advice_report import build

        print(build(args.records))


if __name__ == "__main__":
    sys.exit(main())
