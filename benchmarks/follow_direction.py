"""What the ego direction column alone is worth: fly ``action = direction`` (no learning).

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/follow_direction.py

on the 32 saved evaluation scenarios of ``results/paper_table_eval_set.json`` with ``env=shaped``
(straight-line direction) and ``env=shaped_geodesic`` (the way around BZs and NFZs), through the
same ``uavlae.evaluate.Evaluator`` as every learner, and times the one-off geodesic distance fields
(256 scenarios at once, as when ``UAVEnv`` fills its pool); writes ``follow_direction.json``.
"""

from __future__ import annotations

import json
import os
import sys
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))


def main() -> None:
    torch.set_num_threads(1)
    os.environ.setdefault("WANDB_MODE", "disabled")
    from time_to_target import env_config

    from uavlae.machine import describe_machine
    from uavlae.envs.scenario import load_scenarios
    from uavlae.evaluate import Evaluator

    scenarios = load_scenarios(ROOT / "results" / "paper_table_eval_set.json")

    def follow(td):
        td.set("action", td.get("observation")[..., -6:-4])  # the direction column (ego_features)
        return td

    out = {"measured_at": time.strftime("%Y-%m-%d %H:%M:%S %Z"), "machine": describe_machine(),
           "command": "python benchmarks/follow_direction.py", "episodes": len(scenarios), "results": {}}
    for env in ("shaped", "shaped_geodesic"):
        agg = Evaluator(env_config(env), scenarios, seed=12345, n_plots=0).run(follow)
        row = {k: round(float(agg[k]), 4) for k in ("DCR", "CR", "SLR", "RVR", "ECR")}
        out["results"][env] = row
        print(env, row, flush=True)
    # the one-off cost of the geodesic distance fields, per scenario, at a pool fill of 256
    from uavlae.envs.scenario import sample_scenarios
    from uavlae.envs.world import initial_state

    cfg = env_config("shaped_geodesic")
    pool = sample_scenarios(cfg, 256, torch.Generator().manual_seed(0)).to_dict()
    t = time.perf_counter()
    initial_state(pool, cfg)
    out["geodesic_fields_ms_per_scenario_at_256"] = round((time.perf_counter() - t) / 256 * 1e3, 2)
    print("geodesic fields:", out["geodesic_fields_ms_per_scenario_at_256"], "ms per scenario (256 at once)")
    (ROOT / "benchmarks" / "follow_direction.json").write_text(json.dumps(out, indent=1) + "\n")


if __name__ == "__main__":
    main()
