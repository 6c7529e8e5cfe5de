"""What the safety filter costs: env-steps/s of the collector's loop with and without it, side by side.

    python benchmarks/safety_filter.py [--batches 64] [--seconds 4] [--rounds 3] [--compile]

The loop is the one a collector runs: random actions written into the root, (the filter on the
root's raw state,) ``step_and_maybe_reset``. The two variants alternate round by round in one
process on the same env, so the machine's drift hits both alike; the ratio is the mean rate
without the filter over the mean with it. ``--compile`` steps the env through ``torch.compile``
(the quick profile's and the pilot study's setting); the filter itself runs eagerly. Writes
``benchmarks/safety_filter.json``.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import torch

from uavlae.envs import UAVEnv
from uavlae.factories import dump_json
from uavlae.machine import describe_machine
from uavlae.policies.safety import SafetyFilter, apply_filter


def rate(env: UAVEnv, td, actions: torch.Tensor, safety: SafetyFilter | None, seconds: float):
    """Env-steps/s (batch rows a second) of the loop over ``seconds``; returns it and the root."""
    steps, t0 = 0, time.perf_counter()
    while time.perf_counter() - t0 < seconds:
        td["action"] = actions[steps % actions.shape[0]]
        if safety is not None:
            apply_filter(safety, td)
        _, td = env.step_and_maybe_reset(td)
        steps += 1
    return steps * env.batch_size[0] / (time.perf_counter() - t0), td


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--batches", type=int, nargs="+", default=[64])
    p.add_argument("--seconds", type=float, default=4.0)
    p.add_argument("--rounds", type=int, default=3)
    p.add_argument("--compile", action="store_true")
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--out", default=str(Path(__file__).with_suffix(".json")))
    a = p.parse_args()
    torch.set_num_threads(a.threads)
    rows = []
    for b in a.batches:
        env = UAVEnv(batch_size=[b], seed=0, compile_step=a.compile)
        safety = SafetyFilter(env.cfg, {"mode": "deploy"})
        actions = torch.rand(64, b, 2, generator=torch.Generator().manual_seed(0)) * 2 - 1
        td = env.reset()
        _, td = rate(env, td, actions, safety, 1.0)  # warm-up (the compile, the allocator) of both paths
        _, td = rate(env, td, actions, None, 1.0)
        plain, filtered = [], []
        for _ in range(a.rounds):
            r, td = rate(env, td, actions, None, a.seconds)
            plain.append(r)
            r, td = rate(env, td, actions, safety, a.seconds)
            filtered.append(r)
        row = {"batch": b, "compile_env": a.compile, "steps_per_s_without": sum(plain) / len(plain),
               "steps_per_s_with": sum(filtered) / len(filtered), "rounds": a.rounds, "seconds": a.seconds}
        row["ratio_without_over_with"] = row["steps_per_s_without"] / row["steps_per_s_with"]
        rows.append(row)
        print(f"B={b}: {row['steps_per_s_without']:.0f} env-steps/s without the filter, "
              f"{row['steps_per_s_with']:.0f} with it: {row['ratio_without_over_with']:.2f}x")
    dump_json(Path(a.out), {"machine": describe_machine(threads=a.threads), "rows": rows})


if __name__ == "__main__":
    main()
