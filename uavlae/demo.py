"""A one-minute look at the world: a batched rollout of a simple greedy controller.

``python -m uavlae.demo [--batch 64] [--seed 0] [--out outputs] [--max-steps N] [--random]`` samples ``batch`` scenarios,
flies each once with :func:`greedy_policy` (nearest GE with data first, then the landing area;
a crude push away from buildings and no-fly zones; the RZ speed limit near residential zones),
prints the paper's five metrics (SPEC §5) and writes ``OUT/demo_scenario.png`` (one scenario
with its trajectory) and ``OUT/demo_records.csv`` (one row per episode).

This controller is a stand-in to show the world and the metrics; the paper's heuristic and the
learners live in ``uavlae.policies`` and ``uavlae.algos``.
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

import torch
from tensordict import TensorDictBase

from uavlae.envs.config import EnvConfig, make_env_config

AVOID_MARGIN = 10.0  # start pushing away this far beyond d_safe [m]


def greedy_policy(cfg: EnvConfig):
    """A batched tensor controller on the raw ``("state", ...)`` entries; writes ``"action"``."""
    m, s = cfg.motion, cfg.safety
    reach = s.d_safe + AVOID_MARGIN

    def away_from(p: torch.Tensor, rects: torch.Tensor, mask: torch.Tensor, goal_dir: torch.Tensor) -> torch.Tensor:
        # nearest point of each rectangle; push away from it and slide along it toward the goal
        q = torch.stack((p[:, None, 0].clamp(rects[..., 0], rects[..., 2]),
                         p[:, None, 1].clamp(rects[..., 1], rects[..., 3])), -1)
        off = p[:, None] - q
        d = torch.linalg.vector_norm(off, dim=-1, keepdim=True)
        n = off / d.clamp_min(1e-6)
        tangent = torch.stack((-n[..., 1], n[..., 0]), -1)
        side = torch.sign((tangent * goal_dir[:, None]).sum(-1, keepdim=True))
        tangent = tangent * torch.where(side == 0, torch.ones_like(side), side)
        w = ((reach - d) / (reach - s.d_min)).clamp(0.0, 2.0) * mask[..., None]
        return (w * (1.5 * n + tangent)).sum(1)

    def policy(td: TensorDictBase) -> TensorDictBase:
        st = td.get("state")
        p = st.get("position")
        rem, ge_pos = st.get("ge_remaining"), st.get("ge_pos")
        la = st.get("landing")
        la_c = (la[:, :2] + la[:, 2:]) / 2
        d_la = torch.linalg.vector_norm(la_c - p, dim=-1)
        # go home when the slots left barely cover the way back
        slots_left = (cfg.t_max - st.get("step")).float()
        late = slots_left < d_la / (m.v_max * m.t_fly) * 1.5 + 20
        wants = st.get("ge_mask") & (rem > 0)
        d_ge = torch.linalg.vector_norm(ge_pos - p[:, None], dim=-1).masked_fill(~wants, float("inf"))
        nearest = d_ge.argmin(-1)
        ge_target = ge_pos[torch.arange(p.shape[0]), nearest]
        to_ge = wants.any(-1) & ~late
        target = torch.where(to_ge[:, None], ge_target, la_c)
        delta = target - p
        dist = torch.linalg.vector_norm(delta, dim=-1, keepdim=True)
        goal_dir = delta / dist.clamp_min(1e-6)
        push = away_from(p, st.get("bz"), st.get("bz_mask"), goal_dir)
        push = push + away_from(p, st.get("nfz"), st.get("nfz_mask"), goal_dir)
        direction = goal_dir + push
        direction = direction / torch.linalg.vector_norm(direction, dim=-1, keepdim=True).clamp_min(1e-6)
        # speed: arrive without overshooting; the RZ limit when an RZ is within one slot's flight
        cap = torch.where(st.get("d_rz") <= m.v_max * m.t_fly + 1.0, 0.98 * m.v_limit, m.v_max)
        speed = torch.minimum(cap, dist.squeeze(-1) / m.t_fly)
        # inside LA with data left (sent home by time): land by slowing down
        in_la = (p[:, 0] >= la[:, 0]) & (p[:, 0] <= la[:, 2]) & (p[:, 1] >= la[:, 1]) & (p[:, 1] <= la[:, 3])
        speed = torch.where(in_la & ~to_ge, speed.clamp_max(m.v_land * 0.9), speed)
        v = direction * speed[:, None]
        td.set("action", (v / m.v_max).clamp(-1.0, 1.0))
        return td

    return policy


def main(argv: list[str] | None = None) -> dict[str, float]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--batch", type=int, default=64, help="scenarios flown at once")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, default=Path("outputs"))
    parser.add_argument("--max-steps", type=int, default=None, help="step budget (default: the env's t_max)")
    parser.add_argument("--random", action="store_true", help="uniform random actions instead of the greedy controller")
    args = parser.parse_args(argv)
    torch.set_num_threads(int(os.environ.get("UAVLAE_NUM_THREADS", "1")))

    from uavlae.envs.metrics import PAPER_METRICS, format_metrics, rollout_metrics, save_records
    from uavlae.envs.render import draw_scenario
    from uavlae.envs.uav_env import UAVEnv

    cfg = make_env_config()
    t0 = time.perf_counter()
    env = UAVEnv(cfg, batch_size=[args.batch], seed=args.seed)
    start = env.reset()
    t_reset = time.perf_counter() - t0
    policy = None if args.random else greedy_policy(cfg)
    gen = torch.Generator().manual_seed(args.seed)
    records, agg, trajs = rollout_metrics(
        env, policy, max_steps=args.max_steps, generator=gen, cfg=cfg, tensordict=start.clone()
    )
    t_total = time.perf_counter() - t0

    name = "random" if args.random else "greedy"
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
