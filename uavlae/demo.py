"""A one-minute look at the world: a batched rollout of the greedy heuristic (SPEC §8).

``python -m uavlae.demo [--batch 64] [--seed 0] [--out outputs] [--max-steps N] [--random]``
samples ``batch`` scenarios, flies each once with :class:`~uavlae.policies.greedy.GreedyPolicy`
(or uniform random actions), prints the paper's five metrics (SPEC §5) and writes
``OUT/demo_scenario.png`` (one scenario with its trajectory) and ``OUT/demo_records.csv``.
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

import torch

from uavlae.envs.config import make_env_config

def main(argv: list[str] | None = None) -> dict[str, float]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--batch", type=int, default=64, help="scenarios flown at once")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, default=Path("outputs"))
    parser.add_argument("--max-steps", type=int, default=None, help="step budget (default: the env's t_max)")
    parser.add_argument("--random", action="store_true", help="uniform random actions instead of the heuristic")
    args = parser.parse_args(argv)
    torch.set_num_threads(int(os.environ.get("UAVLAE_NUM_THREADS", "1")))

    from uavlae.envs.metrics import PAPER_METRICS, format_metrics, rollout_metrics, save_records
    from uavlae.envs.render import draw_scenario
    from uavlae.envs.uav_env import UAVEnv
    from uavlae.policies.greedy import GreedyPolicy

    cfg = make_env_config()
    t0 = time.perf_counter()
    env = UAVEnv(cfg, batch_size=[args.batch], seed=args.seed)
    start = env.reset()
    t_reset = time.perf_counter() - t0
    policy = None if args.random else GreedyPolicy(cfg)
    gen = torch.Generator().manual_seed(args.seed)
    records, agg, trajs = rollout_metrics(
        env, policy, max_steps=args.max_steps, generator=gen, cfg=cfg, tensordict=start.clone()
    )
    t_total = time.perf_counter() - t0

    name = "random" if args.random else "heuristic"
    print(f"uavlae demo: {args.batch} scenarios, {name} policy, seed {args.seed}")
    print(f"sampled in {t_reset:.1f} s; flown in {t_total - t_reset:.1f} s "
          f"({int(records['length'].sum())} slots, mean length {agg['mean_length']:.0f})")
    print(format_metrics(agg, PAPER_METRICS))
    print(f"mean return {agg['mean_return']:.2f}; boundary exits {agg['boundary_exit_rate']:.3f}")

    args.out.mkdir(parents=True, exist_ok=True)
    row = 0
    png = args.out / "demo_scenario.png"
    outcome = "landed" if bool(records["landed"][row]) else "collided" if bool(records["collided"][row]) else "not landed"
    draw_scenario(start, trajs[row], path=png, cfg=cfg, index=row,
                  title=f"scenario 0, {name} policy: {outcome}, "
                        f"{float(records['data_collected'][row]):.1f}/{float(records['data_total'][row]):.1f} data")
    save_records(records, args.out / "demo_records.csv")
    print(f"wrote {png} and {args.out / 'demo_records.csv'}")
    return agg


if __name__ == "__main__":
    main()
