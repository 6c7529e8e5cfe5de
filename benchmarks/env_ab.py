"""Env-steps/s of ``UAVEnv.step_and_maybe_reset``, this checkout against another one, side by side.

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/env_ab.py --base ../other-checkout \
        [--batches 4096 64] [--compile] [--rounds 3] [--seconds 3]       (make bench-env-ab)

``--base`` is another checkout of the project with its own ``.venv``. Each measurement is a
fresh subprocess running this file's worker with that checkout's interpreter, in that checkout,
so each side imports only its own code; the loop it times is ``env_throughput.bench_torchrl`` of
this checkout (random actions, partial resets included, one thread). The two sides alternate, in
opposite order from round to round. Writes ``benchmarks/env_ab.json`` with the machine.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def worker(batch: int, compiled: bool, seconds: float) -> None:
    import torch

    torch.set_num_threads(1)
    sys.path.insert(0, str(ROOT / "benchmarks"))
    from env_throughput import bench_torchrl

    print(json.dumps(bench_torchrl(batch, seconds, "cpu", compile_step=compiled)))


def _measure(checkout: Path, batch: int, compiled: bool, seconds: float) -> dict:
    cmd = [str(checkout / ".venv" / "bin" / "python"), str(Path(__file__).resolve()), "--worker",
           "--batches", str(batch), "--seconds", str(seconds)] + (["--compile"] if compiled else [])
    env = {**os.environ, "OMP_NUM_THREADS": "1", "UAVLAE_NUM_THREADS": "1"}
    out = subprocess.run(cmd, cwd=checkout, env=env, capture_output=True, text=True, check=False)
    if out.returncode != 0:
        raise RuntimeError(f"the worker failed in {checkout}:\n{out.stderr[-3000:]}")
    return json.loads(out.stdout.strip().splitlines()[-1])


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--base", type=Path, help="the other checkout (with its own .venv)")
    p.add_argument("--batches", type=int, nargs="+", default=[4096, 64])
    p.add_argument("--compile", action="store_true", help="UAVEnv(compile_step=True) on both sides")
    p.add_argument("--rounds", type=int, default=3)
    p.add_argument("--seconds", type=float, default=3.0, help="timed seconds per measurement")
    p.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "env_ab.json")
    p.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    a = p.parse_args(argv)
    if a.worker:
        worker(a.batches[0], a.compile, a.seconds)
        return
    if a.base is None or not (a.base / ".venv" / "bin" / "python").exists():
        p.error("--base must be a checkout of the project with its own .venv")
    from uavlae.factories import dump_json
    from uavlae.files import portable
    from uavlae.machine import describe_machine

    base, ours = a.base.resolve(), ROOT
    rows = []
    for b in a.batches:
        sps: dict[str, list[float]] = {"ours": [], "base": []}
        for r in range(a.rounds):
            order = [("ours", ours), ("base", base)] if r % 2 == 0 else [("base", base), ("ours", ours)]
            for name, checkout in order:
                sps[name].append(_measure(checkout, b, a.compile, a.seconds)["env_steps_per_s"])
        ratios = [o / s for o, s in zip(sps["ours"], sps["base"])]
        rows.append({"batch": b, "compiled": a.compile, "env_steps_per_s_ours": sps["ours"],
                     "env_steps_per_s_base": sps["base"], "ratios": ratios, "median_ratio": statistics.median(ratios)})
        print(f"B = {b:5d} compiled = {a.compile}: ours {statistics.median(sps['ours']):9.0f} "
              f"base {statistics.median(sps['base']):9.0f} env-steps/s, ours / base x{statistics.median(ratios):.3f}",
              flush=True)
    dump_json(a.out, {
        "what": "env-steps/s of step_and_maybe_reset with random actions, one thread, ours vs --base",
        "command": portable("python benchmarks/env_ab.py " + " ".join(sys.argv[1:] if argv is None else argv), ROOT),
        "base": portable(str(base), ROOT),
        "rows": rows,
        "machine": describe_machine(),
    })


if __name__ == "__main__":
    main()
