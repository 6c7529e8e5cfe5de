"""SAC gradient steps per second on CPU, one thread: our learner vs a plain-PyTorch reference.

Measures, side by side in one run (docs/style.md rule 10), on the same replay-shaped batch:

- ``uavlae_fused``: :func:`uavlae.algos.sac.make_sac` as shipped (``loss_impl: fused``: SACLoss's
  gradients written out by hand, ``uavlae.algos.sac_fused``; ``Adam(fused=True).step()``; the
  target lerp), ``update(batch)`` including the log ``.item()``s;
- ``torchrl_eager``: ``loss_impl: torchrl`` (torchrl ``SACLoss`` forward, twin Q under vmap,
  autograd, one fused Adam with three parameter groups), the reference implementation;
- ``torchrl_compiled``: the same with ``compile: true`` (``torch.compile`` of the loss, inductor
  CPU vectors of ``compile_simdlen: 128`` bits, see ``uavlae.algos.sac.compile_loss``);
- ``plain_torch_reference``: the same maths hand-written on bare ``nn.Module``s and tensors
  (two Q nets, targets, tanh-Gaussian actor, learned alpha), the floor of the eager Python
  overhead.

Compile times (first three calls) are recorded, and the error if a compilation fails.

Variants alternate within each of ``--repeats`` short rounds; the median and best round of each
and the per-round (paired) ratio to the reference are reported, so a noisy shared machine hurts
them alike; the load average before and after is recorded with the machine.

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/sac_update_speed.py   # (make bench-sac) -> sac_update_speed.json
"""

from __future__ import annotations

import argparse
import copy
import json
import math
import os
import statistics
import sys
import time
import traceback
import warnings
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")

import torch  # noqa: E402
import torch.nn.functional as F  # noqa: E402
from tensordict import TensorDict  # noqa: E402
from torch import nn  # noqa: E402
from torchrl.data import Bounded  # noqa: E402

from uavlae.algos.sac import make_sac  # noqa: E402
from uavlae.machine import describe_machine  # noqa: E402
from uavlae.factories import dump_json  # noqa: E402




def replay_batch(n: int, obs_dim: int, act_dim: int) -> TensorDict:
    g = torch.Generator().manual_seed(0)
    done = torch.rand(n, 1, generator=g) < 0.01
    return TensorDict(
        {
            "observation": torch.randn(n, obs_dim, generator=g),
            "action": torch.rand(n, act_dim, generator=g) * 2 - 1,
            "next": {
                "observation": torch.randn(n, obs_dim, generator=g),
                "reward": torch.randn(n, 1, generator=g),
                "done": done,
                "terminated": done.clone(),
            },
        },
        [n],
    )


class ReferenceSAC:
    """SAC's update on bare modules: the same sizes, passes and optimisers as the learner."""

    def __init__(self, obs_dim: int, act_dim: int, hidden: tuple[int, ...], cfg):
        def mlp(i, o):
            layers, d = [], i
            for h in hidden:
                layers += [nn.Linear(d, h), nn.ReLU()]
                d = h
            return nn.Sequential(*layers, nn.Linear(d, o))

        self.actor = mlp(obs_dim, 2 * act_dim)
        self.qs = nn.ModuleList([mlp(obs_dim + act_dim, 1) for _ in range(2)])
        self.targets = copy.deepcopy(self.qs).requires_grad_(False)
        self.log_alpha = nn.Parameter(torch.zeros(()))
        self.gamma, self.tau, self.target_entropy = cfg.gamma, cfg.tau, -float(act_dim)
        self.opt_actor = torch.optim.Adam(self.actor.parameters(), lr=cfg.actor_lr, fused=True)
        self.opt_q = torch.optim.Adam(self.qs.parameters(), lr=cfg.critic_lr, fused=True)
        self.opt_alpha = torch.optim.Adam([self.log_alpha], lr=cfg.alpha_lr, fused=True)

    def _sample(self, obs):
        loc, raw = self.actor(obs).chunk(2, -1)
        scale = F.softplus(raw + 0.5413) + 1e-4  # NormalParamExtractor's biased softplus
        u = loc + scale * torch.randn_like(loc)
        a = torch.tanh(u)
        logp = torch.distributions.Normal(loc, scale).log_prob(u).sum(-1)
        logp = logp - (2 * (math.log(2) - u - F.softplus(-2 * u))).sum(-1)
        return a, logp

    @staticmethod
    def _q(nets, obs, act):
        x = torch.cat([obs, act], -1)
        return torch.stack([q(x).squeeze(-1) for q in nets])

    def update(self, b: TensorDict) -> dict[str, float]:
        obs, act = b["observation"], b["action"]
        nobs, rew = b["next", "observation"], b["next", "reward"].squeeze(-1)
        notdone = (~b["next", "terminated"]).squeeze(-1).float()
        alpha = self.log_alpha.detach().exp()
        with torch.no_grad():
            na, nlogp = self._sample(nobs)
            target = rew + self.gamma * notdone * (self._q(self.targets, nobs, na).min(0).values - alpha * nlogp)
        q_loss = (self._q(self.qs, obs, act) - target).pow(2).sum(0).mean()
        a, logp = self._sample(obs)
        self.qs.requires_grad_(False)
        actor_loss = (alpha * logp - self._q(self.qs, obs, a).min(0).values).mean()
        self.qs.requires_grad_(True)
        alpha_loss = -(self.log_alpha * (logp.detach() + self.target_entropy)).mean()
        for o in (self.opt_actor, self.opt_q, self.opt_alpha):
            o.zero_grad(set_to_none=True)
        (q_loss + actor_loss + alpha_loss).backward()
        for o in (self.opt_actor, self.opt_q, self.opt_alpha):
            o.step()
        with torch.no_grad():
            for t, s in zip(self.targets.parameters(), self.qs.parameters()):
                t.lerp_(s, self.tau)
        return {"loss_qvalue": q_loss.item(), "loss_actor": actor_loss.item(), "loss_alpha": alpha_loss.item()}


def timed(update, batch, steps: int) -> float:
    t0 = time.perf_counter()
    for _ in range(steps):
        update(batch)
    return steps / (time.perf_counter() - t0)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--obs-dim", type=int, default=None, help="default: UAVEnv's observation size")
    p.add_argument("--batch", type=int, default=256)
    p.add_argument("--steps", type=int, default=50, help="timed updates per variant per round")
    p.add_argument("--warmup", type=int, default=20)
    p.add_argument("--repeats", type=int, default=12, help="rounds; variants alternate within each")
    p.add_argument("--no-compile", action="store_true")
    p.add_argument("--out", type=Path, default=Path(__file__).with_suffix(".json"))
    args = p.parse_args()

    torch.set_num_threads(1)
    torch.manual_seed(0)
    warnings.filterwarnings("ignore")
    if args.obs_dim is None:
        from uavlae.envs import UAVEnv

        args.obs_dim = int(UAVEnv(batch_size=[1], seed=0).observation_spec["observation"].shape[-1])
    act_dim = 2
    spec = Bounded(-1.0, 1.0, shape=(act_dim,))
    batch = replay_batch(args.batch, args.obs_dim, act_dim)
    load_before = os.getloadavg()

    eager = make_sac({}, args.obs_dim, spec)
    variants: dict[str, callable] = {"uavlae_fused": eager.update}
    variants["torchrl_eager"] = make_sac({"loss_impl": "torchrl"}, args.obs_dim, spec).update
    ref = ReferenceSAC(args.obs_dim, act_dim, eager.cfg.hidden, eager.cfg)
    variants["plain_torch_reference"] = ref.update
    compiled_info: dict = {"attempted": not args.no_compile}
    builders = {
        "torchrl_compiled": lambda: make_sac({"loss_impl": "torchrl", "compile": True}, args.obs_dim, spec).update,
    }
    wanted = [] if args.no_compile else list(builders)
    for name in wanted:
        build = builders[name]
        try:
            fn = build()
            t0 = time.perf_counter()
            for _ in range(3):  # first calls compile (and may recompile once)
                fn(batch)
            compiled_info[f"{name}_compile_s"] = round(time.perf_counter() - t0, 1)
            variants[name] = fn
        except Exception as e:  # noqa: BLE001 -- record why, keep measuring the rest
            compiled_info[f"{name}_error"] = f"{type(e).__name__}: {e}"[:2000]
            compiled_info[f"{name}_traceback_tail"] = traceback.format_exc()[-2000:]

    for fn in variants.values():
        timed(fn, batch, args.warmup)
    rounds: dict[str, list[float]] = {k: [] for k in variants}
    for _ in range(args.repeats):
        for k, fn in variants.items():
            rounds[k].append(timed(fn, batch, args.steps))
    median = {k: statistics.median(v) for k, v in rounds.items()}
    # Paired per round: the variants of one round ran within seconds of each other, so their
    # ratio survives the load changes of a shared machine better than a ratio of medians.
    ref_rounds = rounds["plain_torch_reference"]
    paired = {k: statistics.median(x / r for x, r in zip(v, ref_rounds)) for k, v in rounds.items()}
    result = {
        "benchmark": "SAC gradient steps per second (one update = actor + twin Q + alpha + soft target)",
        "command": "OMP_NUM_THREADS=1 .venv/bin/python benchmarks/sac_update_speed.py " + " ".join(sys.argv[1:]),
        "config": {
            "batch": args.batch,
            "obs_dim": args.obs_dim,
            "act_dim": act_dim,
            "hidden": list(eager.cfg.hidden),
            "device": "cpu",
            "torch_num_threads": 1,
            "steps_per_round": args.steps,
            "rounds": args.repeats,
        },
        "updates_per_s_median": {k: round(v, 1) for k, v in median.items()},
        "updates_per_s_best_round": {k: round(max(v), 1) for k, v in rounds.items()},
        "updates_per_s_rounds": {k: [round(x, 1) for x in v] for k, v in rounds.items()},
        "ratio_to_reference_paired_median": {k: round(v, 3) for k, v in paired.items()},
        "compile": compiled_info,
        "machine": describe_machine(),
        "load_average_1_5_15": {"before": [round(x, 2) for x in load_before], "after": [round(x, 2) for x in os.getloadavg()]},
        "measured_at": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
    }
    dump_json(Path(args.out), result)
    keys = ("updates_per_s_median", "updates_per_s_best_round", "ratio_to_reference_paired_median", "compile")
    print(json.dumps({k: result[k] for k in keys}, indent=2))
    print(f"written to {args.out}")


if __name__ == "__main__":
    main()
