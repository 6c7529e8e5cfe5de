"""Where a training frame's wall clock goes, ours against Stable-Baselines3's SAC, side by side.

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/ttt_cost_breakdown.py [--env shaped_geodesic]
        [--env-batch 64] [--utd 0.25] [--rounds 8]      (make bench-breakdown)

The time-to-target benchmark (``time_to_target.py``) reports training frames/s of each method.
This one takes the per-frame cost apart, in the same regime (``--env-batch`` scenarios stepped
together, ``--utd`` gradient steps per frame, Table 4's networks and batch 256, one thread), by
timing each part alone, in alternating rounds so that both methods see the same machine:

- ours: one SAC update (``learner.update(replay.sample())``, the default fused update), a replay
  sample alone (ours, and torchrl's stock ``TensorDictReplayBuffer.sample`` of the same buffer:
  the A/B of ``uavlae.collect.UniformReplayBuffer``), and one collector step of all ``B`` rows (env step, partial reset, actor,
  episode tracking: ``UAVCollector.step``);
- SB3: ``SAC.train(gradient_steps=16)`` divided by 16 (its replay sample included), and its
  collection of one vector step of ``B`` ``UAVGymEnv`` (``SAC.learn`` with no gradient steps:
  actor, ``DummyVecEnv.step``, replay add).

From these, per ``B`` frames: ``cost = B·utd·update + collect``. The bound printed last is what
the ratio of training frames/s (SB3 cost / our cost) would be if everything of ours except the
updates themselves (collection, sampling, loop) cost nothing: with the same gradient steps per
frame, no implementation of ours can beat it without a faster update. Writes
``benchmarks/ttt_cost_breakdown.json`` with the machine.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))


def _time(fn, n: int) -> float:
    t = time.perf_counter()
    for _ in range(n):
        fn()
    return (time.perf_counter() - t) / n


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--env", default="shaped_geodesic")
    p.add_argument("--env-batch", type=int, default=64)
    p.add_argument("--utd", type=float, default=0.25)
    p.add_argument("--rounds", type=int, default=8)
    p.add_argument("--out", default=str(ROOT / "benchmarks" / "ttt_cost_breakdown.json"))
    a = p.parse_args(argv)
    torch.set_num_threads(1)
    os.environ.setdefault("WANDB_MODE", "disabled")

    from hydra import compose, initialize_config_dir
    from stable_baselines3.common.vec_env import DummyVecEnv
    from torchrl.data import TensorDictReplayBuffer
    from time_to_target import SAC_HP, env_config, make_sb3_sac

    from uavlae.collect import TRANSITION_KEYS, UAVCollector, make_replay_buffer
    from uavlae.envs.gym_adapter import UAVGymEnv
    from uavlae.factories import CONF_DIR, HeuristicGroup, make_env, make_learner, make_policy
    from uavlae.machine import describe_machine
    from uavlae.factories import dump_json
    from uavlae.train import REPLAY_KEYS

    b, utd = a.env_batch, a.utd
    grad_steps = b * utd
    if grad_steps != int(grad_steps) or grad_steps < 1:
        raise SystemExit(f"--env-batch x --utd must be a whole number >= 1, got {grad_steps}")
    grad_steps = int(grad_steps)
    env_cfg = env_config(a.env)

    # ours: the objects uavlae.train builds for +exp=sac
    with initialize_config_dir(str(CONF_DIR), version_base="1.3"):
        cfg = compose("config", overrides=["+exp=sac", f"env={a.env}", "threads=1"])
    env = make_env(env_cfg, b, seed=0)
    learner = make_learner(cfg.algo, env)
    policy = make_policy(cfg.advisor, learner.behaviour, env_cfg, seed=int(cfg.seed), heuristic=HeuristicGroup.of(cfg),
                         llm_cfg=cfg.llm)
    collector = UAVCollector(env, policy, frames_per_batch=b, keep_keys=TRANSITION_KEYS, seed=0)
    replay = make_replay_buffer(1_000_000, SAC_HP["batch_size"], seed=0)
    while len(replay) < 20_000:  # the actor's own transitions (a real mix of states)
        replay.extend(collector.step().select(*REPLAY_KEYS, strict=False).reshape(-1))
    for _ in range(20):  # warm-up: allocator, fused Adam state
        learner.update(replay.sample())

    # SB3, built as benchmarks/time_to_target.py builds it
    vec = DummyVecEnv([lambda: UAVGymEnv(env_cfg) for _ in range(b)])
    vec.seed(0)
    model = make_sb3_sac(vec, 0, learning_starts=0, gradient_steps=0)  # as time_to_target.py, gradient steps timed apart
    model.learn(total_timesteps=20_000, reset_num_timesteps=True)  # fill its buffer with the actor's transitions
    model.train(gradient_steps=20, batch_size=SAC_HP["batch_size"])  # warm-up

    def sb3_collect_round(n_vec_steps: int) -> float:
        t = time.perf_counter()
        model.learn(total_timesteps=n_vec_steps * b, reset_num_timesteps=False)
        return (time.perf_counter() - t) / n_vec_steps

    keys = ("ours_update", "ours_sample", "ours_sample_torchrl", "ours_collect", "sb3_update", "sb3_collect")
    rows: dict[str, list[float]] = {k: [] for k in keys}
    for r in range(a.rounds):
        rows["ours_update"].append(_time(lambda: learner.update(replay.sample()), 64))
        rows["sb3_update"].append(_time(lambda: model.train(gradient_steps=16, batch_size=SAC_HP["batch_size"]), 4) / 16)
        rows["ours_sample"].append(_time(replay.sample, 64))
        rows["ours_sample_torchrl"].append(_time(lambda: TensorDictReplayBuffer.sample(replay), 64))
        rows["ours_collect"].append(_time(collector.step, 32))
        rows["sb3_collect"].append(sb3_collect_round(8))
        print(f"round {r}: " + ", ".join(f"{k} {v[-1] * 1e3:.2f} ms" for k, v in rows.items()), flush=True)
    med = {k: statistics.median(v) for k, v in rows.items()}
    ours_cost = grad_steps * med["ours_update"] + med["ours_collect"]
    sb3_cost = grad_steps * med["sb3_update"] + med["sb3_collect"]
    out = {
        "measured_at": time.strftime("%Y-%m-%d %H:%M:%S %Z"),
        "machine": describe_machine(),
        "command": "python benchmarks/ttt_cost_breakdown.py " + " ".join(sys.argv[1:] if argv is None else argv),
        "env": a.env, "env_batch": b, "utd": utd, "gradient_steps_per_vector_step": grad_steps,
        "median_ms": {k: round(v * 1e3, 3) for k, v in med.items()},
        "rounds_ms": {k: [round(x * 1e3, 3) for x in v] for k, v in rows.items()},
        "per_vector_step_ms": {"ours_parts": round(ours_cost * 1e3, 2), "sb3_parts": round(sb3_cost * 1e3, 2)},
        "ratio_sample_torchrl_over_ours": round(med["ours_sample_torchrl"] / med["ours_sample"], 2),
        "ratio_update_sb3_over_ours": round(med["sb3_update"] / med["ours_update"], 2),
        "ratio_collect_sb3_over_ours": round(med["sb3_collect"] / med["ours_collect"], 2),
        "ratio_frames_per_s_from_parts": round(sb3_cost / ours_cost, 2),
        "bound_if_only_our_updates_cost": round(sb3_cost / (grad_steps * med["ours_update"]), 2),
    }
    print(json.dumps({k: out[k] for k in ("median_ms", "per_vector_step_ms", "ratio_sample_torchrl_over_ours",
                                          "ratio_update_sb3_over_ours",
                                          "ratio_collect_sb3_over_ours", "ratio_frames_per_s_from_parts",
                                          "bound_if_only_our_updates_cost")}, indent=1))
    dump_json(Path(a.out), out)


if __name__ == "__main__":
    main()
