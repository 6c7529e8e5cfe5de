"""The paper's comparison table: every method at equal training
frames and the same seeds, evaluated on one fixed evaluation set.

    python experiments/paper_table.py --frames 12288 --seeds 0        # what `make paper-table` runs

Each (method, seed) is one ``python -m uavlae.train +exp=METHOD`` subprocess (one at a time; the
exact command is recorded) with ``trainer.eval_set`` pointing at the shared evaluation set
(``results/paper_table_eval_set.json``, sampled once with ``--eval-seed``), so every row flies the
same scenarios with its deterministic actor alone. ``heuristic`` trains nothing (0 frames).

Methods that cannot reach the frame budget in their wall-clock cap (``sac_llm``: one answer of
the local SmolLM2 takes seconds, and the proximity trigger asks it for many rows per step) are
run with frequent checkpoints, stopped at the cap, and their last checkpoint is evaluated with
``python -m uavlae.evaluate`` on the same set; the frames they reached are in the table and the
row is flagged. Nothing is extrapolated.

Writes ``results/paper_table.csv`` (one row per method: mean and std over seeds),
``results/paper_table_runs.csv`` (one row per run), ``results/paper_table.md`` and
``results/paper_table.json`` (everything, with the machine and the commands).

The Hydra multirun form gives the same runs without the aggregation::

    python -m uavlae.train -m +exp=sac,ppo seed=0,1 trainer.total_frames=12288 \
        trainer.eval_set=$PWD/results/paper_table_eval_set.json
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import os
import shlex
import signal
import subprocess
import sys
import time
from pathlib import Path

import torch

from uavlae.envs import make_env_config
from uavlae.envs.metrics import PAPER_METRICS
from uavlae.evaluate import load_or_make_eval_set
from uavlae.machine import describe_machine  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
METHODS = ("heuristic", "sac", "sac_heuristic", "sac_llm", "ppo", "ddpg", "cpo")
CONTROLLERS = ("heuristic", "llm")  # evaluation-only: no training frames



def _code_version(run_dir: Path) -> dict:
    """The commit a run used, from the meta.json that uavlae.train wrote when it started."""
    try:
        git = json.loads((run_dir / "meta.json").read_text())["git"]
        return {"git_commit": git.get("commit", "")[:10], "git_dirty": bool(git.get("dirty"))}
    except (OSError, KeyError, ValueError):
        return {"git_commit": "", "git_dirty": None}


def _env() -> dict:
    env = dict(os.environ)
    env.update({"OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1", "UAVLAE_NUM_THREADS": "1"})
    env.setdefault("WANDB_MODE", "disabled")
    return env


def train_command(method: str, seed: int, frames: int, run_dir: Path, eval_set: Path, a: argparse.Namespace,
                  capped: bool) -> list[str]:
    cmd = [sys.executable, "-m", "uavlae.train", f"+exp={method}", f"seed={seed}", "threads=1",
           f"run_dir={run_dir}", f"trainer.eval_set={eval_set}", f"trainer.eval_episodes={a.eval_episodes}",
           f"trainer.eval_seed={a.eval_seed}", "trainer.progress_bar=false", "trainer.eval_plots=1"]
    if method in CONTROLLERS:
        return cmd
    cmd += [f"trainer.total_frames={frames}", "trainer.eval_every_frames=0", "trainer.checkpoint_replay_buffer=false"]
    if capped:
        # small collector batches and a checkpoint after each, so the cap loses little; utd stays 1
        cmd += [f"trainer.frames_per_batch={a.capped_frames_per_batch}",
                f"trainer.checkpoint_every_frames={a.capped_frames_per_batch}"]
    else:
        cmd += ["trainer.checkpoint_every_frames=0"]
    return cmd


def run_one(method: str, seed: int, a: argparse.Namespace, eval_set: Path) -> dict:
    run_dir = Path(a.run_root).resolve() / f"{method}_seed{seed}"
    capped = method in a.capped
    cap_s = a.cap_minutes * 60 if capped else None
    cmd = train_command(method, seed, a.frames, run_dir, eval_set, a, capped)
    done = run_dir / "paper_table_row.json"
    if a.reuse and done.is_file():
        row = json.loads(done.read_text())
        if row["command"] == shlex.join(["python"] + cmd[1:]) and row.get("cap_minutes") == (a.cap_minutes if capped else None):
            print(f"[paper_table] {method} seed {seed}: reusing {done}", flush=True)
            return {**row, **_code_version(run_dir)}
    print(f"[paper_table] {method} seed {seed}: {shlex.join(cmd[1:])}", flush=True)
    log = run_dir.parent / f"{run_dir.name}.log"
    log.parent.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    stopped = False
    with log.open("w") as fh:
        proc = subprocess.Popen(cmd, cwd=ROOT, env=_env(), stdout=fh, stderr=subprocess.STDOUT, start_new_session=True)
        try:
            rc = proc.wait(timeout=cap_s)
        except subprocess.TimeoutExpired:
            stopped = True
            os.killpg(proc.pid, signal.SIGTERM)  # our own child's session (it may hold the LLM server)
            try:
                rc = proc.wait(timeout=30)
            except subprocess.TimeoutExpired:
                os.killpg(proc.pid, signal.SIGKILL)
                rc = proc.wait()
    wall = time.perf_counter() - t0
    row = {"method": method, "seed": seed, "command": shlex.join(["python"] + cmd[1:]), "wall_s": round(wall, 1),
           "stopped_at_cap": stopped, "target_frames": 0 if method in CONTROLLERS else a.frames}
    if not stopped:
        if rc != 0:
            raise RuntimeError(f"{method} seed {seed} failed (rc={rc}); see {log}")
        final = json.loads((run_dir / "final_metrics.json").read_text())
        row["frames"] = int(final.get("frames", 0))
        row["updates"] = int(final.get("updates", 0))
        metrics = {k: final.get(f"eval/{k}", float("nan")) for k in PAPER_METRICS}
    else:
        ckpt = run_dir / "checkpoints" / "last.pt"
        if not ckpt.exists():
            row["frames"] = 0
            metrics = {k: float("nan") for k in PAPER_METRICS}
            row["note"] = f"no checkpoint within the {a.cap_minutes:g} min cap"
        else:
            ev = [sys.executable, "-m", "uavlae.evaluate", f"checkpoint={ckpt}", "threads=1",
                  f"trainer.eval_set={eval_set}", f"trainer.eval_episodes={a.eval_episodes}",
                  f"trainer.eval_seed={a.eval_seed}", "trainer.eval_plots=1"]
            row["eval_command"] = shlex.join(["python"] + ev[1:])
            t1 = time.perf_counter()
            subprocess.run(ev, cwd=ROOT, env=_env(), check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
            row["eval_wall_s"] = round(time.perf_counter() - t1, 1)
            state = torch.load(ckpt, map_location="cpu", weights_only=False)
            row["frames"] = int(state["counters"]["frames"])
            row["updates"] = int(state["counters"]["updates"])
            out = sorted((run_dir / "evaluate").glob(f"last_frames{row['frames']}/metrics.json"))
            agg = json.loads(out[-1].read_text())
            metrics = {k: agg.get(k, float("nan")) for k in PAPER_METRICS}
            row["note"] = (f"stopped at the {a.cap_minutes:g} min cap at {row['frames']} of {a.frames} frames, "
                           f"{row['updates']} gradient steps")
    row.update(metrics)
    row.update(_code_version(run_dir))
    row["cap_minutes"] = a.cap_minutes if capped else None
    done.write_text(json.dumps(row, indent=1) + "\n")
    print(f"[paper_table]   -> {row['frames']} frames, {wall:.0f} s, "
          + ", ".join(f"{k} {row[k]:.3f}" for k in PAPER_METRICS), flush=True)
    return row


def _mean_std(xs: list[float]) -> tuple[float, float]:
    xs = [x for x in xs if not math.isnan(x)]
    if not xs:
        return float("nan"), float("nan")
    m = sum(xs) / len(xs)
    s = math.sqrt(sum((x - m) ** 2 for x in xs) / (len(xs) - 1)) if len(xs) > 1 else float("nan")
    return m, s


def aggregate(rows: list[dict]) -> list[dict]:
    out = []
    for method in dict.fromkeys(r["method"] for r in rows):
        rs = [r for r in rows if r["method"] == method]
        agg = {"method": method, "seeds": " ".join(str(r["seed"]) for r in rs),
               "frames": " ".join(str(r["frames"]) for r in rs),
               "updates": " ".join(str(r.get("updates", "")) for r in rs), "target_frames": rs[0]["target_frames"],
               "wall_s_mean": round(sum(r["wall_s"] for r in rs) / len(rs), 1),
               "flag": "; ".join(r["note"] for r in rs if r.get("note"))}
        for k in PAPER_METRICS:
            m, s = _mean_std([float(r[k]) for r in rs])
            agg[f"{k}_mean"], agg[f"{k}_std"] = m, s
        out.append(agg)
    return out


def _fmt(m: float, s: float) -> str:
    if math.isnan(m):
        return "n/a"
    return f"{m:.3f}" if math.isnan(s) else f"{m:.3f} ± {s:.3f}"


def write_outputs(rows: list[dict], table: list[dict], a: argparse.Namespace, meta: dict) -> None:
    out = Path(a.out_dir)
    out.mkdir(parents=True, exist_ok=True)
    with (out / "paper_table.csv").open("w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(table[0]))
        w.writeheader()
        w.writerows(table)
    keys = list(dict.fromkeys(k for r in rows for k in r))
    with (out / "paper_table_runs.csv").open("w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=keys)
        w.writeheader()
        w.writerows(rows)
    (out / "paper_table.json").write_text(json.dumps({**meta, "table": table, "runs": rows}, indent=1) + "\n")
    lines = [
        "# Paper table: default scenario distribution",
        "",
        f"Command: `{meta['command']}`  ",
        f"Date: {meta['date']}  ",
        f"Training frames per run: {a.frames} (equal for every learner; `heuristic` trains nothing)  ",
        f"Seeds: {' '.join(map(str, a.seeds))}  ",
        f"Evaluation: the deterministic actor alone on {a.eval_episodes} fixed scenarios "
        f"(`{Path(meta['eval_set']).relative_to(ROOT) if Path(meta['eval_set']).is_relative_to(ROOT) else meta['eval_set']}`, "
        f"seed {a.eval_seed}), one episode each, up to t_max steps  ",
        f"Machine: {meta['machine']['cpu']}, {meta['machine']['logical_cores']} logical cores shared with other jobs "
        f"(load average at start {meta['machine']['load_average_1_5_15']}), torch {meta['machine']['torch']}, 1 thread  ",
        "Code (per run, from its meta.json): "
        + ", ".join(sorted({f"{r['git_commit']}{' (dirty tree)' if r.get('git_dirty') else ''}" for r in rows}))
        + "; runs made at different times can differ in commit  ",
        f"Total wall time: {meta['total_wall_s'] / 60:.1f} min (sum over the runs, reused ones included)",
        "",
        "Mean ± std over seeds (std only with 2+ seeds). DCR, SLR: higher is better; CR, RVR, ECR: lower is better. "
        "updates: the training loop's counter (sac, sac_*, ddpg: gradient steps, none before the 5000 "
        "uniform-random warm-up frames; ppo, cpo: rollout updates of 10 epochs x 8 minibatches).",
        "",
        "| method | DCR | CR | SLR | RVR | ECR | frames | updates | wall s (mean) | seeds | flag |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for t in table:
        cells = [_fmt(t[f"{k}_mean"], t[f"{k}_std"]) for k in PAPER_METRICS]
        lines.append(f"| {t['method']} | " + " | ".join(cells)
                     + f" | {t['frames']} | {t['updates']} | {t['wall_s_mean']} | {t['seeds']} | {t['flag']} |")
    if a.note:
        lines += ["", a.note]
    lines += ["", "Per-run commands (`python` = `.venv/bin/python`, from the repository root):", ""]
    for r in rows:
        lines.append(f"- `{r['command']}`" + (f" then `{r['eval_command']}`" if r.get("eval_command") else ""))
    lines.append("")
    (out / "paper_table.md").write_text("\n".join(lines))


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--methods", nargs="+", default=list(METHODS), choices=METHODS)
    p.add_argument("--seeds", nargs="+", type=int, default=[0])
    p.add_argument("--frames", type=int, default=12288, help="training frames of every learner")
    p.add_argument("--eval-episodes", type=int, default=32)
    p.add_argument("--eval-seed", type=int, default=12345)
    p.add_argument("--capped", nargs="*", default=["sac_llm"], help="methods run under --cap-minutes")
    p.add_argument("--cap-minutes", type=float, default=6.0, help="wall-clock cap of each capped run")
    p.add_argument("--capped-frames-per-batch", type=int, default=64, help="collector batch (and checkpoint) of capped runs")
    p.add_argument("--reuse", action="store_true",
                   help="reuse a run whose run dir holds a result of the identical command (adding seeds)")
    p.add_argument("--note", default="", help="a paragraph for paper_table.md (how to read these numbers)")
    p.add_argument("--run-root", default=str(ROOT / "runs" / "paper_table"))
    p.add_argument("--out-dir", default=str(ROOT / "results"))
    a = p.parse_args(argv)

    torch.set_num_threads(1)
    meta = {"command": "python experiments/paper_table.py " + shlex.join(sys.argv[1:] if argv is None else argv),
            "date": time.strftime("%Y-%m-%d %H:%M:%S %Z"), "machine": describe_machine(torch_threads=1)}
    eval_set = Path(a.out_dir).resolve() / "paper_table_eval_set.json"
    env_cfg = make_env_config(None)
    load_or_make_eval_set(env_cfg, eval_set, a.eval_episodes, a.eval_seed)  # sampled once, then reused
    meta["eval_set"] = str(eval_set)
    rows = []
    for method in a.methods:
        for seed in a.seeds:
            rows.append(run_one(method, seed, a, eval_set))
            meta["total_wall_s"] = sum(r["wall_s"] + float(r.get("eval_wall_s") or 0) for r in rows)
            write_outputs(rows, aggregate(rows), a, meta)  # partial results survive an interruption
    print((Path(a.out_dir) / "paper_table.md").read_text())


if __name__ == "__main__":
    main()
