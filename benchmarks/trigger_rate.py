"""How often SAC+LLM's trigger fires, and how many LLM calls that asks for, by who flies.

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/trigger_rate.py      (make bench-trigger)

The training env of ``make run`` (``uavlae/conf/env/default.yaml``, B = 16 scenarios stepped together,
episodes reset as they end) is flown for ``--frames`` frames by each of: the greedy heuristic
(``uavlae/conf/advisor/heuristic.yaml``; it lands with every GE served on the evaluation set), the
untrained SAC actor (``uavlae/conf/algo/sac.yaml``, sampled, as in the first frames of a run) and a
uniform-random policy (the warm-up). On every state the override's trigger
(``uavlae/conf/advisor/llm.yaml``: any BZ, NFZ, RZ or OU within ``d_th``) is evaluated without asking
anyone: the flying policy is never overridden, so no LLM call is made. From the trigger's slots
the benchmark counts the calls SAC+LLM would make per 1000 frames with ``advisor.hold_steps``
1 (the paper: every triggered slot) and 4 (a row asks at the first slot of each run of
triggered slots within an episode, then every 4th), and which obstacle kind was within
``d_th`` (the env's raw distances; a slot can have several; the trigger itself counts an OU only
within the perception radius). Writes ``trigger_rate.json``.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import torch
from omegaconf import OmegaConf

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

KINDS = ("d_bz", "d_nfz", "d_rz", "d_ou")


def calls_with_hold(trig: torch.Tensor, step: torch.Tensor, hold: int) -> int:
    """Calls of ``advisor.hold_steps=hold`` over the ``[T, B]`` trigger and slot-index tensors:
    a row asks when triggered and not inside a held answer (the slot after the last one, in the
    same episode, with uses left), as :class:`uavlae.policies.override.OverridePolicy` does
    when every answer is valid."""
    T, B = trig.shape
    left = torch.zeros(B, dtype=torch.int64)
    last = torch.full((B,), -2, dtype=torch.int64)
    calls = 0
    for t in range(T):
        held = trig[t] & (left > 0) & (step[t] == last + 1)
        ask = trig[t] & ~held
        calls += int(ask.sum())
        left = torch.where(held, left - 1, torch.zeros_like(left))
        left[ask] = hold - 1
        last = step[t].clone()
    return calls


def fly(name: str, policy, env, trigger, d_th: float, steps: int, seed: int) -> dict:
    """``trigger``: an OverridePolicy whose ``trigger(td)`` is asked, never its advisor."""
    from torchrl.envs.utils import ExplorationType, set_exploration_type, step_mdp

    env.set_seed(seed)
    td = env.reset()
    trig, step, near = [], [], {k: 0 for k in KINDS}
    episodes = 0
    t0 = time.perf_counter()
    with torch.no_grad(), set_exploration_type(ExplorationType.RANDOM):
        for _ in range(steps):
            d = torch.stack([td.get(("state", k)).reshape(-1) for k in KINDS], dim=-1)
            close = d <= d_th
            for i, k in enumerate(KINDS):
                near[k] += int(close[:, i].sum())
            trig.append(trigger.trigger(td).clone())
            step.append(td.get(("state", "step")).reshape(-1).clone())
            td = env.step(policy(td))
            episodes += int(td.get(("next", "done")).sum())
            td = env.maybe_reset(step_mdp(td, keep_other=False, exclude_action=True))
    trig_t, step_t = torch.stack(trig), torch.stack(step)
    frames = trig_t.numel()
    out = {
        "frames": frames,
        "episodes_ended": episodes,
        "trigger_rate": round(trig_t.float().mean().item(), 4),
        "calls_per_1000_frames": {f"hold_steps={k}": round(1000 * calls_with_hold(trig_t, step_t, k) / frames, 1)
                                  for k in (1, 4)},
        "within_d_th_rate": {k[2:]: round(near[k] / frames, 4) for k in KINDS},
        "seconds": round(time.perf_counter() - t0, 1),
    }
    print(name, out, flush=True)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--frames", type=int, default=16384)
    ap.add_argument("--batch", type=int, default=16, help="scenarios stepped together (make run: 16)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default=str(ROOT / "benchmarks" / "trigger_rate.json"))
    args = ap.parse_args()
    torch.set_num_threads(1)
    os.environ.setdefault("WANDB_MODE", "disabled")

    from uavlae.collect import _UniformRandom
    from uavlae.envs import make_env_config
    from uavlae.factories import CONF_DIR, git_info, make_env, make_learner
    from uavlae.files import dump_json
    from uavlae.machine import describe_machine
    from uavlae.policies.heuristic import HeuristicPolicy
    from uavlae.policies.override import HeuristicAdvisor, OverridePolicy

    conf = CONF_DIR
    env_cfg = make_env_config(OmegaConf.load(conf / "env" / "default.yaml"))
    d_th = float(OmegaConf.load(conf / "advisor" / "llm.yaml").d_th)
    env = make_env(env_cfg, args.batch, seed=args.seed)
    steps = args.frames // args.batch
    torch.manual_seed(args.seed)
    learner = make_learner(OmegaConf.load(conf / "algo" / "sac.yaml"), env)
    generator = torch.Generator()
    generator.manual_seed(args.seed)
    heuristic = HeuristicPolicy(env_cfg, OmegaConf.to_container(OmegaConf.load(conf / "advisor" / "heuristic.yaml")))
    policies = {
        "heuristic": heuristic,
        "untrained_sac_actor": learner.behaviour,
        "uniform_random": _UniformRandom(env.action_spec, generator),
    }
    # the override's own trigger (uavlae/conf/advisor/llm.yaml, the env's perception radius for OUs)
    trigger = OverridePolicy(heuristic, HeuristicAdvisor(heuristic), mode="proximity", d_th=d_th,
                             perception_radius=env_cfg.safety.perception_radius)
    results = {name: fly(name, p, env, trigger, d_th, steps, args.seed) for name, p in policies.items()}
    h, u = results["heuristic"], results["untrained_sac_actor"]
    out = {
        "measured_at": time.strftime("%Y-%m-%d %H:%M:%S %Z"),
        "machine": describe_machine(),
        "git": git_info(),
        "command": "python benchmarks/trigger_rate.py " + " ".join(sys.argv[1:]),
        "env_batch": args.batch,
        "d_th_m": d_th,
        "results": results,
        "heuristic_over_untrained_trigger_rate": round(h["trigger_rate"] / max(u["trigger_rate"], 1e-12), 2),
    }
    dump_json(Path(args.out), out)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
