"""Training frames/s of ``python -m uavlae.train``, this checkout against another one, side by side.

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/train_ab.py --base ../other-checkout \
        [--exps sac sac_heuristic] [--env-batch 16 64] [--rounds 9] [--frames 8192] [--update-steps 2000]   (make bench-train)

``--base`` is another checkout of the project (a ``git worktree`` of an earlier commit, say);
it runs with its own ``.venv`` when it has one, else with this interpreter (each side imports
its own code: the subprocess starts in its checkout). Every measurement is a whole training run
of that checkout's ``uavlae.train``, and its frames/s is what the run itself reports in
``summary.json`` (frames over the time spent collecting and updating; evaluations, baselines and
start-up are not counted), so the figure is the training loop as a user runs it. The two sides
alternate, in opposite order from round to round, so both see the same machine.

Writes ``benchmarks/train_ab.json``: per setting, every round's frames/s of both sides, the
paired ratios (ours / base), their median and a 95% bootstrap interval of the median over
rounds, with the machine and both commits. ``--update-steps``: also SAC's update alone on each side
(alternating processes, one fixed batch), to tell a slower loop from a slower update; ``--exps``
with no name times only that.
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
from typing import Any, Callable

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from uavlae.machine import describe_machine  # noqa: E402


def _python(checkout: Path) -> str:
    own = checkout / ".venv" / "bin" / "python"
    return str(own) if own.is_file() else sys.executable


def one_run(checkout: Path, exp: str, env_batch: int, frames: int) -> dict[str, float]:
    """One ``uavlae.train`` run in ``checkout``: its own frames/s, and its seconds of training
    and of gradient steps (the rest is collection)."""
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
        summary = json.loads((out / "run" / "summary.json").read_text())
        return {k: float(summary[k]) for k in ("fps", "train_s", "update_s")}
    finally:
        shutil.rmtree(out, ignore_errors=True)


UPDATE_ONLY = """
import sys, time, torch
from tensordict import TensorDict
from uavlae.algos.sac import make_sac
from uavlae.envs.uav_env import UAVEnv
torch.manual_seed(0)
env = UAVEnv(batch_size=4)
obs_dim, n, steps = env.observation_spec["observation"].shape[-1], 256, int(sys.argv[1])
learner = make_sac(None, obs_dim, env.action_spec)
nxt = {"observation": torch.randn(n, obs_dim), "reward": torch.randn(n, 1),
       "terminated": torch.zeros(n, 1, dtype=torch.bool), "done": torch.zeros(n, 1, dtype=torch.bool)}
batch = TensorDict({"observation": torch.randn(n, obs_dim), "action": torch.rand(n, 2) * 2 - 1,
                    "next": TensorDict(nxt, [n])}, [n])
for _ in range(100):
    learner.update(batch)
t0 = time.perf_counter()
for _ in range(steps):
    learner.update(batch)
print(steps / (time.perf_counter() - t0))
"""


def one_update_run(checkout: Path, steps: int) -> float:
    """SAC's update alone (``+exp=sac``'s default learner, one fixed batch of 256) in
    ``checkout``: updates/s, to tell the loop's cost from the update's."""
    env = dict(os.environ, OMP_NUM_THREADS="1", MKL_NUM_THREADS="1")
    out = subprocess.run([_python(checkout), "-c", UPDATE_ONLY, str(steps)], cwd=checkout, env=env, check=True,
                         capture_output=True, text=True)
    return float(out.stdout.strip().splitlines()[-1])


def commit_of(checkout: Path) -> str:
    """The checkout's commit (``+dirty`` when its tracked files differ), or ``unknown``."""
    def git(*args: str) -> str:
        return subprocess.run(["git", "-C", str(checkout), *args], capture_output=True, text=True).stdout.strip()
    head = git("rev-parse", "--short=10", "HEAD")
    if not head:
        return "unknown"
    # the record this run writes is the one tracked file allowed to change while it runs
    dirty = [line for line in git("status", "--porcelain", "--untracked-files=no").splitlines()
             if not line.endswith("benchmarks/train_ab.json")]
    return head + ("+dirty" if dirty else "")


def bootstrap_median(xs: list[float], n: int = 5000, seed: int = 0) -> tuple[float, float]:
    rng = random.Random(seed)
    meds = sorted(statistics.median(rng.choices(xs, k=len(xs))) for _ in range(n))
    return meds[int(0.025 * n)], meds[int(0.975 * n) - 1]


def alternate(rounds: int, base: Path, measure: Callable[[Path], Any], label: str,
              rate: Callable[[Any], float], unit: str) -> dict[str, list[Any]]:
    """``measure`` in this checkout and in ``base``, ``rounds`` times, in opposite order from round
    to round so both sides see the same machine; each side's measurements."""
    got: dict[str, list[Any]] = {"ours": [], "base": []}
    for r in range(rounds):
        order = (("ours", ROOT), ("base", base)) if r % 2 == 0 else (("base", base), ("ours", ROOT))
        for side, where in order:
            got[side].append(measure(where))
        print(f"{label} round {r}: ours {rate(got['ours'][-1]):.1f} base {rate(got['base'][-1]):.1f} {unit}", flush=True)
    return got


def paired(ours: list[float], theirs: list[float], label: str) -> dict[str, Any]:
    """The paired ratios (ours / base), their median and its 95% bootstrap interval."""
    ratios = [o / t for o, t in zip(ours, theirs)]
    lo, hi = bootstrap_median(ratios)
    print(f"{label}: median ratio {statistics.median(ratios):.3f} [{lo:.3f}, {hi:.3f}]", flush=True)
    return {"ratios": ratios, "median_ratio": statistics.median(ratios), "ratio_ci95": [lo, hi]}


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--base", type=Path, required=True)
    p.add_argument("--exps", nargs="*", default=["sac", "sac_heuristic"])
    p.add_argument("--env-batch", type=int, nargs="+", default=[16, 64])
    p.add_argument("--rounds", type=int, default=9)
    p.add_argument("--frames", type=int, default=8192)
    p.add_argument("--update-steps", type=int, default=2000,
                   help="also time SAC's update alone, this many steps a round on each side (0: skip)")
    p.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "train_ab.json")
    a = p.parse_args(argv)
    base = a.base.resolve()
    commits = {"ours": commit_of(ROOT), "base": commit_of(base)}
    results = []
    for exp in a.exps:
        for b in a.env_batch:
            runs = alternate(a.rounds, base, lambda where, exp=exp, b=b: one_run(where, exp, b, a.frames),
                             f"{exp} B={b}", lambda got: got["fps"], "frames/s")
            ours, theirs = ([run["fps"] for run in runs[side]] for side in ("ours", "base"))
            seconds = {side: [{k: run[k] for k in ("train_s", "update_s")} for run in runs[side]] for side in runs}
            results.append({"exp": exp, "env_batch": b, "frames": a.frames, "ours_fps": ours, "base_fps": theirs,
                            **paired(ours, theirs, f"{exp} B={b}"), "seconds": seconds})
    update_only = None
    if a.update_steps:
        runs = alternate(a.rounds, base, lambda where: one_update_run(where, a.update_steps), "update alone",
                         lambda got: got, "updates/s")
        update_only = {"steps": a.update_steps, "ours_updates_per_s": runs["ours"],
                       "base_updates_per_s": runs["base"], **paired(runs["ours"], runs["base"], "update alone")}
    command = (f"python benchmarks/train_ab.py --base <a checkout of {base.name}> --exps {' '.join(a.exps)} "
               f"--env-batch {' '.join(map(str, a.env_batch))} --rounds {a.rounds} --frames {a.frames} --update-steps {a.update_steps}")
    report = {"command": command,
              "base": base.name, "commits": commits, "machine": describe_machine(), "results": results,
              "update_alone": update_only}
    a.out.write_text(json.dumps(report, indent=1) + "\n")


if __name__ == "__main__":
    main()
