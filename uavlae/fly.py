"""Fly an exported actor or pilot on a scenario with torch alone (no torchrl, no LLM):

    python -m uavlae.fly --actor actor.pt2 --scenario scenario.json [--index 0] [--png out.png]
    python -m uavlae.fly --actor pilot.pt2 --scenario set.json --all [--no-filter] [--act mean|sample] [--full-speed]

An actor reads the observation (built here from the embedded env config); a pilot
(``uavlae.export`` of a run with a safety filter) reads the raw state the DCU perceives and
flies through its filter (``--no-filter``: its actor alone), its actor acting as its recipe says
(its mean action, or a draw from its policy from the evaluator's noise stream; ``--act``).
``--all`` flies every scenario of the file as one batch with the evaluator's OU random stream
(and noise stream), so it reproduces the evaluator's pooled metrics.

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


# the raw state entries an exported pilot takes (uavlae.export.PILOT_STATE_KEYS, kept in step by a test)
PILOT_STATE_KEYS = (
    "nfz", "nfz_mask", "rz", "rz_mask", "bz", "bz_mask", "ge_pos", "ge_mask", "takeoff", "landing", "data_total",
    "position", "velocity", "energy_used", "energy_left", "slot_data", "data_collected", "step", "ge_remaining",
    "ou_pos", "ou_vel", "ou_mask", "served_ge",
)


def perceived(state: dict[str, torch.Tensor], env_cfg: Any) -> dict[str, torch.Tensor]:
    """What the DCU knows of ``state``: the pilot's entries, the OUs beyond the perception radius masked."""
    s = {k: state[k] for k in PILOT_STATE_KEYS}
    d = torch.linalg.vector_norm(s["ou_pos"] - s["position"].unsqueeze(-2), dim=-1)
    s["ou_mask"] = s["ou_mask"] & (d <= env_cfg.safety.perception_radius)
    return s


def full_speed(action: torch.Tensor, v_max: float) -> torch.Tensor:
    """The action of the same direction at ``v_max`` (in the env's units: |a| = 1) where the
    action's velocity (docs/model.md §2) is at least 0.5 m/s, else the action: what
    ``safety_filter.cruise`` flies (:func:`uavlae.policies.safety.cruise_action`)."""
    _world_modules()
    from uavlae.policies.safety import cruise_action

    return cruise_action(action, v_max)


def policy_of(module: Any, meta: dict[str, Any], env_cfg: Any, use_filter: bool = True, act: str | None = None,
              at_full_speed: bool = False) -> Any:
    """``state -> action`` for an exported file: an actor reads the observation the env would
    build, a pilot the perceived raw state (its filter on unless ``use_filter`` is False). A pilot's
    actor acts as ``act`` says (default: as its recipe, meta ``actor``): ``mean``, or ``sample``, a
    draw from its policy with the noise from the evaluator's stream (meta ``noise_seed``),
    started anew by each call of this function. ``at_full_speed``, a diagnosis and not the pilot:
    the actor's action through the pilot's filter (the same module in-process: ``SafetyFilter``
    with the pilot's settings) with ``cruise`` on, which flies it in its direction at v_max first
    (alone: :func:`full_speed`), to ask how much of a pilot's time its wished speed costs."""
    from uavlae.policies.draws import draw, noise_stream

    world, _ = _world_modules()
    if meta.get("kind", "actor") == "pilot":
        flag = torch.tensor(bool(use_filter))
        if "noise_dim" not in meta:  # a pilot exported before the noise input: its mean action
            if act == "sample":
                raise ValueError("--act sample: this pilot was exported without a noise input (its mean action only)")
            if at_full_speed:
                raise ValueError("--full-speed: this pilot was exported without a noise input")
            return lambda state: module(perceived(state, env_cfg), flag)
        dim, mode = int(meta["noise_dim"]), act or meta.get("actor", "mean")
        stream = noise_stream(int(meta.get("noise_seed", 0)))
        safety = None
        if at_full_speed and use_filter:
            from uavlae.policies.safety import SafetyFilter

            safety = SafetyFilter(env_cfg, {**meta["safety_filter"], "cruise": True})

        def pilot(state: dict[str, torch.Tensor]) -> torch.Tensor:
            rows = state["position"].shape[0]
            noise = draw(stream, rows, dim) if mode == "sample" else torch.zeros(rows, dim)
            s = perceived(state, env_cfg)
            if not at_full_speed:
                return module(s, flag, noise)
            wish = module(s, torch.tensor(False), noise)
            if safety is None:
                return full_speed(wish, env_cfg.motion.v_max)
            s = dict(s)
            s.update(world.nearest_distances(s, env_cfg))
            return safety.filter_action(s, wish)[0]

        return pilot
    if at_full_speed:
        raise ValueError("--full-speed: an exported actor without its filter; export the pilot")
    if act == "sample":
        raise ValueError("--act sample: an exported actor flies its mean action; a pilot (exported with its filter) can sample")
    layout = world.ObservationLayout(env_cfg)
    return lambda state: module(layout.build(state))


def fly_batch(policy: Any, env_cfg: Any, scenarios: list[dict[str, Any]], seed: int = 0,
              max_steps: int | None = None, on_step: Any = None) -> dict[str, Any]:
    """Every scenario at once, one row each, as the evaluator flies its set: the same batch, the
    same OU random stream (``seed``), each row's first episode scored, rows that ended stepped on
    until all have (their output ignored). Returns per-episode records and the pooled metrics.
    ``on_step(state, action)``, if given, sees each slot's state before the step and its action
    (for diagnoses that record the flight)."""
    world, _ = _world_modules()
    parts = [scenario_tensors(d, env_cfg) for d in scenarios]
    scen = {k: torch.cat([p[k] for p in parts]) for k in parts[0]}
    g = torch.Generator().manual_seed(seed)
    state = world.initial_state(scen, env_cfg)
    b = len(scenarios)
    ended = torch.zeros(b, dtype=torch.bool)
    keys = ("bz_collision", "nfz_entry", "ou_collision", "rz_speeding", "landed")
    seen = {k: torch.zeros(b, dtype=torch.bool) for k in keys}
    final = {k: torch.zeros(b) for k in ("data_collected", "data_total", "energy_used")}
    length = torch.zeros(b, dtype=torch.int64)
    with torch.no_grad():
        for _ in range(int(max_steps or env_cfg.t_max)):
            action = policy(state)
            if on_step is not None:
                on_step(state, action)
            state, events, _, _, terminated, truncated = world.world_step(state, action, env_cfg, g)
            live = ~ended
            for k in keys:
                seen[k] |= events[k] & live
            done = (terminated | truncated) & live
            for k in final:
                final[k] = torch.where(done, state[k], final[k])
            length += live.long()
            ended |= done
            if bool(ended.all()):
                break
    for k in final:  # rows still flying when the budget ran out
        final[k] = torch.where(ended, final[k], state[k])
    collided = seen["bz_collision"] | seen["nfz_entry"] | seen["ou_collision"]
    metrics = {
        "DCR": float(final["data_collected"].sum() / final["data_total"].sum()),
        "CR": float(collided.float().mean()),
        "SLR": float(seen["landed"].float().mean()),
        "RVR": float(seen["rz_speeding"].float().mean()),
        "ECR": float(final["energy_used"].sum()) / (b * env_cfg.energy.e_total),
    }
    return {"metrics": metrics, "episodes": b, "length": length.tolist(), "collided": collided.tolist(),
            "landed": seen["landed"].tolist(), "rz_speeding": seen["rz_speeding"].tolist()}


def fly(actor: Any, env_cfg: Any, scenario: dict[str, Any], seed: int = 0) -> dict[str, Any]:
    """One episode of ``actor`` (``state -> action``, :func:`policy_of`) in ``scenario``;
    returns the metrics and the trajectory."""
    world, _ = _world_modules()
    g = torch.Generator().manual_seed(seed)
    state = world.initial_state(scenario_tensors(scenario, env_cfg), env_cfg)
    path = [state["position"][0].clone()]
    ret = cost = 0.0
    any_event: dict[str, bool] = {}
    terminated = truncated = torch.zeros(1, dtype=torch.bool)
    with torch.no_grad():
        for _ in range(env_cfg.t_max):
            action = actor(state)
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
    p.add_argument("--actor", required=True, help="actor or pilot file written by python -m uavlae.export (.pt2)")
    p.add_argument("--scenario", required=True, help="scenario JSON (one object, or a list)")
    p.add_argument("--index", type=int, default=0, help="which scenario of a list")
    p.add_argument("--all", action="store_true",
                   help="fly every scenario of the list as the evaluator does; the last line is the pooled metrics as JSON")
    p.add_argument("--no-filter", action="store_true", help="a pilot's actor alone, without its safety filter")
    p.add_argument("--act", choices=("mean", "sample"), default=None,
                   help="a pilot's actor: its mean action, or a draw from its policy from the evaluator's noise stream "
                        "(default: as its recipe flies, meta 'actor')")
    p.add_argument("--full-speed", action="store_true",
                   help="a diagnosis, not the pilot: the actor's action flown in its direction at v_max (wishes "
                        "under 0.5 m/s as they are), then through the pilot's filter (safety_filter.cruise in training)")
    p.add_argument("--seed", type=int, default=None,
                   help="seeds the other UAVs' random motion (default: the run's evaluation seed with --all, else 0)")
    p.add_argument("--png", default=None, help="draw the flight to this PNG (needs matplotlib)")
    args = p.parse_args(argv)

    actor, meta = load_actor(args.actor)
    _, config = _world_modules()
    env_cfg = config.make_env_config(meta["env"])
    if args.no_filter and meta.get("kind", "actor") != "pilot":
        raise SystemExit(f"--no-filter: {args.actor} is an actor without a safety filter")
    try:
        policy = policy_of(actor, meta, env_cfg, use_filter=not args.no_filter, act=args.act,
                           at_full_speed=args.full_speed)
    except ValueError as e:
        raise SystemExit(str(e)) from None
    data = json.loads(Path(args.scenario).read_text())
    if args.all:
        scenarios = data if isinstance(data, list) else [data]
        seed = int(meta.get("eval_seed", 0)) if args.seed is None else args.seed
        out = fly_batch(policy, env_cfg, scenarios, seed=seed, max_steps=meta.get("eval_max_steps"))
        print(json.dumps({k: v for k, v in out.items() if k != "metrics"}))
        print(json.dumps(out["metrics"]))
        return out
    scenario = data[args.index] if isinstance(data, list) else data
    result = fly(policy, env_cfg, scenario, seed=args.seed or 0)
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
