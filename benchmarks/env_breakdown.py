"""Where one ``step_and_maybe_reset`` call of the compiled CPU env goes, and what is left without
the physics: the map for the 1 M env-steps/s target of issue #2.

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/env_breakdown.py [--batch 4096] [--calls 200]
                                                                    [--threads 1 2]   (make bench-env-breakdown)

For each thread count, ``UAVEnv(compile_step=True)`` runs the collector's loop (random actions,
``step_and_maybe_reset``, partial resets included) with a timer around each part:

- ``noise``: ``world.draw_noise``, the slot's random draws;
- ``core``: the compiled step (physics, reward, observation), C kernels included;
- ``step_rest``: the rest of ``UAVEnv._step`` (the state dict, the cos/sin of the headings, the
  output tensordict) and ``step_torchrl``: what ``EnvBase.step`` adds around ``_step``;
- ``step_mdp``: TorchRL's root-for-the-next-step;
- ``maybe_reset``: the partial reset, of which ``sampling`` is the scenario pool's refills and
  ``pool_rows`` the initial rows of a fresh pool; the rest is the copy of every entry of the root
  (a root must not share storage with the transition's ``"next"``) and the fresh rows put in.

Then the same loop with the compiled step replaced by a stored output of it (the same tensors
each call, so the same number of done rows; ``stub_core``): everything of the call but the
physics, against the 1 M target's budget of ``batch / 1e6`` s per call. And the machine's copy
rate for a buffer the size of the root (``copy_GBps``), which bounds the copies.

The timers are ``time.perf_counter`` around Python calls (a few microseconds each); parts are
means per call over the same ``--calls`` calls, so they add up to about the total. Absolute
figures drift with this machine's speed (see env_ab.py for side-by-side ratios); the shares are
what to read. Writes ``benchmarks/env_breakdown.json`` with the machine.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import torch

OUT = Path(__file__).with_name("env_breakdown.json")


def _timed(table: dict, key: str, fn):
    def wrapper(*a, **k):
        t = time.perf_counter()
        try:
            return fn(*a, **k)
        finally:
            table[key] = table.get(key, 0.0) + time.perf_counter() - t
    return wrapper


def _loop(env, td, actions, calls: int, done: list | None = None) -> tuple[float, object]:
    t = time.perf_counter()
    for i in range(calls):
        td["action"] = actions[i % actions.shape[0]]
        out, td = env.step_and_maybe_reset(td)
        if done is not None:
            done.append(out.get(("next", "done")))
    return time.perf_counter() - t, td


def breakdown(batch: int, calls: int, threads: int, seed: int = 0) -> dict:
    import uavlae.envs.uav_env as ue
    from uavlae.envs import UAVEnv

    torch.set_num_threads(threads)
    env = UAVEnv(batch_size=[batch], seed=seed, compile_step=True)
    td = env.reset()
    actions = torch.rand(64, batch, 2, generator=torch.Generator().manual_seed(seed)) * 2 - 1
    _, td = _loop(env, td, actions, 30)  # compile, allocator, first refills

    acc: dict[str, float] = {}
    saved = {"draw_noise": ue.draw_noise, "sample_scenarios": ue.sample_scenarios}
    ue.draw_noise = _timed(acc, "noise", ue.draw_noise)
    ue.sample_scenarios = _timed(acc, "sampling", ue.sample_scenarios)
    core = env._core
    env._core = _timed(acc, "core", core)
    for name, key in (("_step", "_step"), ("step", "step"), ("maybe_reset", "maybe_reset"),
                      ("_initial_rows", "pool_rows")):
        setattr(env, name, _timed(acc, key, getattr(env, name)))
    mdp = env._step_mdp
    cls_prop = type(env).__dict__.get("_step_mdp")
    type(env)._step_mdp = property(lambda self: _timed(acc, "step_mdp", mdp))
    done: list = []
    try:
        total, td = _loop(env, td, actions, calls, done)
    finally:
        ue.draw_noise, ue.sample_scenarios = saved["draw_noise"], saved["sample_scenarios"]
        if cls_prop is None:
            del type(env)._step_mdp
        else:
            type(env)._step_mdp = cls_prop
    ms = {k: 1e3 * v / calls for k, v in acc.items()}
    parts = {
        "noise": ms["noise"], "core": ms["core"], "step_rest": ms["_step"] - ms["noise"] - ms["core"],
        "step_torchrl": ms["step"] - ms["_step"], "step_mdp": ms["step_mdp"],
        "maybe_reset": ms["maybe_reset"], "sampling": ms.get("sampling", 0.0), "pool_rows": ms.get("pool_rows", 0.0),
    }
    parts["maybe_reset_copies_and_rest"] = parts["maybe_reset"] - parts["sampling"] - parts["pool_rows"]
    row = {"batch": batch, "threads": threads, "calls": calls, "ms_per_call": 1e3 * total / calls,
           "env_steps_per_s": batch * calls / total, "parts_ms": {k: round(v, 3) for k, v in parts.items()}}
    row["unaccounted_ms"] = round(row["ms_per_call"] - sum(parts[k] for k in ("noise", "core", "step_rest",
                                                                             "step_torchrl", "step_mdp", "maybe_reset")), 3)

    mean_done = float(torch.stack(done).float().sum()) / calls
    row["done_rows_per_call"] = round(mean_done, 2)

    # everything but the physics: one output of the compiled step (one with the mean number of
    # done rows, so the resets cost what they cost above), stored and handed back every call
    best = None
    for i in range(200):
        out = core(*env._core_inputs(td))
        gap = abs(int(out[5][0].sum()) - round(mean_done))
        if best is None or gap < best[0]:
            best = (gap, out)
        if gap == 0:
            break
        td["action"] = actions[i % actions.shape[0]]
        _, td = env.step_and_maybe_reset(td)
    stored = best[1]
    env._core = lambda *_: stored
    stub, td = _loop(env, td, actions, calls)
    row["stub_core"] = {"ms_per_call": 1e3 * stub / calls, "done_rows_per_call": int(stored[5][0].sum()),
                        "budget_ms_for_1M": 1e3 * batch / 1e6}
    nbytes = sum(v.numel() * v.element_size() for _, v in td.items(True, True))
    src, dst = torch.empty(nbytes, dtype=torch.uint8), torch.empty(nbytes, dtype=torch.uint8)
    for _ in range(3):
        dst.copy_(src)
    t, n = time.perf_counter(), 50
    for _ in range(n):
        dst.copy_(src)
    dt = (time.perf_counter() - t) / n
    row["root_bytes"] = nbytes
    row["copy_root_ms"] = 1e3 * dt
    row["copy_GBps"] = nbytes / dt / 1e9
    return row


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--batch", type=int, default=4096)
    p.add_argument("--calls", type=int, default=200)
    p.add_argument("--threads", type=int, nargs="+", default=[1, 2])
    p.add_argument("--out", default=str(OUT))
    a = p.parse_args(argv)
    from uavlae.factories import dump_json
    from uavlae.machine import describe_machine

    rows = []
    for n in a.threads:
        row = breakdown(a.batch, a.calls, n)
        rows.append(row)
        print(json.dumps(row), flush=True)
    out = {"measured_at": time.strftime("%Y-%m-%d %H:%M:%S %Z"), "machine": describe_machine(),
           "command": "python benchmarks/env_breakdown.py " + " ".join(sys.argv[1:] if argv is None else argv),
           "args": {k: v for k, v in vars(a).items() if k != "out"}, "rows": rows}
    dump_json(Path(a.out), out)
    print(f"wrote {a.out}")


if __name__ == "__main__":
    main()
