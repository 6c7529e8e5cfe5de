"""The paper's greedy heuristic against the global planner beyond the paper, on the same scenarios.

    python -m uavlae.experiments.heuristics_table   # make heuristics-table; writes results/heuristics_table.{json,md}

Each (method, evaluation set) is one ``python -m uavlae.train +exp=METHOD`` subprocess (the
evaluation-only controllers: no training) with ``trainer.eval_set`` pointing at the set:

- the 32 fixed scenarios every training run is evaluated on by default (``results/eval_set_32.json``:
  SPEC's world, ``trainer.eval_episodes`` = 32, ``trainer.eval_seed`` = 12345; the first run that
  names a missing set samples and saves it; the sweeps' ``eval_sets/train.json`` is the same set);
- 256 scenarios sampled with ``--sample-seed`` and saved once to
  ``results/heuristics_eval_set_256.json``.

Writes ``results/heuristics_table.json`` (the five metrics and the per-event rates of every run,
the exact commands, wall-clock seconds and the machine) and ``results/heuristics_table.md``.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import torch

from uavlae.envs import make_env_config
from uavlae.envs.metrics import PAPER_METRICS
from uavlae.envs.scenario import sample_scenarios, save_scenarios, unstack_scenarios
from uavlae.experiments.reporting import cell_true, markdown_table, read_json, read_rows, write_text
from uavlae.files import dump_json, portable
from uavlae.machine import describe_machine

# the repository's results folder: the tool runs from the checkout's root (make heuristics-table)
RESULTS = Path("results")
METHODS = {
    "heuristic": "the paper's greedy heuristic (uavlae.policies.greedy)",
    "heuristic_planner": "visibility-graph planner, beyond the paper (uavlae.policies.heuristic)",
}
EVENTS = ("bz_collision", "nfz_entry", "ou_collision", "boundary_exit")  # columns of episodes.csv


def _sampled_set(n: int, seed: int) -> Path:
    path = RESULTS / f"heuristics_eval_set_{n}.json"
    if not path.is_file():
        g = torch.Generator().manual_seed(seed)
        save_scenarios(path, unstack_scenarios(sample_scenarios(make_env_config(), n, g)))
    return path


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--sampled", type=int, default=256, help="size of the sampled evaluation set")
    p.add_argument("--sample-seed", type=int, default=2026)
    p.add_argument("--eval-seed", type=int, default=12345, help="seeds the evaluation env (OU motion)")
    a = p.parse_args()
    sets = {"eval_set_32": RESULTS / "eval_set_32.json", f"sampled_{a.sampled}": _sampled_set(a.sampled, a.sample_seed)}
    runs = []
    with tempfile.TemporaryDirectory() as tmp:
        for set_name, set_path in sets.items():
            for method in METHODS:
                run_dir = Path(tmp) / f"{method}_{set_name}"
                cmd = [
                    sys.executable, "-m", "uavlae.train", f"+exp={method}", f"run_dir={run_dir}",
                    f"trainer.eval_set={set_path}", f"trainer.eval_seed={a.eval_seed}", "trainer.eval_plots=0",
                    "logger.wandb.mode=disabled",
                ]
                t0 = time.perf_counter()
                subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL)
                wall = time.perf_counter() - t0
                final = read_json(run_dir / "final_metrics.json")
                metrics = {k: final[f"eval/{k}"] for k in (*PAPER_METRICS, "mean_length")}
                rows = read_rows(next((run_dir / "eval").glob("*/episodes.csv")))
                for k in EVENTS:  # the share of episodes that ended in each kind of collision
                    metrics[f"{k}_rate"] = sum(cell_true(r[k]) for r in rows) / len(rows)
                shown = [c if not c.startswith("run_dir=") else "run_dir=<tmp>" for c in cmd[1:]]
                runs.append({"method": method, "eval_set": set_name, "episodes": final.get("eval/n_episodes"),
                             "metrics": metrics, "wall_s": round(wall, 1),
                             "command": portable("python " + " ".join(shown), Path.cwd())})
                print(method, set_name, {k: round(v, 3) for k, v in metrics.items()}, f"{wall:.0f} s", flush=True)
    out = {"runs": runs, "methods": METHODS, "sets": {k: v.as_posix() for k, v in sets.items()},
           "command": "python -m uavlae.experiments.heuristics_table " + " ".join(sys.argv[1:]), "machine": describe_machine()}
    dump_json(RESULTS / "heuristics_table.json", out)
    write_text(RESULTS / "heuristics_table.md", markdown(out, a.eval_seed))


def markdown(out: dict, eval_seed: int) -> str:
    """The table of ``heuristics_table.json`` (``out``) as ``heuristics_table.md``."""
    events = {"bz_collision": "BZ", "nfz_entry": "NFZ", "ou_collision": "OU"}  # EVENTS' collisions, as headed
    rows = [{"method": r["method"], "evaluation set": r["eval_set"], "episodes": f"{r['episodes']:.0f}",
             **{k: f"{r['metrics'][k]:.3f}" for k in PAPER_METRICS},
             **{name: f"{r['metrics'][k + '_rate']:.3f}" for k, name in events.items()}, "wall s": r["wall_s"]}
            for r in out["runs"]]
    lines = [
        "# The greedy heuristic (the paper's) and the global planner (beyond the paper)", "",
        f"Command: `{out['command'].strip()}`; one episode per scenario, up to t_max slots; "
        f"evaluation env seed {eval_seed}. Machine: {out['machine']['cpu']}, torch {out['machine']['torch']}.", "",
        *markdown_table(rows, ["method", "evaluation set", "episodes", *PAPER_METRICS, *events.values(), "wall s"]),
        "", "BZ, NFZ, OU: the share of episodes that ended in that collision (their sum is CR).",
    ]
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    main()
