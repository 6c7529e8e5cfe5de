"""Training frames/s of ``+exp=sac``, this checkout against another one, side by side.

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/train_ab.py --base ../other-checkout \
        [--env-batch 16 64] [--compile-env false true] [--rounds 3] [--batches 2]   (make bench-train)

``--base`` is another checkout of the project with its own ``.venv`` (a ``git worktree`` of an
earlier commit, for example). Each measurement is a fresh subprocess that runs this file's
worker with that checkout's interpreter, in that checkout, so each side imports only its own
code. The two sides alternate, in opposite order from round to round, so both see the same
machine.

The worker builds what ``uavlae.train`` builds for ``+exp=sac`` (env, SAC learner, override
policy, collector, replay buffer, seed 0, one torch thread), collects one batch of
``trainer.frames_per_batch`` frames with the random warm-up (and the one-off compile of the
step when ``--compile-env true``), then times ``--batches`` batches of the training loop: a
collector batch, the replay extend, and ``utd_ratio`` updates per frame (each on a replay
sample). Evaluation, logging and checkpoints are left out. It prints frames/s.

Writes ``benchmarks/train_ab.json``: per setting, every round's frames/s of both sides, the
paired ratios (ours / base) and their median, with the machine.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
WARMUP_RANDOM_FRAMES = 256  # the replay holds one SAC batch before the first update


def worker(env_batch: int, compile_env: bool, batches: int) -> None:
    import torch
    from hydra import compose, initialize_config_dir

    from uavlae.checkpoint import seed_everything
    from uavlae.collect import TRANSITION_KEYS, UAVCollector, make_replay_buffer
    from uavlae.envs import make_env_config
    from uavlae.factories import behaviour_actor, make_env, make_learner, make_policy, make_trainer_config
    from uavlae.train import REPLAY_KEYS

    torch.set_num_threads(1)
    overrides = [
        "+exp=sac", f"trainer.env_batch_size={env_batch}", f"trainer.compile_env={str(compile_env).lower()}",
        f"trainer.init_random_frames={WARMUP_RANDOM_FRAMES}",
    ]
    # the configs of the checkout this runs in: inside the package, or at the root in older commits
    conf = next(d for d in (Path.cwd() / "uavlae" / "conf", Path.cwd() / "conf") if d.is_dir())
    with initialize_config_dir(config_dir=str(conf), version_base="1.3"):
        cfg = compose(config_name="config", overrides=overrides)
    tr = make_trainer_config(cfg.trainer)
    env_cfg = make_env_config(cfg.env)
    seed_everything(0)
    env = make_env(env_cfg, tr.env_batch_size, seed=0, compile_step=tr.compile_env)
    learner = make_learner(cfg.algo, env)
    policy = make_policy(cfg, behaviour_actor(learner), env_cfg)
    collector = UAVCollector(
        env, policy, frames_per_batch=tr.frames_per_batch, total_frames=None,
        init_random_frames=tr.init_random_frames, keep_keys=TRANSITION_KEYS, seed=0,
    )
    replay = make_replay_buffer(tr.replay_capacity, tr.batch_size, seed=0)
    debt = 0.0

    def one_batch() -> int:
        nonlocal debt
        batch = collector.rollout_batch()
        replay.extend(batch.select(*REPLAY_KEYS, strict=False).reshape(-1))
        debt += tr.utd_ratio * collector.frames_per_batch
        n = int(debt)
        debt -= n
        for _ in range(n):
            learner.update(replay.sample())
        return collector.frames_per_batch

    one_batch()  # the warm-up: random actions, the first updates, the compile of the step
    t = time.perf_counter()
    frames = sum(one_batch() for _ in range(batches))
    print(json.dumps({"fps": frames / (time.perf_counter() - t), "frames": frames}))


def _measure(checkout: Path, env_batch: int, compile_env: bool, batches: int) -> float:
    python = checkout / ".venv" / "bin" / "python"
    cmd = [str(python), str(Path(__file__).resolve()), "--worker", "--env-batch", str(env_batch),
           "--compile-env", str(compile_env).lower(), "--batches", str(batches)]
    env = {**os.environ, "OMP_NUM_THREADS": "1", "UAVLAE_NUM_THREADS": "1", "WANDB_MODE": "disabled"}
    out = subprocess.run(cmd, cwd=checkout, env=env, capture_output=True, text=True, check=False)
    if out.returncode != 0:
        raise RuntimeError(f"the worker failed in {checkout}:\n{out.stderr[-3000:]}")
    return float(json.loads(out.stdout.strip().splitlines()[-1])["fps"])


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--base", type=Path, help="the other checkout (with its own .venv)")
    p.add_argument("--env-batch", type=int, nargs="+", default=[16, 64])
    p.add_argument("--compile-env", choices=["false", "true"], nargs="+", default=["false", "true"])
    p.add_argument("--rounds", type=int, default=3)
    p.add_argument("--batches", type=int, default=2, help="timed collector batches per measurement")
    p.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "train_ab.json")
    p.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    a = p.parse_args(argv)
    if a.worker:
        worker(a.env_batch[0], a.compile_env[0] == "true", a.batches)
        return
    if a.base is None or not (a.base / ".venv" / "bin" / "python").exists():
        p.error("--base must be a checkout of the project with its own .venv")
    from uavlae.factories import dump_json
    from uavlae.files import portable
    from uavlae.machine import describe_machine

    base, ours = a.base.resolve(), ROOT
    rows = []
    for compile_env in a.compile_env:
        for b in a.env_batch:
            fps: dict[str, list[float]] = {"ours": [], "base": []}
            for r in range(a.rounds):
                order = [("ours", ours), ("base", base)] if r % 2 == 0 else [("base", base), ("ours", ours)]
                for name, checkout in order:
                    fps[name].append(_measure(checkout, b, compile_env == "true", a.batches))
            ratios = [o / s for o, s in zip(fps["ours"], fps["base"])]
            row = {"env_batch": b, "compile_env": compile_env == "true",
                   "command": portable("python benchmarks/train_ab.py " + " ".join(sys.argv[1:] if argv is None else argv),
                                       ROOT),
                   "fps_ours": fps["ours"],
                   "fps_base": fps["base"], "ratios": ratios, "median_ratio": statistics.median(ratios)}
            rows.append(row)
            print(f"B = {b:3d} compile_env = {compile_env:5s}: ours {statistics.median(fps['ours']):7.0f} "
                  f"base {statistics.median(fps['base']):7.0f} frames/s, ours / base x{row['median_ratio']:.3f}",
                  flush=True)
    out = {
        "what": "training frames/s of +exp=sac (collector batch, replay extend, utd updates), ours vs --base",
        "base": portable(str(base), ROOT),
        "rows": rows,
        "machine": describe_machine(),
    }
    if a.out.exists():  # keep the rows of other settings measured earlier into the same file
        old = json.loads(a.out.read_text())
        if old.get("base") == out["base"]:
            keep = [r for r in old.get("rows", []) if (r["env_batch"], r["compile_env"]) not in
                    {(x["env_batch"], x["compile_env"]) for x in rows}]
            out["rows"] = keep + rows
    dump_json(a.out, out)


if __name__ == "__main__":
    main()
