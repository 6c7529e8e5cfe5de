"""Fly an exported actor on a scenario with torch alone (no torchrl, no LLM):

    python -m uavlae.fly --actor actor.pt2 --scenario scenario.json [--index 0] [--png out.png]

The scenario file is one scenario object or a list of them (``uavlae.envs.scenario`` JSON, as
the evaluation sets are saved). The world is the pure-torch ``uavlae.envs.world`` step with the
env config embedded in the actor file; the command prints the paper's metrics of the episode.
"""

from __future__ import annotations

import argparse
import importlib
import json
import sys
import types
from pathlib import Path
from typing import Any

import torch


def _world_modules() -> tuple[Any, Any]:
    """``uavlae.envs.world`` and ``uavlae.envs.config`` without the package ``__init__`` (which
    imports the TorchRL env): a bare package object stands in for ``uavlae.envs``."""
    if "uavlae.envs" not in sys.modules:
        pkg = types.ModuleType("uavlae.envs")
        pkg.__path__ = [str(Path(__file__).resolve().parent / "envs")]
        sys.modules["uavlae.envs"] = pkg
    return importlib.import_module("uavlae.envs.world"), importlib.import_module("uavlae.envs.config")


def scenario_tensors(d: dict[str, Any], cfg: Any) -> dict[str, torch.Tensor]:
    """One scenario dict (JSON) -> the padded batch-1 tensors of docs/env_contract.md."""
    pads = {
        "nfz": cfg.zones.n_nfz.padded, "rz": cfg.zones.n_rz.padded, "bz": cfg.zones.n_bz.padded,
        "ge_pos": cfg.ge.count.padded, "ou_pos": cfg.ou.count.padded,
    }

    def fill(rows: list, width: int, pad: int) -> tuple[torch.Tensor, torch.Tensor]:
        if len(rows) > pad:
            raise ValueError(f"the scenario has {len(rows)} entries where the config pads to {pad}")
        t = torch.zeros(1, pad, width)
        m = torch.zeros(1, pad, dtype=torch.bool)
        if rows:
            t[0, : len(rows)] = torch.tensor(rows, dtype=torch.float32)
            m[0, : len(rows)] = True
        return t, m

    out: dict[str, torch.Tensor] = {}
    for k in ("nfz", "rz", "bz"):
        out[k], out[f"{k}_mask"] = fill(d[k], 4, pads[k])
    out["ge_pos"], out["ge_mask"] = fill(d["ge_pos"], 2, pads["ge_pos"])
    out["ge_data"] = torch.zeros(1, pads["ge_pos"])
    out["ge_data"][0, : len(d["ge_data"])] = torch.tensor(d["ge_data"], dtype=torch.float32)
    out["ou_pos"], out["ou_mask"] = fill(d["ou_pos"], 2, pads["ou_pos"])
    out["ou_vel"], _ = fill(d["ou_vel"], 2, pads["ou_pos"])
    out["start"] = torch.tensor([d["start"]], dtype=torch.float32)
    return out


def load_actor(path: str | Path) -> tuple[Any, dict[str, Any]]:
    """An actor written by ``python -m uavlae.export`` (callable ``observation -> action``) and
    its ``meta`` (env config, algorithm, frames, versions); needs torch only."""
    extra = {"meta.json": ""}
    try:
        program = torch.export.load(str(path), extra_files=extra)
    except FileNotFoundError:
        raise
    except Exception as e:  # a torn file, a TorchScript file, anything else that is not ours
        raise ValueError(f"{path} is not an actor written by `python -m uavlae.export` ({type(e).__name__}: {e})") from e
    try:
        meta = json.loads(extra["meta.json"])
    except json.JSONDecodeError as e:
        raise ValueError(f"{path} has no valid meta.json (was it written by `python -m uavlae.export`?)") from e
    return program.module(), meta


def fly(actor: Any, env_cfg: Any, scenario: dict[str, Any], seed: int = 0) -> dict[str, Any]:
    """One episode of ``actor`` in ``scenario``; returns the metrics and the trajectory."""
    world, _ = _world_modules()
    layout = world.ObservationLayout(env_cfg)
    g = torch.Generator().manual_seed(seed)
    state = world.initial_state(scenario_tensors(scenario, env_cfg), env_cfg)
    path = [state["position"][0].clone()]
    ret = cost = 0.0
    any_event: dict[str, bool] = {}
    terminated = truncated = torch.zeros(1, dtype=torch.bool)
    with torch.no_grad():
        for _ in range(env_cfg.t_max):
            action = actor(layout.build(state))
            state, events, terms, c, terminated, truncated = world.world_step(state, action, env_cfg, g)
            path.append(state["position"][0].clone())
            ret += float(sum(t.sum() for t in terms.values()))
            cost += float(c.sum())
            for k, v in events.items():
                any_event[k] = any_event.get(k, False) or bool(v.any())
            if bool((terminated | truncated).any()):
                break
    collided = any_event["bz_collision"] or any_event["nfz_entry"] or any_event["ou_collision"]
    total = float(state["data_total"].sum())
    return {
        "steps": len(path) - 1,
        "return": ret,
        "cost": cost,
        "DCR": float(state["data_collected"].sum()) / total if total > 0 else float("nan"),
        "collided": collided,
        "landed": any_event["landed"],
        "rz_speeding": any_event["rz_speeding"],
        "ECR": float(state["energy_used"].sum()) / env_cfg.energy.e_total,
        "terminated": bool(terminated.any()),
        "truncated": bool(truncated.any()),
        "trajectory": torch.stack(path).tolist(),
    }


def main(argv: list[str] | None = None) -> dict[str, Any]:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--actor", required=True, help="actor file written by python -m uavlae.export (.pt2)")
    p.add_argument("--scenario", required=True, help="scenario JSON (one object, or a list)")
    p.add_argument("--index", type=int, default=0, help="which scenario of a list")
    p.add_argument("--seed", type=int, default=0, help="seeds the other UAVs' random motion")
    p.add_argument("--png", default=None, help="draw the flight to this PNG (needs matplotlib)")
    args = p.parse_args(argv)

    actor, meta = load_actor(args.actor)
    _, config = _world_modules()
    env_cfg = config.make_env_config(meta["env"])
    data = json.loads(Path(args.scenario).read_text())
    scenario = data[args.index] if isinstance(data, list) else data
    result = fly(actor, env_cfg, scenario, seed=args.seed)
    traj = result.pop("trajectory")
    print(json.dumps(result, indent=1))
    if args.png:
        from uavlae.envs.render import draw_scenario  # plotting only: not needed to fly

        draw_scenario(scenario_tensors(scenario, env_cfg), [torch.tensor(traj)], path=args.png,
                      title=f"{meta.get('name', 'actor')} ({result['steps']} steps)", cfg=env_cfg)
    result["trajectory"] = traj
    return result


if __name__ == "__main__":
    main()
