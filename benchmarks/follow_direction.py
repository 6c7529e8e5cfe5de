"""What the ego direction column alone is worth: fly ``action = direction`` (no learning).

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/follow_direction.py

on the 32 saved evaluation scenarios of ``results/eval_set_32.json`` with ``env=shaped``
(straight-line direction), ``env=shaped_geodesic`` (the way around BZs and NFZs, the clearance
as walls) and ``env=shaped_geodesic_soft`` (the clearance passable at a cost), through the same
``uavlae.evaluate.Evaluator`` as every learner, then the two geodesic variants on 256 scenarios
sampled with seed 999 (episodes that stall, neither landing nor crashing, are counted), and times the one-off geodesic distance fields
(256 scenarios at once, as when ``UAVEnv`` fills its pool); writes ``follow_direction.json``.
"""

from __future__ import annotations

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

    from uavlae.factories import dump_json
    from uavlae.envs.scenario import load_scenarios
    from uavlae.evaluate import Evaluator

    scenarios = load_scenarios(ROOT / "results" / "eval_set_32.json")

    def follow(td):
        td.set("action", td.get("observation")[..., -6:-4])  # the direction column (ego_features)
        return td

    out = {"measured_at": time.strftime("%Y-%m-%d %H:%M:%S %Z"), "machine": describe_machine(),
           "command": "python benchmarks/follow_direction.py", "episodes": len(scenarios), "results": {}}
    from uavlae.envs.metrics import rollout_metrics
    from uavlae.envs.scenario import sample_scenarios, unstack_scenarios

    def fly(env: str, scen: list, seed: int) -> dict:
        ev = Evaluator(env_config(env), scen, seed=seed, n_plots=0)
        ev.env.set_seed(seed)
        with torch.no_grad():
            rec, agg, _ = rollout_metrics(ev.env, follow, cfg=ev.env_cfg)
        row = {k: round(float(agg[k]), 4) for k in ("DCR", "CR", "SLR", "RVR", "ECR")}
        # episodes neither landed nor crashed: the direction column stalled (truncated at t_max)
        row["stalled"] = int((~rec["landed"] & ~rec["collided"]).sum())
        row["zone_entries"] = int((rec["bz_collision"] | rec["nfz_entry"]).sum())
        row["ou_collisions"] = int(rec["ou_collision"].sum())
        print(env, len(scen), row, flush=True)
        return row

    for env in ("shaped", "shaped_geodesic", "shaped_geodesic_soft"):
        out["results"][env] = fly(env, scenarios, 12345)
    # the 32 evaluation scenarios are few: the geodesic variants again on 256 sampled ones
    big = unstack_scenarios(sample_scenarios(env_config("default"), 256, torch.Generator().manual_seed(999)))
    out["results_256_sampled_seed_999"] = {env: fly(env, big, 999) for env in ("shaped_geodesic", "shaped_geodesic_soft")}
    # the one-off cost of the geodesic distance fields, per scenario, at a pool fill of 256
    from uavlae.envs.scenario import sample_scenarios
    from uavlae.envs.world import initial_state

    cfg = env_config("shaped_geodesic")
    pool = sample_scenarios(cfg, 256, torch.Generator().manual_seed(0)).to_dict()
    t = time.perf_counter()
    initial_state(pool, cfg)
    out["geodesic_fields_ms_per_scenario_at_256"] = round((time.perf_counter() - t) / 256 * 1e3, 2)
    print("geodesic fields:", out["geodesic_fields_ms_per_scenario_at_256"], "ms per scenario (256 at once)")
    dump_json(ROOT / "benchmarks" / "follow_direction.json", out)


if __name__ == "__main__":
    main()
