"""Env-steps per second: UAVEnv through the TorchRL API vs the gymnasium adapter, side by side.

    python benchmarks/env_throughput.py [--batches 1 64 1024 4096] [--seconds 3] [--device cpu] [--compile]
                                        [--threads 1] [--extra-threads 2]

Both paths run the same world (``world_step``). The TorchRL path is the loop a collector runs:
``step_and_maybe_reset`` with a policy's actions written into the tensordict, so partial resets
(fresh scenarios for finished rows) are included. The reference steps one scenario at a time
through ``UAVGymEnv`` with numpy actions. ``--compile`` adds, for each batch size, a row with
``UAVEnv(compile_step=True)`` (the step through ``torch.compile``) measured right after the eager
one in the same run; its one-off compile time (first step) is reported separately as
``compile_seconds``. ``--extra-threads 2`` (the default) then measures the largest batch again
with 2 intra-op threads (rows with ``"threads": 2``; every other row runs with ``--threads``,
default 1). After each row the gymnasium loop runs again (``--gym-seconds``): a row's
``ratio_vs_gym`` is against the mean of the gymnasium runs just before and after it, because this
machine's speed drifts by up to 2x within minutes. Writes ``benchmarks/env_throughput.json``.
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

import torch

from uavlae.factories import dump_json
from uavlae.machine import describe_machine



def _sync(device: str) -> None:
    if device.startswith("cuda"):
        torch.cuda.synchronize()


def bench_torchrl(batch: int, seconds: float, device: str, seed: int = 0, compile_step: bool = False) -> dict:
    from uavlae.envs import UAVEnv

    env = UAVEnv(batch_size=[batch], device=device, seed=seed, compile_step=compile_step)
    gen = torch.Generator(device=device).manual_seed(seed)
    td = env.reset()
    # the policy: uniform random actions drawn outside the timed region's env code
    n_pre = 64
    actions = torch.rand(n_pre, batch, 2, generator=gen, device=device) * 2 - 1
    compile_s = None
    for i in range(5):  # warm-up (allocator, first resets; the compile happens in the first step)
        t_first = time.perf_counter()
        td["action"] = actions[i % n_pre]
        _, td = env.step_and_maybe_reset(td)
        if i == 0 and compile_step:
            _sync(device)
            compile_s = time.perf_counter() - t_first
    _sync(device)
    steps, t0 = 0, time.perf_counter()
    while True:
        td["action"] = actions[steps % n_pre]
        _, td = env.step_and_maybe_reset(td)
        steps += 1
        if steps % 10 == 0:
            _sync(device)
            if time.perf_counter() - t0 >= seconds:
                break
    _sync(device)
    dt = time.perf_counter() - t0
    row = {"batch": batch, "compiled": compile_step, "calls": steps, "seconds": dt,
           "env_steps_per_s": steps * batch / dt, "ms_per_call": 1e3 * dt / steps}
    if compile_step:
        row["compile_seconds"] = compile_s
    return row


def bench_gym(seconds: float, seed: int = 0) -> dict:
    import numpy as np

    from uavlae.envs.gym_adapter import UAVGymEnv

    env = UAVGymEnv()
    rng = np.random.default_rng(seed)
    env.reset(seed=seed)
    actions = rng.uniform(-1, 1, size=(1024, 2)).astype(np.float32)
    steps, episodes, t0 = 0, 0, time.perf_counter()
    while time.perf_counter() - t0 < seconds:
        for _ in range(50):
            _, _, term, trunc, _ = env.step(actions[steps % 1024])
            steps += 1
            if term or trunc:
                env.reset()
                episodes += 1
    dt = time.perf_counter() - t0
    return {"batch": 1, "calls": steps, "seconds": dt, "env_steps_per_s": steps / dt,
            "episodes": episodes}


def _row(b: int, compiled: bool, threads: int, args: argparse.Namespace, gym: list[dict]) -> dict:
    """One TorchRL row, then the gymnasium loop again (on ``args.threads``, like the first one):
    the row's ratio is against the mean of the gymnasium runs just before and just after it
    (``gym`` holds them in order), so a drift of the machine's speed between rows does not
    enter the ratio."""
    r = bench_torchrl(b, args.seconds, args.device, compile_step=compiled)
    r["threads"] = threads
    n = torch.get_num_threads()
    torch.set_num_threads(args.threads)
    gym.append(bench_gym(args.gym_seconds))
    torch.set_num_threads(n)
    before, after = gym[-2]["env_steps_per_s"], gym[-1]["env_steps_per_s"]
    r["gym_adjacent_env_steps_per_s"] = [before, after]
    r["ratio_vs_gym"] = r["env_steps_per_s"] / ((before + after) / 2)
    tag = "compiled" if compiled else "eager"
    extra = f"  (one-off compile {r['compile_seconds']:.1f} s)" if compiled else ""
    print(f"UAVEnv B={b:>5} ({args.device}, {tag:>8}, {threads} thread{'s' if threads > 1 else ''}): "
          f"{r['env_steps_per_s']:>12,.0f} env-steps/s  {r['ms_per_call']:7.2f} ms/call  "
          f"x{r['ratio_vs_gym']:.1f} vs gym{extra}", flush=True)
    return r


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--batches", type=int, nargs="+", default=[1, 64, 1024, 4096])
    ap.add_argument("--seconds", type=float, default=3.0)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--threads", type=int, default=int(os.environ.get("UAVLAE_NUM_THREADS", "1")))
    ap.add_argument("--compile", action="store_true",
                    help="also measure UAVEnv(compile_step=True) next to each eager row")
    ap.add_argument("--extra-threads", type=int, nargs="*", default=[2], metavar="N",
                    help="after the main table, measure the largest batch again with N intra-op "
                         "threads (eager, and compiled with --compile); rows labelled threads=N "
                         "(default: 2, the target machine's core count; none: no extra rows)")
    ap.add_argument("--gym-seconds", type=float, default=1.5,
                    help="length of the gymnasium run after each row (its ratio's reference)")
    ap.add_argument("--out", default=str(Path(__file__).with_name("env_throughput.json")))
    args = ap.parse_args()
    torch.set_num_threads(args.threads)

    gym = [bench_gym(args.seconds)]
    print(f"gymnasium adapter, one scenario at a time: {gym[0]['env_steps_per_s']:,.0f} env-steps/s")
    rows = []
    for b in args.batches:
        for compiled in (False, True) if args.compile else (False,):
            rows.append(_row(b, compiled, args.threads, args, gym))
    # the same loop with more intra-op threads (the gym reference stays single-threaded)
    for n in args.extra_threads or []:
        if n == args.threads:
            continue
        torch.set_num_threads(n)
        for compiled in (False, True) if args.compile else (False,):
            rows.append(_row(max(args.batches), compiled, n, args, gym))
        torch.set_num_threads(args.threads)
    result = {"machine": describe_machine(), "device": args.device, "threads": args.threads,
              "seconds_per_measurement": args.seconds, "gym": gym[0], "gym_runs": gym, "torchrl": rows,
              "measured_at": time.strftime("%Y-%m-%d %H:%M:%S %Z")}
    dump_json(Path(args.out), result)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
