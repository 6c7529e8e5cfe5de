"""The advice study (``make advice-study``; uavlae/experiments/README.md, "Does advice teach?").

Three steps, each a sub-command:

- ``records RUNS_DIR --out results/advice``: what the report needs of every finished run of the
  study, as plain CSV files that travel with the repository: ``runs.csv`` (one row a run: world,
  transfer, method, seed, frames, wall clock, commit, machine, the run's dependence counters),
  ``episodes.csv`` (one row per evaluation episode: the actor alone at the end, the actor with
  its advisor, and the heuristic and uniform-random baselines of the same evaluation set) and
  ``curves.csv`` (every evaluation during training, and the logged trigger rate, advised fraction
  and actor-advisor agreement over frames). No run archive, no checkpoint.
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
import csv
import json
import math
import sys
from collections import defaultdict
from pathlib import Path
from typing import Any

from uavlae.files import atomic_write, train_eval_dir

EPISODE_COLUMNS = ("data_collected", "data_total", "collided", "landed", "rz_speeding", "energy_used", "energy_total",
                   "boundary_exit", "length")
RUN_COUNTERS = ("advised_fraction", "trigger_rate", "actor_gap", "actor_agree", "triggered", "advised",
                "budget_skipped", "frames", "source/fallback")
# what the training curves keep: (scalar file under logs/scalars, column name)
CURVE_SCALARS = (("eval/DCR", "DCR"), ("eval/SLR", "SLR"), ("eval/CR", "CR"), ("eval/RVR", "RVR"),
                 ("override/trigger_rate", "trigger_rate"), ("override/advised_fraction", "advised_fraction"),
                 ("override/actor_gap", "actor_gap"), ("override/actor_agree", "actor_agree"),
                 ("override/phase", "phase"))


def _read_json(path: Path) -> Any:
    return json.loads(path.read_text())


def _write_csv(path: Path, rows: list[dict[str, Any]], fields: list[str]) -> None:
    def write(fh: Any) -> None:
        text = __import__("io").TextIOWrapper(fh, encoding="utf-8", newline="")
        w = csv.DictWriter(text, fieldnames=fields, extrasaction="ignore")
        w.writeheader()
        w.writerows(rows)
        text.flush()
        text.detach()

    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write(path, write)


def world_of(cfg: dict[str, Any]) -> str:
    """``aid`` for the learning-aid world (a progress reward or ego-centric columns), ``spec`` for SPEC's."""
    env = cfg.get("env", {})
    aided = float(env.get("reward", {}).get("progress_weight", 0.0)) > 0 or bool(env.get("ego_features"))
    point = str((cfg.get("experiment") or {}).get("point") or "")
    return point.split("_", 1)[0] if point.split("_", 1)[0] in ("aid", "spec") else ("aid" if aided else "spec")


def transfer_of(cfg: dict[str, Any]) -> str:
    point = str((cfg.get("experiment") or {}).get("point") or "")
    return point.split("_", 1)[1] if "_" in point else point


def _episodes(path: Path) -> list[dict[str, str]]:
    if not path.is_file():
        return []
    with path.open(newline="") as fh:
        return list(csv.DictReader(fh))


def _scalar(run_dir: Path, name: str) -> list[tuple[int, float]]:
    f = run_dir / "logs" / "scalars" / f"{name}.csv"
    if not f.is_file():
        return []
    out = []
    with f.open(newline="") as fh:
        for row in csv.reader(fh):  # step,value rows, no header (uavlae.factories' CSV logger)
            try:
                out.append((int(float(row[0])), float(row[1])))
            except (IndexError, ValueError):
                continue
    return out


def run_record(d: Path) -> tuple[dict[str, Any], list[dict[str, Any]], list[dict[str, Any]]] | None:
    """(run row, episode rows, curve rows) of a finished run in ``d``; None when unfinished."""
    final_file = d / "final_metrics.json"
    if not (final_file.is_file() and (d / "config.json").is_file()):
        return None
    cfg, final = _read_json(d / "config.json"), _read_json(final_file)
    meta = _read_json(d / "meta.json") if (d / "meta.json").is_file() else {}
    frames = int(final.get("frames", 0))
    if frames < int(cfg["trainer"]["total_frames"]):
        return None
    ex = cfg.get("experiment") or {}
    key = {"world": world_of(cfg), "transfer": transfer_of(cfg), "method": str(ex.get("method") or cfg["name"]),
           "seed": int(cfg["seed"])}
    git = meta.get("git") or {}
    machine = meta.get("machine") or {}
    run = {**key, "frames": frames, "wall_s": final.get("wall_s"), "updates": final.get("updates"),
           "advisor": cfg["advisor"]["kind"] + ("/" + cfg["heuristic_kind"] if cfg["advisor"]["kind"] == "heuristic" else ""),
           "clone_weight": cfg["algo"].get("clone_weight", 0.0), "phase_out_frames": cfg["advisor"].get("phase_out_frames"),
           "max_calls": cfg["advisor"].get("max_calls"),
           "commit": str(git.get("commit") or "")[:10], "dirty": git.get("dirty"),
           "machine": f"{machine.get('cpu', '')}, {machine.get('logical_cores', '?')} cores" if machine else "",
           "path": str(d.name)}
    for k in RUN_COUNTERS:
        run[f"override/{k}"] = final.get(f"override/{k}")
        run[f"advised/override/{k}"] = final.get(f"advised/override/{k}")
    for k in ("advisor/calls", "advisor/prompt_tokens", "advisor/completion_tokens"):
        run[f"override/{k}"] = final.get(f"override/{k}")
    episodes = []
    sources = {"alone": train_eval_dir(d, frames), "with_advisor": d / "eval" / "with_advisor",
               "heuristic": d / "eval" / "baseline_heuristic", "random": d / "eval" / "baseline_random"}
    for evaluation, folder in sources.items():
        for i, row in enumerate(_episodes(folder / "episodes.csv")):
            episodes.append({**key, "evaluation": evaluation, "scenario": int(row.get("row", i)),
                             **{c: row.get(c) for c in EPISODE_COLUMNS}})
    curves: dict[int, dict[str, Any]] = defaultdict(dict)
    for name, col in CURVE_SCALARS:
        for step, value in _scalar(d, name):
            curves[step][col] = value
    curve_rows = [{**key, "frames": step, **vals} for step, vals in sorted(curves.items())]
    return run, episodes, curve_rows


def collect(root: Path) -> tuple[list[dict[str, Any]], list[dict[str, Any]], list[dict[str, Any]], list[str]]:
    """Every finished run under ``root`` (``<point>/<method>/seed<k>``), and the unfinished ones' paths."""
    runs, episodes, curves, unfinished = [], [], [], []
    for cfg_file in sorted(root.rglob("config.json")):
        d = cfg_file.parent
        if any(p.startswith(".") for p in d.relative_to(root).parts) or not (d / "meta.json").is_file():
            continue
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


def write_records(root: Path, out: Path) -> dict[str, int]:
    runs, episodes, curves, unfinished = collect(root)
    run_fields = list(dict.fromkeys(k for r in runs for k in r)) or ["world"]
    _write_csv(out / "runs.csv", runs, run_fields)
    _write_csv(out / "episodes.csv", episodes, ["world", "transfer", "method", "seed", "evaluation", "scenario",
                                                 *EPISODE_COLUMNS])
    _write_csv(out / "curves.csv", curves, ["world", "transfer", "method", "seed", "frames",
                                             *[c for _, c in CURVE_SCALARS]])
    _write_csv(out / "unfinished.csv", [{"path": p} for p in unfinished], ["path"])
    return {"runs": len(runs), "episodes": len(episodes), "curve_rows": len(curves), "unfinished": len(unfinished)}


def episode_dcr_slr(rows: list[dict[str, Any]]) -> tuple[float, float]:
    """The pooled DCR (collected over held) and the landing rate of some episode rows."""
    held = sum(float(r["data_total"]) for r in rows)
    dcr = sum(float(r["data_collected"]) for r in rows) / held if held > 0 else math.nan
    slr = sum(str(r["landed"]) == "True" for r in rows) / len(rows) if rows else math.nan
    return dcr, slr


def choose(root: Path, point: str = "aid_tune") -> float:
    """The tuning cell's weight with the best mean of DCR and SLR of the actor alone (module doc)."""
    runs, episodes, _, unfinished = collect(root / point) if (root / point).is_dir() else ([], [], [], [])
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
    c = sub.add_parser("choose", help="print the tuned cloning weight")
    c.add_argument("runs", type=Path)
    c.add_argument("--point", default="aid_tune")
    rep = sub.add_parser("report", help="CSV records -> tables, figures, report.md")
    rep.add_argument("records", type=Path, nargs="?", default=Path("results/advice"))
    args = p.parse_args(argv)
    if args.cmd == "records":
        print(json.dumps(write_records(args.runs, args.out)))
    elif args.cmd == "choose":
        print(choose(args.runs, args.point))
    else:
        from uavlae.experiments.advice_report import build

        print(build(args.records))


if __name__ == "__main__":
    sys.exit(main())
