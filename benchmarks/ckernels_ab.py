"""The CPU env's C kernels outside the compiled graph, on and off, side by side in one process.

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/ckernels_ab.py [--bursts 10]     (make bench-ckernels)

Each measurement alternates bursts with the kernel on and off (process CPU time, one
thread), reporting each side's median and the median of the per-burst ratios:

- ``uniform``: one slot's random draws at B = 4096 (262,144 float32 numbers), ``ckernels.uniform``
  (the C replay of torch's mt19937) against ``torch.rand``; checked equal first.
- ``draw_noise``: one slot's random draws at B = 4096 as the step takes them (the OU turns,
  speeds, headings and retries, the GE ties), drawn and transformed in one C pass
  (``ckernels.uniform_runs``) against ``torch.rand`` and torch's ops; checked equal first.
- ``sample_scenarios``: 256 scenarios (one pool refill of a partial reset) and 4096 (a full reset
  at B = 4096), every kernel of the sampler on (the occupancy grid, ``ckernels.free_grid``; the
  flood fill, ``ckernels.flood``; the candidate scans, ``ckernels.first_clear``; the draws,
  ``ckernels.uniform``) against none (the torch code); checked equal first, scenarios and
  generator state.

Writes ``benchmarks/ckernels_ab.json`` with the machine.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]


def _ab(run, switch, bursts: int, calls: int) -> dict:
    ms = {"c": [], "torch": []}
    for r in range(bursts):
        for side in (("c", "torch") if r % 2 == 0 else ("torch", "c")):
            switch(side == "c")
            t = time.process_time()
            for _ in range(calls):
                run()
            ms[side].append(1e3 * (time.process_time() - t) / calls)
    switch(True)
    ratios = [t / c for t, c in zip(ms["torch"], ms["c"])]
    return {"calls_per_burst": calls, "median_ms": {k: round(statistics.median(v), 3) for k, v in ms.items()},
            "speedup_c_over_torch": round(statistics.median(ratios), 3),
            "speedup_range": [round(min(ratios), 3), round(max(ratios), 3)]}


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--bursts", type=int, default=10)
    p.add_argument("--out", default=str(ROOT / "benchmarks" / "ckernels_ab.json"))
    a = p.parse_args(argv)
    torch.set_num_threads(1)
    from uavlae.envs import ckernels
    from uavlae.envs.config import EnvConfig
    from uavlae.envs.scenario import sample_scenarios
    from uavlae.machine import describe_machine
    from uavlae.factories import dump_json

    if not ckernels.load():
        raise SystemExit("the C kernels could not be built (see the warning): nothing to compare")
    state, lib, rows = ckernels._STATE, ckernels._STATE["lib"], {}

    n, g = 262_144, torch.Generator().manual_seed(0)
    assert torch.equal(ckernels.uniform(torch.Generator().manual_seed(1), n), torch.rand(n, generator=torch.Generator().manual_seed(1)))
    rows["uniform"] = {"numbers": n, **_ab(lambda: ckernels.uniform(g, n), lambda on: state.update(mt=on), a.bursts, 50)}
    print(json.dumps(rows["uniform"]), flush=True)

    cfg, mt = EnvConfig(), state["mt"]

    # one slot's noise at B = 4096 (world.draw_noise): the runs drawn and transformed in one C pass
    # (ckernels.uniform_runs) against torch.rand and torch's ops
    from uavlae.envs import UAVEnv
    from uavlae.envs.world import draw_noise

    env = UAVEnv(batch_size=[4096], seed=0)
    st = {k: v for k, v in env.reset()["state"].items()}
    on = draw_noise(st, cfg, torch.Generator().manual_seed(3))
    state["mt"] = False
    off = draw_noise(st, cfg, torch.Generator().manual_seed(3))
    state["mt"] = mt
    assert all(torch.equal(on[k], off[k]) for k in on)
    rows["draw_noise"] = {"batch": 4096, **_ab(lambda: draw_noise(st, cfg, g), lambda on: state.update(mt=mt if on else False),
                                                a.bursts, 50)}
    print(json.dumps(rows["draw_noise"]), flush=True)

    def kernels(on: bool) -> None:
        state.update(lib=lib if on else None, mt=mt if on else False)

    for b, calls, bursts in ((256, 3, a.bursts), (4096, 1, max(2, a.bursts // 2))):
        sides = {}
        for on in (True, False):
            kernels(on)
            h = torch.Generator().manual_seed(2)
            sides[on] = (sample_scenarios(cfg, b, h), h.get_state())
        kernels(True)
        assert all(torch.equal(sides[True][0][k], sides[False][0][k]) for k in sides[True][0].keys())
        assert torch.equal(sides[True][1], sides[False][1])
        name = "sample_scenarios" if b == 256 else f"sample_scenarios_{b}"
        rows[name] = {"scenarios": b, **_ab(lambda b=b: sample_scenarios(cfg, b, g), kernels, bursts, calls)}
        print(json.dumps(rows[name]), flush=True)

    out = {"measured_at": time.strftime("%Y-%m-%d %H:%M:%S %Z"), "machine": describe_machine(),
           "command": "python benchmarks/ckernels_ab.py " + " ".join(sys.argv[1:] if argv is None else argv),
           "rows": rows}
    dump_json(Path(a.out), out)


if __name__ == "__main__":
    main()
