"""Learners beside a base learner (``ppo``) at an equal frame budget: training frames/s and metrics.

    python benchmarks/vs_ppo.py --methods wang --frames 8192     # make bench-wang   -> benchmarks/wang_vs_ppo.json
    python benchmarks/vs_ppo.py --methods theile --frames 8192   # make bench-theile -> benchmarks/theile_vs_ppo.json

Each method is one ``python -m uavlae.train +exp=METHOD`` subprocess, the base first, one after
the other, with the same seed, world, frame budget and evaluation set (the 32
scenarios of results/eval_set_32.json). Reported side by side: the training frames/s of the loop (``time/fps`` at the last
batch: collection plus updates, before the final evaluation) and each method's ratio to the
base's, and the five metrics of each deterministic actor, beside a uniform-random policy on the
same scenarios. Run it on an otherwise idle machine: the frames/s are only comparable within
one run.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import torch
from hydra import compose, initialize_config_dir

from uavlae.envs import make_env_config
from uavlae.envs.metrics import PAPER_METRICS
from uavlae.envs.scenario import load_scenarios
from uavlae.evaluate import Evaluator
from uavlae.factories import CONF_DIR
from uavlae.files import dump_json, portable
from uavlae.machine import describe_machine

ROOT = Path(__file__).resolve().parents[1]
EVAL_SET = ROOT / "results" / "eval_set_32.json"


class UniformRandom(torch.nn.Module):
    """Uniform actions in [-1, 1]^2, seeded: the floor a learner must clear on DCR."""

    def __init__(self, seed: int):
        super().__init__()
        self.g = torch.Generator().manual_seed(seed)

    def forward(self, td):
        b = td["observation"].shape[:-1]
        td["action"] = torch.rand(*b, 2, generator=self.g) * 2 - 1
        return td


def _last(csv_path: Path) -> float:
    return float(csv_path.read_text().strip().splitlines()[-1].split(",")[1])


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--frames", type=int, default=8192)
    p.add_argument("--env", default="shaped", help="uavlae/conf/env group: shaped adds SPEC §10's learning aids")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--base", default="ppo", help="the +exp= every method's frames/s is divided by")
    p.add_argument("--methods", nargs="+", default=["wang"], help="+exp= names run after the base")
    p.add_argument("--out", default=None, help="default: benchmarks/<first method>_vs_<base>.json")
    p.add_argument("overrides", nargs="*", help="extra Hydra overrides for every run (e.g. trainer.env_batch_size=32)")
    a = p.parse_args()
    out_file = Path(a.out) if a.out else ROOT / "benchmarks" / f"{a.methods[0]}_vs_{a.base}.json"
    runs = {}
    with tempfile.TemporaryDirectory() as tmp:
        for method in (a.base, *a.methods):
            run_dir = Path(tmp) / method
            cmd = [
                sys.executable, "-m", "uavlae.train", f"+exp={method}", f"env={a.env}", f"seed={a.seed}",
                f"trainer.total_frames={a.frames}", "trainer.eval_every_frames=0", "trainer.checkpoint_every_frames=0",
                f"trainer.eval_set={EVAL_SET}", "trainer.eval_plots=0", "trainer.progress_bar=false",
                "logger.wandb.mode=disabled", f"run_dir={run_dir}", *a.overrides,
            ]
            t0 = time.perf_counter()
            subprocess.run(cmd, check=True, cwd=ROOT, stdout=subprocess.DEVNULL)
            wall = time.perf_counter() - t0
            final = json.loads((run_dir / "final_metrics.json").read_text())
            runs[method] = {
                "train_fps": _last(run_dir / "logs" / "scalars" / "time" / "fps.csv"),
                "frames": final["frames"],
                "updates": final["updates"],
                "wall_s": round(wall, 1),
                "metrics": {k: final[f"eval/{k}"] for k in PAPER_METRICS},
                "command": portable("python " + " ".join(c if not c.startswith("run_dir=") else "run_dir=<tmp>"
                                                         for c in cmd[1:]), ROOT),
            }
            print(method, runs[method]["train_fps"], runs[method]["metrics"], flush=True)
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        env_cfg = make_env_config(compose("config", overrides=[f"env={a.env}"]).env)
    evaluator = Evaluator(env_cfg, load_scenarios(EVAL_SET), seed=12345, n_plots=0)  # the trainer's eval_seed
    random_agg = evaluator.run(UniformRandom(a.seed))
    out = {
        "frames": a.frames,
        "env": a.env,
        "eval_set": str(EVAL_SET.relative_to(ROOT)),
        "runs": runs,
        "uniform_random": {k: random_agg[k] for k in PAPER_METRICS},
        **{f"fps_ratio_{m}_over_{a.base}": runs[m]["train_fps"] / runs[a.base]["train_fps"] for m in a.methods},
        "command": portable("python benchmarks/vs_ppo.py " + " ".join(sys.argv[1:]), ROOT),
        "machine": describe_machine(),
    }
    dump_json(out_file, out)
    print(json.dumps({k: v for k, v in out.items() if k.startswith("fps_ratio") or k == "uniform_random"}, indent=1))


if __name__ == "__main__":
    main()
