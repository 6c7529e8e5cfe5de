"""The student advisor (``advisor.amortize``) beside plain SAC and beside the LLM at every
trigger, at the same settings, side by side in one run.

    python benchmarks/amortize.py --frames 20000 --batch 16                    (make bench-amortize)
    python benchmarks/amortize.py --methods sac amortized every --seeds 0 1     (make bench-amortize-outcome)
    python benchmarks/amortize.py --quick --checkpoint-every 25000              (make amortize-quick: 400k frames, B = 64)
    python benchmarks/amortize.py --compare --seeds 0 1 --frames 12000 --batch 16 --root ROOT
                                  (no training: amortized minus every trigger on finished runs, paired)

Trains, in this process and one after another, each seed's methods: ``sac`` (``+exp=sac``),
``amortized`` (``+exp=sac_llm_amortized``: the student at its stated budget) and ``every`` (``+exp=sac_llm``: the LLM
at every trigger, the paper's method, no call budget), with the quick profile's world and
learner (``+profile=quick``: env shaped_geodesic, 0.25 gradient steps a frame) at ``--frames``
and B = ``--batch``, the env not compiled (the LLM runs' setting in the Makefile), no evaluation
during training, 32 evaluation episodes of the actor alone at the end (``--eval-with-advisor``:
also with its advisor, full episodes, which asks the LLM more than a short run's training does). The LLM runs ask one local server started
first (its start-up is in no run's time), each with a new, empty cache file.

Per run: the training wall clock (``train_s``: collection, advice, gradient steps; evaluation
excluded) and its ratio to the seed's ``sac`` run; every triggered row and who answered it (the
LLM, the student, the fallback; ``advised_all``: no triggered row was left to the actor); the
LLM's share of the triggered rows over the whole run and from ``--late-from`` frames on (the
bound to meet at the quick profile's size: 1% from 50k frames); the student's velocity error
against the LLM on audited rows per logging window; tokens and seconds; the evaluation metrics and advised fraction. The
runs stay in ``--root`` (the student's checkpoint is what ``make bench-advice-student`` scores).
Writes ``benchmarks/amortize.json`` with the machine, one entry per size, methods and seeds.
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import os
import shlex
import sys
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from uavlae.files import portable  # noqa: E402

METHODS = {"sac": ["+exp=sac"], "amortized": ["+exp=sac_llm_amortized"], "every": ["+exp=sac_llm"]}
METRICS = ("DCR", "CR", "SLR", "RVR", "ECR")


def _series(run_dir: Path, metric: str) -> list[tuple[int, float]]:
    """``(frames, value)`` rows of one logged metric (the CSV logger's ``step,value`` lines)."""
    path = run_dir / "logs" / "scalars" / f"{metric}.csv"
    if not path.is_file():
        return []
    with path.open() as fh:
        return [(int(float(r[0])), float(r[1])) for r in csv.reader(fh) if r]


def _after(run_dir: Path, metric: str, frames: int) -> float:
    return sum(v for s, v in _series(run_dir, metric) if s > frames)


def train(method: str, seed: int, run_dir: Path, args: argparse.Namespace, llm: list[str]) -> dict:
    from hydra import compose, initialize_config_dir

    from uavlae.factories import CONF_DIR
    from uavlae.train import run

    overrides = [*METHODS[method], "+profile=quick", f"seed={seed}", f"run_dir={run_dir}",
                 f"trainer.total_frames={args.frames}", f"trainer.env_batch_size={args.batch}",
                 f"trainer.replay_capacity={args.frames}", "trainer.compile_env=false", "trainer.eval_every_frames=0",
                 f"trainer.checkpoint_every_frames={args.checkpoint_every}", "trainer.progress_bar=false",
                 "trainer.baselines=false", "logger.wandb.mode=disabled",
                 f"trainer.eval_with_advisor={str(args.eval_with_advisor).lower()}", *shlex.split(args.extra),
                 *([*llm, *shlex.split(args.llm_extra)] if method != "sac" else []),
                 *(shlex.split(args.amortized_extra) if method == "amortized" else [])]
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        cfg = compose("config", overrides=overrides)
    t0 = time.perf_counter()
    final = run(cfg)
    wall = time.perf_counter() - t0
    s = json.loads((run_dir / "summary.json").read_text())
    row = {"method": method, "seed": seed, "run_dir": portable(str(run_dir), ROOT),
           "overrides": [o for o in overrides if not o.startswith(("run_dir=", "llm.cache_path=", "llm.base_url="))],
           "frames": s["frames"], "updates": s["updates"], "train_s": round(s["train_s"], 1),
           "frames_per_s": round(s["frames"] / s["train_s"], 1),
           "wall_s": final.get("wall_s"),  # the training loop's, over every resumed part
           "this_part_s_with_eval": round(wall, 1),
           "eval": {k: final.get(f"eval/{k}") for k in METRICS}}
    ov, cost = s.get("override"), s.get("cost")
    if ov:
        trig = int(ov["triggered"])
        who = {k: int(ov.get(f"source/{k}", 0)) for k in ("llm", "student", "fallback", "policy", "heuristic")}
        late = args.late_from
        late_trig = _after(run_dir, "override/triggered", late)
        late_llm = _after(run_dir, "override/advisor/student/llm_rows", late) if method == "amortized" else \
            _after(run_dir, "override/advised", late)
        audit = [(f, v) for f, v in _series(run_dir, "override/advisor/student/audit_err_mps") if not math.isnan(v)]
        row.update({
            "triggered": trig, "trigger_rate": round(ov["trigger_rate"], 4),
            "rows_by_source": who, "advised_all": who["llm"] + who["student"] + who["fallback"] == trig,
            "llm_rows": int(ov.get("advisor/student/llm_rows", ov["advised"])),
            "llm_share_of_triggered": round(ov.get("advisor/student/llm_rows", ov["advised"]) / max(trig, 1), 4),
            f"llm_share_of_triggered_after_{late}": round(late_llm / late_trig, 4) if late_trig else None,
            "llm_asked_by_reason": {r: int(ov.get(f"advisor/student/asked_{r}", 0))
                                    for r in ("warmup", "unsure", "novel", "audit")} if method == "amortized" else None,
            "student_audit_err_mps": ov.get("advisor/student/audit_err_mps"),
            "student_audit_err_mps_by_window": [[f, round(v, 3)] for f, v in audit],
            "student_llm_err_mps": ov.get("advisor/student/llm_err_mps"),
            "student_train_s": round(ov.get("advisor/student/train_s", 0.0), 1),
            "advised_fraction": round(ov["advised_fraction"], 4),
            "cost": cost,
        })
    print(method, seed, json.dumps({k: v for k, v in row.items() if k != "student_audit_err_mps_by_window"}), flush=True)
    return row


def compare(root: Path, seeds: list[int], n_boot: int = 2000) -> dict:
    """The outcome's dependence on amortization: each method's metrics over ``seeds`` x the 32
    evaluation scenarios (stratified bootstrap), and amortized minus every trigger, paired by seed
    and scenario, with rliable's probability of improvement (uavlae.experiments.advice_stats)."""
    from uavlae.experiments.advice_stats import difference, grid_from_rows, interval, probability_of_improvement
    from uavlae.files import train_eval_dir

    grids = {}
    for method in ("sac", "every", "amortized"):
        rows = []
        for seed in seeds:
            d = root / f"{method}_seed{seed}"
            final = json.loads((d / "final_metrics.json").read_text())
            with (train_eval_dir(d, int(final["frames"])) / "episodes.csv").open() as fh:
                rows += [{**r, "seed": seed, "scenario": r["row"]} for r in csv.DictReader(fh)]
        grids[method] = grid_from_rows(rows)
    out: dict = {"seeds": seeds, "method": "stratified bootstrap over seeds x scenarios, 95%; P(better): "
                 "rliable's probability of improvement", "n_boot": n_boot, "metrics": {}, "amortized_minus_every": {}}
    for m, g in grids.items():
        out["metrics"][m] = {k: [round(v, 4) for v in interval(g, k, n_boot)] for k in ("DCR", "CR", "SLR")}
    for k in ("DCR", "CR", "SLR"):
        out["amortized_minus_every"][k] = {
            "difference": [round(v, 4) for v in difference(grids["amortized"], grids["every"], k, n_boot)],
            "p_better": [round(v, 3) for v in probability_of_improvement(grids["amortized"], grids["every"], k, n_boot)]}
    return out


def record(path: Path, section: str, key: str, entry: dict) -> None:
    """``entry`` under ``section`` / ``key`` of the result file, the other entries kept."""
    from uavlae.files import dump_json

    out = json.loads(path.read_text()) if path.is_file() else {"benchmark": "amortize", "measurements": {}}
    out.setdefault(section, {})[key] = entry
    dump_json(path, out)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--methods", nargs="+", default=["sac", "amortized"], choices=list(METHODS))
    ap.add_argument("--seeds", nargs="+", type=int, default=[0])
    ap.add_argument("--frames", type=int, default=20000)
    ap.add_argument("--batch", type=int, default=16)
    ap.add_argument("--quick", action="store_true", help="the quick profile's size: 400k frames, B = 64")
    ap.add_argument("--late-from", type=int, default=None, help="frames after which the LLM's share is counted again "
                                                                "(default: 50k with --quick, else half the frames)")
    ap.add_argument("--checkpoint-every", type=int, default=0, help="trainer.checkpoint_every_frames (0: at the end)")
    ap.add_argument("--eval-with-advisor", action="store_true",
                    help="also fly the LLM runs' actors with their advisor at the end (full episodes: many LLM calls)")
    ap.add_argument("--extra", default="", help="overrides of every run (quoted)")
    ap.add_argument("--llm-extra", default="", help="overrides of the LLM runs (quoted), e.g. 'llm.observation=verbose'")
    ap.add_argument("--amortized-extra", default="", help="overrides of the amortized runs only (quoted), "
                                                          "e.g. 'advisor.student.share_allowance=200'")
    ap.add_argument("--root", default=str(ROOT / "runs" / "bench_amortize"))
    ap.add_argument("--note", default="")
    ap.add_argument("--out", default=str(ROOT / "benchmarks" / "amortize.json"))
    ap.add_argument("--compare", action="store_true",
                    help="no training: read the finished every / amortized / sac runs of --seeds under --root and "
                         "record amortized minus every trigger, paired (the outcome's dependence on amortization)")
    args = ap.parse_args()
    if args.quick:
        args.frames, args.batch = 400_000, 64
    if args.late_from is None:
        args.late_from = 50_000 if args.quick else args.frames // 2
    torch.set_num_threads(1)
    os.environ.setdefault("WANDB_MODE", "disabled")

    from omegaconf import OmegaConf

    from uavlae.factories import CONF_DIR, git_info
    from uavlae.llm.config import ServerConfig
    from uavlae.llm.server import local_server
    from uavlae.machine import describe_machine

    root = Path(args.root) / f"f{args.frames}_b{args.batch}"
    if args.compare:
        result = compare(root, args.seeds)
        record(Path(args.out), "outcome", f"frames{args.frames}_b{args.batch}_seeds{'+'.join(map(str, args.seeds))}", {
            "measured_at": time.strftime("%Y-%m-%d %H:%M:%S %Z"), "git": git_info(),
            "command": "python benchmarks/amortize.py " + " ".join(shlex.quote(a) for a in sys.argv[1:]), **result})
        for m, v in result["metrics"].items():
            print(f"{m:>9}: " + "  ".join(f"{k} {p:.3f} [{lo:.3f}, {hi:.3f}]" for k, (p, lo, hi) in v.items()))
        for k, v in result["amortized_minus_every"].items():
            (p, lo, hi), (q, qlo, qhi) = v["difference"], v["p_better"]
            print(f"amortized - every, {k}: {p:+.3f} [{lo:+.3f}, {hi:+.3f}], P(better) {q:.2f} [{qlo:.2f}, {qhi:.2f}]")
        print(f"wrote {args.out}")
        return
    server_cfg = ServerConfig(**OmegaConf.to_container(OmegaConf.load(CONF_DIR / "llm" / "local.yaml").server))
    runs: list[dict] = []
    t0 = time.perf_counter()
    with local_server(server_cfg) as srv:
        server_start_s = time.perf_counter() - t0
        for seed in args.seeds:
            for method in args.methods:
                run_dir = root / f"{method}_seed{seed}"  # an existing one resumes, or is read back when done
                llm = [f"llm.base_url={srv.base_url}", f"llm.cache_path={run_dir / 'llm_cache.sqlite'}",
                       "llm.cache_mode=read_write"]
                runs.append(train(method, seed, run_dir, args, llm))
    for r in runs:  # the wall clock against plain SAC's on the same seed
        sac = next((x for x in runs if x["method"] == "sac" and x["seed"] == r["seed"]), None)
        r["train_s_over_sac"] = round(r["train_s"] / sac["train_s"], 2) if sac else None
    entry = {
        "measured_at": time.strftime("%Y-%m-%d %H:%M:%S %Z"), "machine": describe_machine(), "git": git_info(),
        "command": "python benchmarks/amortize.py " + " ".join(shlex.quote(a) for a in sys.argv[1:]),
        "note": args.note, "frames": args.frames, "batch": args.batch, "late_from": args.late_from,
        "llm_server": server_cfg.model_dump(), "server_start_s": round(server_start_s, 1), "runs": runs,
    }
    # one result file: each measurement (size x methods x seeds) under its own key, the latest kept
    record(Path(args.out), "measurements",
           f"frames{args.frames}_b{args.batch}_{'+'.join(args.methods)}_seeds{'+'.join(map(str, args.seeds))}", entry)
    for r in runs:
        print(f"{r['method']:>9} seed {r['seed']}: {r['train_s']:.0f} s ({r['train_s_over_sac']}x sac), "
              + (f"{r['triggered']} triggered, LLM {r['llm_rows']} ({100 * r['llm_share_of_triggered']:.1f}%), "
                 f"student {r['rows_by_source']['student']}, all advised: {r['advised_all']}; " if "triggered" in r else "")
              + " ".join(f"{k} {v:.3f}" for k, v in r["eval"].items() if v is not None))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
