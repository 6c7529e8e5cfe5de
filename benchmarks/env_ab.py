"""UAVEnv's step, this checkout against an earlier commit, side by side in one process.

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/env_ab.py --base 072c0d7 [--batches 4096 64]
        [--bursts 10] [--compiled 1] [--threads 1]        (make bench-env-ab)

Each variant's ``UAVEnv`` is imported from its own source tree (the base commit checked out with
``git worktree`` into a temporary folder, ``sys.modules`` swapped between the imports); then
bursts of ``step_and_maybe_reset`` calls with the same actions alternate between the two, timed
by process CPU time (less sensitive to other load on the machine than wall time). Reports each
variant's median ms per call and the median of the per-burst ratios; writes
``benchmarks/env_ab.json`` with the machine.
"""

from __future__ import annotations

import argparse
import importlib
import json
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]


def _import_env_class(root: Path):
    for name in [m for m in sys.modules if m == "uavlae" or m.startswith("uavlae.")]:
        del sys.modules[name]
    sys.path.insert(0, str(root))
    try:
        return importlib.import_module("uavlae.envs.uav_env").UAVEnv
    finally:
        sys.path.remove(str(root))


def measure(roots: dict[str, Path], batch: int, compiled: bool, bursts: int, calls: int, clock=time.process_time) -> dict:
    envs = {name: _import_env_class(root)(batch_size=[batch], seed=0, compile_step=compiled) for name, root in roots.items()}
    acts = torch.rand(64, batch, 2, generator=torch.Generator().manual_seed(0)) * 2 - 1
    tds, warm = {}, {}
    for name, env in envs.items():
        td, t = env.reset(), time.perf_counter()
        for i in range(8):  # warm-up: allocator, first resets, the compile
            td["action"] = acts[i]
            _, td = env.step_and_maybe_reset(td)
        tds[name], warm[name] = td, round(time.perf_counter() - t, 1)
    ms = {name: [] for name in envs}
    k = 0
    for r in range(bursts):
        for name in (list(envs) if r % 2 == 0 else list(envs)[::-1]):
            env, td, t = envs[name], tds[name], clock()
            for i in range(calls):
                td["action"] = acts[(k + i) % 64]
                _, td = env.step_and_maybe_reset(td)
            ms[name].append(1e3 * (clock() - t) / calls)
            tds[name] = td
        k += calls
    base, new = ms["base"], ms["new"]
    ratios = [b / n for b, n in zip(base, new)]
    return {"batch": batch, "compiled": compiled, "calls_per_burst": calls, "warm_up_s": warm,
            "median_ms_per_call": {n: round(statistics.median(v), 3) for n, v in ms.items()},
            "speedup_new_over_base": round(statistics.median(ratios), 3),
            "speedup_range": [round(min(ratios), 3), round(max(ratios), 3)]}


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--base", required=True, help="the commit to compare against")
    p.add_argument("--batches", type=int, nargs="+", default=[4096, 64])
    p.add_argument("--compiled", type=int, default=1, choices=[0, 1])
    p.add_argument("--bursts", type=int, default=10)
    p.add_argument("--threads", type=int, default=1,
                   help="intra-op threads; above 1 the bursts are timed by wall clock (process CPU time "
                        "would add the threads up)")
    p.add_argument("--out", default=str(ROOT / "benchmarks" / "env_ab.json"))
    a = p.parse_args(argv)
    torch.set_num_threads(a.threads)
    clock = time.process_time if a.threads == 1 else time.perf_counter
    from uavlae.machine import describe_machine
    from uavlae.factories import dump_json

    rev = subprocess.run(["git", "-C", str(ROOT), "rev-parse", a.base], check=True, capture_output=True, text=True).stdout.strip()
    head = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "HEAD"], check=True, capture_output=True, text=True).stdout.strip()
    with tempfile.TemporaryDirectory(prefix="env_ab_") as tmp:
        base_root = Path(tmp) / "base"
        subprocess.run(["git", "-C", str(ROOT), "worktree", "add", "-q", "--detach", str(base_root), rev], check=True)
        try:
            rows = []
            for b in a.batches:
                calls = max(20, min(2000, 81920 // b))  # about 82k env-steps a burst, at most 2000 calls
                row = measure({"base": base_root, "new": ROOT}, b, bool(a.compiled), a.bursts, calls, clock)
                row["threads"], row["clock"] = a.threads, clock.__name__
                print(json.dumps(row), flush=True)
                rows.append(row)
        finally:
            subprocess.run(["git", "-C", str(ROOT), "worktree", "remove", "--force", str(base_root)], check=False)
    out = {"measured_at": time.strftime("%Y-%m-%d %H:%M:%S %Z"), "machine": describe_machine(),
           "command": "python benchmarks/env_ab.py " + " ".join(sys.argv[1:] if argv is None else argv),
           "base": rev, "new": head, "rows": rows}
    dump_json(Path(a.out), out)


if __name__ == "__main__":
    main()
