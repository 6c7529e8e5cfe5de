"""Training frames/s of ``python -m uavlae.train``, this checkout against another one, side by side.

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/train_ab.py --base ../other-checkout \
        [--exps sac sac_heuristic] [--env-batch 16 64] [--rounds 9] [--frames 8192]   (make bench-train)

``--base`` is another checkout of the project (a ``git worktree`` of an earlier commit, say);
it runs with its own ``.venv`` when it has one, else with this interpreter (each side imports
its own code: the subprocess starts in its checkout). Every measurement is a whole training run
of that checkout's ``uavlae.train``, and its frames/s is what the run itself reports in
``summary.json`` (frames over the time spent collecting and updating; evaluations, baselines and
start-up are not counted), so the figure is the training loop as a user runs it. The two sides
alternate, in opposite order from round to round, so both see the same machine.

Writes ``benchmarks/train_ab.json``: per setting, every round's frames/s of both sides, the
paired ratios (ours / base), their median and a 95% bootstrap interval of the median over
rounds, with the machine.
"""

from __future__ import annotations

import argparse
import json
import os
import random
import shutil
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from uavlae.machine import describe_machine  # noqa: E402


def _python(checkout: Path) -> str:
    own = checkout / ".venv" / "bin" / "python"
    return str(own) if own.is_file() else sys.executable


def one_run(checkout: Path, exp: str, env_batch: int, frames: int) -> float:
    """One ``uavlae.train`` run in ``checkout``; its own frames/s."""
    out = Path(tempfile.mkdtemp(prefix="train_ab_"))
    try:
        args = [
            f"+exp={exp}", f"run_dir={out / 'run'}", f"trainer.total_frames={frames}",
            f"trainer.env_batch_size={env_batch}", "trainer.init_random_frames=1024", "trainer.eval_episodes=2",
            "trainer.eval_max_steps=10", "trainer.eval_every_frames=0", "trainer.checkpoint_every_frames=0",
            "trainer.eval_plots=0", "trainer.baselines=false", "trainer.progress_bar=false",
            "logger.wandb.mode=disabled", "hydra.output_subdir=null", "hydra/job_logging=stdout",
        ]
        env = dict(os.environ, OMP_NUM_THREADS="1", MKL_NUM_THREADS="1", WANDB_MODE="disabled")
        subprocess.run([_python(checkout), "-m", "uavlae.train", *args], cwd=checkout, env=env, check=True,
                       stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
        return float(json.loads((out / "run" / "summary.json").read_text())["fps"])
    finally:
        shutil.rmtree(out, ignore_errors=True)


def bootstrap_median(xs: list[float], n: int = 5000, seed: int = 0) -> tuple[float, float]:
    rng = random.Random(seed)
    meds = sorted(statistics.median(rng.choices(xs, k=len(xs))) for _ in range(n))
    return meds[int(0.025 * n)], meds[int(0.975 * n) - 1]


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--base", type=Path, required=True)
    p.add_argument("--exps", nargs="+", default=["sac", "sac_heuristic"])
    p.add_argument("--env-batch", type=int, nargs="+", default=[16, 64])
    p.add_argument("--rounds", type=int, default=9)
    p.add_argument("--frames", type=int, default=8192)
    p.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "train_ab.json")
    a = p.parse_args(argv)
    base = a.base.resolve()
    results = []
    for exp in a.exps:
        for b in a.env_batch:
            ours, theirs = [], []
            for r in range(a.rounds):
                order = (("ours", ROOT), ("base", base)) if r % 2 == 0 else (("base", base), ("ours", ROOT))
                got = {side: one_run(where, exp, b, a.frames) for side, where in order}
                ours.append(got["ours"])
                theirs.append(got["base"])
                print(f"{exp} B={b} round {r}: ours {got['ours']:.1f} base {got['base']:.1f} frames/s", flush=True)
            ratios = [o / t for o, t in zip(ours, theirs)]
            lo, hi = bootstrap_median(ratios)
            results.append({"exp": exp, "env_batch": b, "frames": a.frames, "ours_fps": ours, "base_fps": theirs,
                            "ratios": ratios, "median_ratio": statistics.median(ratios), "ratio_ci95": [lo, hi]})
            print(f"{exp} B={b}: median ratio {statistics.median(ratios):.3f} [{lo:.3f}, {hi:.3f}]", flush=True)
    command = (f"python benchmarks/train_ab.py --base <a checkout of {base.name}> --exps {' '.join(a.exps)} "
               f"--env-batch {' '.join(map(str, a.env_batch))} --rounds {a.rounds} --frames {a.frames}")
    report = {"command": command,
              "base": base.name, "machine": describe_machine(), "results": results}
    a.out.write_text(json.dumps(report, indent=1) + "\n")


if __name__ == "__main__":
    main()
