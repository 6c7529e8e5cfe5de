"""The pilot study (``make pilot-study``; uavlae/experiments/README.md, "A pilot worth deploying").

Five sub-commands:

- ``records RUNS_DIR --out results/pilot``: what the report needs of every finished run under
  ``RUNS_DIR/pilot/<stage>/<rung>/seed<k>``, as CSV files that travel with the repository:
  ``runs.csv`` (one row a run: stage, rung, seed, frames, wall clock, the recipe's keys, the
  filter's intervention shares, commit), ``episodes.csv`` (one row per evaluation episode: the
  pilot, i.e. the actor through its filter, and the actor alone, on the selection set and, where
  flown, on the held-out and confirmation sets; the greedy heuristic and uniform random on the
  selection set) and
  ``curves.csv`` (every evaluation during training: frames, training wall clock, the pilot's and
  the actor's metrics). Records of runs not under ``RUNS_DIR`` are kept.
- ``references --out results/pilot``: the reference policies flown on the same sets, recorded
  as stage ``references`` (one "seed" each): the greedy heuristic, the global planner, uniform
  random, plain-SAC-free controllers with and without the filter, and the follower of the
  planner's geodesic direction (what planner knowledge buys) with and without the filter.
- ``card results/pilot``: the committed pilot's model card (``README.md``) from those files
  and the recipe (``uavlae/conf/exp/pilot_drawn.yaml``, which ``+exp=pilot`` composes) alone.
- ``stalls --actor results/pilot/pilot.pt2``: where an exported pilot's unlanded held-out
  episodes end (``stalls.json``): beside a building or no-fly zone, held there, and how much
  the filter changes the actor's wish over their last slots; the card reports it.
- ``report results/pilot``: ``report.md`` from those files alone: per stage and rung, the pilot
  and the actor alone side by side with stratified-bootstrap intervals over seeds x scenarios
  (:mod:`uavlae.experiments.advice_stats`), the filter's share, the compute, the time to a pilot
  (the first evaluation whose pilot meets every floor), and the paired differences between
  adjacent rungs of the ladder.
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
import sys
from collections import defaultdict
from pathlib import Path
from typing import Any

from uavlae.experiments.advice import EPISODE_COLUMNS
from uavlae.experiments.advice_stats import METHOD_NAME, METRICS, difference, grid_from_rows, interval
from uavlae.experiments.reporting import cell_true, fmt_interval, markdown_table, read_json, read_rows, read_scalar, write_csv, write_text
from uavlae.entry import command
from uavlae.errors import InputError
from uavlae.files import train_eval_dir
from uavlae.selection import selection_score

KEY_COLUMNS = ["stage", "rung", "seed"]
EPISODE_KEYS = [*KEY_COLUMNS, "evaluation", "set", "scenario"]
# the floors a pilot must meet (ECR: no worse than the greedy heuristic's on the same scenarios)
FLOORS = {"DCR": (">=", 0.95), "SLR": (">=", 0.90), "CR": ("<=", 0.02), "RVR": ("<=", 0.01)}
# what the training curves keep: (scalar file under logs/scalars, column)
CURVE_SCALARS = tuple((f"eval/{m}", m) for m in METRICS) + tuple((f"eval/actor/{m}", f"actor_{m}") for m in METRICS) + (
    ("eval/train_wall_s", "train_wall_s"), ("eval/safety/intervention_rate", "eval_intervention"),
    ("safety/intervention_rate", "train_intervention"))
# a verdict run flown on the sets that judge it: <run>/evaluate/<folder> -> (evaluation, set)
HELDOUT = {"heldout_pilot": ("pilot", "heldout"), "heldout_alone": ("alone", "heldout"),
           "confirm_pilot": ("pilot", "confirm"), "confirm_alone": ("alone", "confirm"),
           # a screening run's kept pilot on the screening set (make pilot-screen-wide)
           "screening_pilot": ("pilot", "screening"), "screening_alone": ("alone", "screening")}
# the same networks flown by draws from their policy (trainer.eval_actor=sample; make pilot-sampling):
# <run>/evaluate/<folder> -> (evaluation, set)
SAMPLED = {"selection_sample": ("pilot_sample", "selection"), "selection_alone_sample": ("alone_sample", "selection"),
           "heldout_pilot_sample": ("pilot_sample", "heldout"), "heldout_alone_sample": ("alone_sample", "heldout")}
# the rows of a stage's table: evaluation -> what flew
FLOWN = {"pilot": "actor + filter", "pilot_sample": "actor (a draw) + filter", "alone": "actor alone",
         "alone_sample": "actor alone (a draw)"}


def _filtered(cfg: dict[str, Any]) -> bool:
    return (cfg.get("safety_filter") or {}).get("mode", "off") != "off"


def run_record(d: Path) -> tuple[dict[str, Any], list[dict[str, Any]], list[dict[str, Any]]] | None:
    """(run row, episode rows, curve rows) of a finished run in ``d``; None when unfinished."""
    if not ((d / "final_metrics.json").is_file() and (d / "config.json").is_file()):
        return None
    cfg, final = read_json(d / "config.json"), read_json(d / "final_metrics.json")
    frames = int(final.get("frames", 0))
    if frames < int(cfg["trainer"]["total_frames"]):
        return None
    ex = cfg.get("experiment") or {}
    key = {"stage": str(ex.get("point")), "rung": str(ex.get("method") or cfg["name"]), "seed": int(cfg["seed"])}
    meta = read_json(d / "meta.json") if (d / "meta.json").is_file() else {}
    env, sf = cfg["env"], cfg.get("safety_filter") or {}
    run = {**key, "frames": frames, "wall_s": final.get("wall_s"), "updates": final.get("updates"),
           "algo": cfg["algo"]["name"], "hidden": cfg["algo"].get("hidden"), "obs_frame": env.get("obs_frame", "world"),
           "filter": sf.get("mode", "off"), "filter_penalty": sf.get("penalty", 0.0),
           "filter_learn_from": sf.get("learn_from", "executed"), "filter_cost": sf.get("cost", 0.0),
           "progress_weight": env["reward"].get("progress_weight"), "advisor": cfg["advisor"]["kind"],
           "train_intervention": final.get("safety/train/intervention_rate"),
           "eval_intervention": final.get("eval/safety/intervention_rate"),
           "eval_mean_change": final.get("eval/safety/mean_change"),
           "best_frames": final.get("best/frames"),
           # how the run's own evaluations fly its actor: mean, or sample (a draw from its policy)
           "eval_actor": str((cfg.get("trainer") or {}).get("eval_actor", "mean")),
           "commit": str((meta.get("git") or {}).get("commit") or "")[:10]}
    out = train_eval_dir(d, frames)
    sources = {("alone", "selection"): out / "actor_alone" if _filtered(cfg) else out,
               ("heuristic", "selection"): d / "eval" / "baseline_heuristic",
               ("random", "selection"): d / "eval" / "baseline_random"}
    if _filtered(cfg):
        sources[("pilot", "selection")] = out
    for folder, cell in (HELDOUT | SAMPLED).items():
        sources[cell] = d / "evaluate" / folder
    episodes = []
    for (evaluation, which), folder in sources.items():
        for i, row in enumerate(read_rows(folder / "episodes.csv")):
            episodes.append({**key, "evaluation": evaluation, "set": which, "scenario": int(row.get("row", i)),
                             **{c: row.get(c) for c in EPISODE_COLUMNS}})
    curves: dict[int, dict[str, Any]] = defaultdict(dict)
    for name, col in CURVE_SCALARS:
        for step, value in read_scalar(d, name):
            curves[int(step)][col] = value  # a frame count: written as a whole number
    curve_rows = [{**key, "frames": step, **vals} for step, vals in sorted(curves.items()) if "DCR" in vals]
    return run, episodes, curve_rows


def _path_key(path: str) -> tuple[str, str, int] | None:
    """(stage, rung, seed) of a run folder named ``pilot/<stage>/<rung>/seed<N>``; None otherwise."""
    parts = Path(path).parts
    if len(parts) != 4 or not parts[3].startswith("seed") or not parts[3][4:].isdigit():
        return None
    return parts[1], parts[2], int(parts[3][4:])


def write_records(root: Path, out: Path) -> dict[str, int]:
    """Adds the finished runs under ``root/pilot`` to the records in ``out`` (module doc)."""
    runs, episodes, curves, unfinished = [], [], [], []
    for cfg_file in sorted((root / "pilot").rglob("config.json")):
        d = cfg_file.parent
        if any(p.startswith(".") for p in d.relative_to(root).parts):
            continue
        rec = run_record(d)
        if rec is None:
            unfinished.append(str(d.relative_to(root)))
            continue
        runs.append(rec[0])
        episodes.extend(rec[1])
        curves.extend(rec[2])
    fresh = {(r["stage"], r["rung"], int(r["seed"])) for r in runs}

    def merged(name: str, new: list[dict[str, Any]]) -> list[dict[str, Any]]:
        old = [r for r in read_rows(out / name) if (r["stage"], r["rung"], int(r["seed"])) not in fresh]
        return old + new

    runs, episodes, curves = merged("runs.csv", runs), merged("episodes.csv", episodes), merged("curves.csv", curves)
    # the runs still unfinished under earlier roots stay listed (the records span several run
    # folders) until a root holds them finished
    done = {(r["stage"], r["rung"], int(r["seed"])) for r in runs}
    unfinished = list(dict.fromkeys([*(r["path"] for r in read_rows(out / "unfinished.csv")
                                       if _path_key(r["path"]) not in done), *unfinished]))
    write_csv(out / "runs.csv", runs, list(dict.fromkeys(k for r in runs for k in r)) or KEY_COLUMNS)
    write_csv(out / "episodes.csv", episodes, [*EPISODE_KEYS, *EPISODE_COLUMNS])
    write_csv(out / "curves.csv", curves, [*KEY_COLUMNS, "frames", *[c for _, c in CURVE_SCALARS]])
    write_csv(out / "unfinished.csv", [{"path": p} for p in unfinished], ["path"])
    return {"runs": len(runs), "episodes": len(episodes), "curve_rows": len(curves), "unfinished": len(unfinished)}


# ---------------------------------------------------------------------------- the references

# the selection set chooses; the held-out set (seed 90210) judges; the confirmation set (seed 8675309)
# judges again on scenarios drawn after the verdict's recipe was fixed and flown by nothing before its
# checkpoints: the held-out set had been flown with tuning-seed checkpoints while the recipe was chosen.
# The screening set (seed 31337) compares the pilots that screening runs kept (each the best of its
# evaluations on the 32 selection scenarios) on 256 scenarios that chose none of them, so that a
# recipe is carried to a verdict on more than 32 scenarios a seed; it judges no verdict.
SETS = {"selection": Path("results/eval_set_32.json"), "screening": Path("results/pilot/screen_set_256.json"),
        "heldout": Path("results/pilot/heldout_set_256.json"), "confirm": Path("results/pilot/confirm_set_256.json")}
# how the report and the card name each set
SET_TITLES = {"selection": "the selection set (results/eval_set_32.json)",
              "screening": "the screening set (results/pilot/screen_set_256.json), each run's kept pilot",
              "heldout": "the held-out set (results/pilot/heldout_set_256.json)",
              "confirm": "the confirmation set (results/pilot/confirm_set_256.json)"}
SET_NAMES = {"selection": "selection", "screening": "screening", "heldout": "held-out", "confirm": "confirmation"}
EVAL_SEED = 12345  # trainer.eval_seed: the OU stream every run's evaluation flies


def _env_cfg(name: str) -> Any:
    from hydra import compose, initialize_config_dir

    from uavlae.envs import make_env_config
    from uavlae.factories import CONF_DIR

    with initialize_config_dir(str(CONF_DIR), version_base="1.3"):
        return make_env_config(compose("config", overrides=[f"env={name}"]).env)


def _follower(td: Any) -> Any:
    """The planner's geodesic direction at full speed: ``env=shaped_geodesic_soft``'s ego columns
    end with the target vector and its unit direction, then the nearest BZ and NFZ vectors."""
    td.set("action", td.get("observation")[..., -6:-4])
    return td


def write_references(out: Path, sets: dict[str, Path] | None = None) -> dict[str, int]:
    """Fly the reference policies on each set (module doc) and add their episodes to the records."""
    import torch

    from uavlae.envs.scenario import load_scenarios
    from uavlae.evaluate import Evaluator
    from uavlae.policies.greedy import GreedyPolicy
    from uavlae.policies.heuristic import HeuristicPolicy
    from uavlae.policies.random import UniformRandomPolicy
    from uavlae.policies.safety import FilteredPolicy, SafetyFilter

    spec, geodesic = _env_cfg("default"), _env_cfg("shaped_geodesic_soft")
    episodes = []
    for which, path in (sets or SETS).items():
        scenarios = load_scenarios(path)
        for world, cfg in (("spec", spec), ("geodesic", geodesic)):
            ev = Evaluator(cfg, scenarios, seed=EVAL_SEED, n_plots=0)
            if world == "spec":
                policies = {"greedy": GreedyPolicy(cfg), "planner": HeuristicPolicy(cfg),
                            "random": UniformRandomPolicy(ev.env.action_spec, seed=EVAL_SEED),
                            "random_filtered": FilteredPolicy(UniformRandomPolicy(ev.env.action_spec, seed=EVAL_SEED),
                                                              SafetyFilter(cfg, {"mode": "deploy"}))}
            else:  # the same world and scenarios; its observation carries the geodesic direction
                policies = {"follower": _follower,
                            "follower_filtered": FilteredPolicy(_follower, SafetyFilter(cfg, {"mode": "deploy"}))}
            for name, policy in policies.items():
                folder = out / "references" / which / name
                with torch.no_grad():
                    ev.run(policy, folder)
                for i, row in enumerate(read_rows(folder / "episodes.csv")):
                    episodes.append({"stage": "references", "rung": name, "seed": 0, "evaluation": "alone",
                                     "set": which, "scenario": int(row.get("row", i)),
                                     **{c: row.get(c) for c in EPISODE_COLUMNS}})
                print(f"{which} {name}", flush=True)
    flown = set(sets or SETS)  # the references on sets not flown now stay recorded
    old = [r for r in read_rows(out / "episodes.csv") if r["stage"] != "references" or r["set"] not in flown]
    write_csv(out / "episodes.csv", old + episodes, [*EPISODE_KEYS, *EPISODE_COLUMNS])
    return {"episodes": len(episodes)}


# ---------------------------------------------------------------------------- where pilots stall

STALL_NEAR_M = 3.0  # an episode "ends at an obstacle" within this distance of a BZ or NFZ
STALL_STILL_M = 20.0  # ... and "is held" when it moved less than this over its last window


def stall_summary(positions: Any, changes: Any, lengths: Any, landed: Any, obstacles: list[tuple[Any, Any]],
                  window: int = 200) -> dict[str, float]:
    """Where the episodes that did not land ended. ``positions`` [T, B, 2] and ``changes``
    [T, B] (the filter's |executed - wished| in m/s) per slot, each row's ``lengths`` [B] and
    ``landed`` [B]; ``obstacles``: (rectangles [B, K, 4] as x0, y0, x1, y1, mask [B, K]) of the
    BZs and NFZs. Over each row's last ``window`` slots: its net displacement and the filter's
    mean change; at its end: its distance to the nearest obstacle."""
    import torch

    b = positions.shape[1]
    rows = torch.arange(b)
    last = (lengths - 1).clamp_min(0)
    first = (lengths - window).clamp_min(0)
    end, start = positions[last, rows], positions[first, rows]
    dist = torch.full((b,), math.inf)
    for rect, mask in obstacles:
        dx = torch.maximum(rect[..., 0] - end[:, None, 0], end[:, None, 0] - rect[..., 2]).clamp_min(0)
        dy = torch.maximum(rect[..., 1] - end[:, None, 1], end[:, None, 1] - rect[..., 3]).clamp_min(0)
        d = torch.where(mask, torch.hypot(dx, dy), torch.full_like(dx, math.inf))
        dist = torch.minimum(dist, d.min(-1).values)
    t = torch.arange(positions.shape[0])[:, None]
    in_window = (t >= first) & (t < lengths)
    in_flight = t < lengths
    change_window = (changes * in_window).sum(0) / in_window.sum(0).clamp_min(1)
    net = torch.linalg.vector_norm(end - start, dim=-1)
    out = ~landed
    n_out = int(out.sum())
    flown = (changes * in_flight)[:, landed].sum() / in_flight[:, landed].sum().clamp_min(1)
    return {
        "episodes": b, "unlanded": n_out,
        "unlanded_at_obstacle": int((out & (dist < STALL_NEAR_M)).sum()),
        "unlanded_held": int((out & (dist < STALL_NEAR_M) & (net < STALL_STILL_M)).sum()),
        "unlanded_filter_change_median": statistics.median(change_window[out].tolist()) if n_out else math.nan,
        "landed_filter_change_mean": float(flown) if bool(landed.any()) else math.nan,
        "window": window,
    }


HELD_CHUNK = 50  # slots: a landed mission's time is cut into chunks this long ...


def mission_pace(positions: Any, lengths: Any, landed: Any, chunk: int = HELD_CHUNK,
                 still: float = STALL_STILL_M, places: dict[str, Any] | None = None) -> dict[str, float]:
    """Where a landed mission's time goes. Each landed row's flight ([T, B, 2] ``positions``,
    the position before each of its ``lengths`` slots): its slots, its path (the sum of the
    moves between those positions) and so its pace (path / slots, pooled over the landed rows),
    and its held slots: the flight cut into whole chunks of ``chunk`` slots from its start (a
    last, shorter chunk is not counted), a chunk whose net displacement is below ``still`` m
    held. Every slot costs 294-337 J whatever the DCU does (docs/model.md §4), so a mission's
    energy is its slots: a longer path, a slower pace or time held.

    With ``places`` (name -> [T, B] bool: where each slot starts, e.g. over a residential zone),
    each slot goes to the first place it starts in, else to ``elsewhere``; for each, the slots a
    landed mission spends there and the pace of the moves that start there (a row's last slot
    has no recorded move)."""
    import torch

    rows = torch.nonzero(landed).flatten().tolist()
    names = [*places, "elsewhere"] if places else []
    place_keys = [f"landed_{n}_{k}" for n in names for k in ("slots_mean", "m_per_slot")]
    if not rows:
        return {"landed_slots_mean": math.nan, "landed_path_m_mean": math.nan, "landed_m_per_slot": math.nan,
                "landed_held_slots_mean": math.nan, "chunk": chunk, **{k: math.nan for k in place_keys}}
    held, paths = [], []
    slots_in, moves_in, path_in = defaultdict(int), defaultdict(int), defaultdict(float)
    for i in rows:
        n_slots = int(lengths[i])
        p = positions[:n_slots, i]
        moves = torch.linalg.vector_norm(p[1:] - p[:-1], dim=-1)
        paths.append(float(moves.sum()))
        starts = torch.arange(n_slots // chunk) * chunk
        net = torch.linalg.vector_norm(p[starts + chunk - 1] - p[starts], dim=-1)
        held.append(int((net < still).sum()) * chunk)
        if places:
            free = torch.ones(n_slots, dtype=torch.bool)
            for n in names:
                here = free.clone() if n == "elsewhere" else places[n][:n_slots, i].bool() & free
                free &= ~here
                slots_in[n] += int(here.sum())
                moves_in[n] += int(here[:-1].sum())
                path_in[n] += float(moves[here[:-1]].sum())
    slots = [int(lengths[i]) for i in rows]
    out = {"landed_slots_mean": sum(slots) / len(rows), "landed_path_m_mean": sum(paths) / len(rows),
           "landed_m_per_slot": sum(paths) / sum(slots), "landed_held_slots_mean": sum(held) / len(rows),
           "chunk": chunk}
    for n in names:
        out[f"landed_{n}_slots_mean"] = slots_in[n] / len(rows)
        out[f"landed_{n}_m_per_slot"] = path_in[n] / moves_in[n] if moves_in[n] else math.nan
    return out


def landed_mean(values: Any, lengths: Any, landed: Any) -> float:
    """The mean of ``values`` ([T, B], one a slot) over every slot of the landed rows."""
    import torch

    live = (torch.arange(values.shape[0]).unsqueeze(1) < torch.as_tensor(lengths).unsqueeze(0)) \
        & torch.as_tensor(landed).bool().unsqueeze(0)
    return float(values[live].mean()) if bool(live.any()) else math.nan


def stalls(actor: Path, scenario_set: Path, window: int = 200) -> dict[str, float]:
    """Fly the exported pilot ``actor`` on every scenario of ``scenario_set`` as ``uavlae.fly
    --all`` does (the same batch and OU stream), asking its actor alone beside it each slot for
    the wish the filter corrected, and summarise where the unlanded episodes ended
    (:func:`stall_summary`) and where the landed ones' time went (:func:`mission_pace`), beside the
    greedy heuristic flown on the same scenarios and OU stream (``greedy_*``)."""
    import torch

    from uavlae import fly
    from uavlae.envs import make_env_config

    module, meta = fly.load_actor(actor)
    if meta.get("kind", "actor") != "pilot":
        raise InputError(f"{actor} is an actor without a safety filter: stalls reads a pilot's (uavlae.export of a "
                         "run with safety_filter.mode other than off)")
    cfg = make_env_config(meta["env"])
    alone = fly.policy_of(module, meta, cfg, False)
    scenarios = read_json(scenario_set)
    from uavlae.envs import physics as ph

    positions, changes, marks, speeds, wishes = [], [], [], [], []
    v_max = cfg.motion.v_max

    def speed(action: Any) -> Any:  # m/s, as the env flies an action (docs/model.md §2)
        return torch.linalg.vector_norm(ph.action_to_velocity(action, v_max), dim=-1)

    near = cfg.safety.d_min  # where the proximity ramps r3 / r4 are at their full weight (docs/model.md §7)

    def where(state: Any, into: list[Any]) -> None:  # [2, B]: over an RZ, within d_min of a wall
        p = state["position"]
        rz = ph.point_rect_distance(p, state["rz"], state["rz_mask"]).le(0).any(-1)
        walls = torch.cat([ph.point_rect_distance(p, state["bz"], state["bz_mask"]),
                           ph.point_rect_distance(p, state["nfz"], state["nfz_mask"])], -1)
        into.append(torch.stack([rz, walls.lt(near).any(-1)]))

    def record(state: Any, action: Any) -> None:
        wish = alone(state)
        positions.append(state["position"].clone())
        changes.append(torch.linalg.vector_norm(action - wish, dim=-1))
        where(state, marks)
        speeds.append(speed(action))
        wishes.append(speed(wish))

    from uavlae.policies.greedy import GreedyPolicy

    greedy, greedy_positions, greedy_marks = GreedyPolicy(cfg), [], []

    def record_greedy(state: Any, _: Any) -> None:
        greedy_positions.append(state["position"].clone())
        where(state, greedy_marks)

    with torch.no_grad():
        flown = fly.fly_batch(fly.policy_of(module, meta, cfg, True), cfg, scenarios, seed=int(meta.get("eval_seed", 0)),
                              max_steps=meta.get("eval_max_steps"), on_step=record)
        by_greedy = fly.fly_batch(greedy.act, cfg, scenarios, seed=int(meta.get("eval_seed", 0)),
                                  max_steps=meta.get("eval_max_steps"), on_step=record_greedy)
    parts = [fly.scenario_tensors(d, cfg) for d in scenarios]
    scen = {k: torch.cat([p[k] for p in parts]) for k in ("bz", "bz_mask", "nfz", "nfz_mask")}
    lengths, landed = torch.tensor(flown["length"]), torch.tensor(flown["landed"])
    def places(marks: list[Any]) -> dict[str, Any]:
        m = torch.stack(marks)  # [T, 2, B]
        return {"rz": m[:, 0], "near_wall": m[:, 1]}

    g_pace = mission_pace(torch.stack(greedy_positions), torch.tensor(by_greedy["length"]),
                          torch.tensor(by_greedy["landed"]), places=places(greedy_marks))
    return {**stall_summary(torch.stack(positions), torch.stack(changes), lengths, landed,
                            [(scen["bz"], scen["bz_mask"]), (scen["nfz"], scen["nfz_mask"])], window),
            **mission_pace(torch.stack(positions), lengths, landed, places=places(marks)),
            # the actor's wished speed and the speed the filter let it fly, over the landed slots
            "landed_wish_speed_mean": landed_mean(torch.stack(wishes), lengths, landed),
            "landed_speed_mean": landed_mean(torch.stack(speeds), lengths, landed),
            "greedy_landed": int(sum(by_greedy["landed"])),
            **{f"greedy_{k}": v for k, v in g_pace.items() if k != "chunk"}}


# ---------------------------------------------------------------------------- the report


def meets(metrics: dict[str, float], ecr_ceiling: float | None) -> bool:
    """Whether pooled ``metrics`` meet every floor (and ECR no worse than ``ecr_ceiling``)."""
    for m, (op, bound) in FLOORS.items():
        v = metrics.get(m, math.nan)
        if not math.isfinite(v) or (v < bound if op == ">=" else v > bound):
            return False
    return ecr_ceiling is None or metrics.get("ECR", math.inf) <= ecr_ceiling


def _cells(episodes: list[dict[str, str]]) -> dict[tuple[str, str, str, str], list[dict[str, str]]]:
    cells: dict[tuple[str, str, str, str], list[dict[str, str]]] = defaultdict(list)
    for e in episodes:
        cells[(e["stage"], e["rung"], e["evaluation"], e["set"])].append(e)
    return cells


# the recipes a verdict runs (uavlae/conf/exp/<name>.yaml; make pilot-verdict PILOT_RECIPE=<name>)
RECIPES = ("pilot_mean", "pilot_drawn", "pilot_cruise")
# the ladder's order (the Makefile's RUNG_*); rungs not named here follow in the order recorded
LADDER = ("sac_world", "sac_ego", "sac_ego_filter", "sac_ego_filter_shaped", "sac_ego_filter_shaped_penalty",
          "sac_ego_filter_shaped_proposed", "sac_ego_filter_shaped_wish", "sac_ego_filter_shaped_teach",
          "sac_ego_filter_shaped_wish_teach", "sac_ego_filter_shaped_teach_all",
          "sac_ego_filter_shaped_wish_teach_all", "sac_ego_filter_shaped_teach_all_labels",
          "sac_ego_filter_shaped_teach_all_labels_strong",
          "sac_ego_filter_shaped_teach_all_labels_greedy", "sac_ego_filter_shaped_teach_all_labels_wide",
          "sac_ego_filter_shaped_teach_all_labels_wide_economy", "saclag_ego_shaped", "saclagln_ego_shaped",
          *RECIPES, "pilot_drawn_sharp", "pilot_drawn_penalty", "pilot_drawn_clear", "pilot_drawn_clearer",
          "pilot_drawn_reach", "pilot_drawn_reach_loose", "pilot_drawn_reach4",
          "pilot_drawn_cruise")


def _order(runs: list[dict[str, str]], stage: str) -> list[str]:
    """The rungs of a stage in the ladder's order."""
    rungs = list(dict.fromkeys(r["rung"] for r in runs if r["stage"] == stage))
    return sorted(rungs, key=lambda r: (LADDER.index(r) if r in LADDER else len(LADDER), rungs.index(r)))


def _time_to_pilot(curves: list[dict[str, str]], stage: str, rung: str, ecr: float | None) -> str:
    """Per seed, the first evaluation whose pilot (the actor alone, when unfiltered) meets every floor."""
    by_seed: dict[str, list[dict[str, str]]] = defaultdict(list)
    for c in curves:
        if c["stage"] == stage and c["rung"] == rung:
            by_seed[c["seed"]].append(c)
    hits = []
    for seed, rows in sorted(by_seed.items()):
        for c in sorted(rows, key=lambda r: int(float(r["frames"]))):
            vals = {m: float(c[m]) for m in METRICS if c.get(m) not in (None, "")}
            if meets(vals, ecr):
                wall = c.get("train_wall_s")
                hits.append(f"seed {seed}: {int(float(c['frames'])):,} frames"
                            + (f", {float(wall) / 60:.0f} min" if wall not in (None, "") else ""))
                break
    return "; ".join(hits) if hits else f"not reached ({len(by_seed)} runs)"


def _best_on_the_way(curves: list[dict[str, str]], stage: str, rung: str) -> str:
    """Per seed, the evaluation during training with the highest DCR + SLR - CR - RVR of the pilot
    (what ``trainer.keep_best`` keeps; chosen on this set, so optimistic for it)."""
    by_seed: dict[str, list[dict[str, str]]] = defaultdict(list)
    for c in curves:
        if c["stage"] == stage and c["rung"] == rung and all(c.get(m) not in (None, "") for m in ("DCR", "SLR", "CR", "RVR")):
            by_seed[c["seed"]].append(c)
    out = []
    for seed, rows in sorted(by_seed.items()):
        best = max(rows, key=lambda c: (selection_score({m: float(c[m]) for m in ("DCR", "SLR", "CR", "RVR")}),
                                        -int(float(c["frames"]))))
        out.append(f"seed {seed}: {float(best['DCR']):.3f} / {float(best['SLR']):.3f} at {int(float(best['frames'])):,}")
    return "; ".join(out)


def _drawn(runs: list[dict[str, str]], stage: str) -> set[str]:
    """The rungs of a stage whose runs fly their own evaluations by draws (trainer.eval_actor=sample)."""
    return {r["rung"] for r in runs if r["stage"] == stage and r.get("eval_actor") == "sample"}


def _flown(evaluation: str, by_draws: bool) -> str:
    """What flew in a cell: a drawn rung's own evaluations (pilot, alone) are its draws."""
    return FLOWN[f"{evaluation}_sample" if by_draws and evaluation in ("pilot", "alone") else evaluation]


def _table(stage: str, runs: list[dict[str, str]], cells: dict, curves: list[dict[str, str]], which: str,
           ecr: float | None) -> list[str]:
    ttp, best = "time to a pilot", "best evaluation: DCR / SLR at frames"
    columns = ["rung", "seeds", "flown", *METRICS, "filter acts (train / eval)", "wall (min)",
               *([ttp, best] if which == "selection" else [])]
    rows = []
    drawn = _drawn(runs, stage)
    for rung in _order(runs, stage):
        rr = [r for r in runs if r["stage"] == stage and r["rung"] == rung]
        wall = sum(float(r["wall_s"] or 0) for r in rr) / max(len(rr), 1) / 60
        share = " / ".join(f"{float(v):.3f}" if v not in (None, "") else "–"
                           for v in (rr[0].get("train_intervention"), rr[0].get("eval_intervention")))
        for evaluation in FLOWN:
            episodes = cells.get((stage, rung, evaluation, which))
            if not episodes:
                continue
            g = grid_from_rows(episodes)
            pilot = evaluation == "pilot"
            rows.append({"rung": rung, "seeds": " ".join(map(str, g.seeds)),
                         "flown": _flown(evaluation, rung in drawn),
                         **{m: fmt_interval(*interval(g, m)) for m in METRICS},
                         "filter acts (train / eval)": share if pilot else "", "wall (min)": f"{wall:.0f}",
                         ttp: _time_to_pilot(curves, stage, rung, ecr) if pilot and which == "selection" else "",
                         best: _best_on_the_way(curves, stage, rung) if pilot and which == "selection" else ""})
    return markdown_table(rows, columns)


# the rung each one changes, where that is not the one above it in LADDER (the ladder branches:
# teaching and the Lagrangian build on other rungs than the one listed before them)
PARENT = {"sac_ego_filter_shaped_wish": "sac_ego_filter_shaped", "sac_ego_filter_shaped_teach": "sac_ego_filter_shaped",
          "sac_ego_filter_shaped_wish_teach": "sac_ego_filter_shaped_teach",
          "sac_ego_filter_shaped_teach_all": "sac_ego_filter_shaped_teach",
          "sac_ego_filter_shaped_wish_teach_all": "sac_ego_filter_shaped_teach_all",
          "sac_ego_filter_shaped_teach_all_labels": "sac_ego_filter_shaped_teach_all",
          "sac_ego_filter_shaped_teach_all_labels_strong": "sac_ego_filter_shaped_teach_all_labels",
          "sac_ego_filter_shaped_teach_all_labels_greedy": "sac_ego_filter_shaped_teach_all_labels",
          "sac_ego_filter_shaped_teach_all_labels_wide": "sac_ego_filter_shaped_teach_all_labels",
          "sac_ego_filter_shaped_teach_all_labels_wide_economy": "sac_ego_filter_shaped_teach_all_labels_wide",
          "saclag_ego_shaped": "sac_ego_filter_shaped",
          "pilot_drawn": "sac_ego_filter_shaped_wish_teach_all",
          "pilot_drawn_sharp": "pilot_drawn", "pilot_drawn_penalty": "pilot_drawn", "pilot_drawn_clear": "pilot_drawn",
          "pilot_drawn_clearer": "pilot_drawn_clear", "pilot_drawn_reach": "pilot_drawn",
          "pilot_drawn_reach_loose": "pilot_drawn_reach", "pilot_drawn_reach4": "pilot_drawn_reach",
          "pilot_drawn_cruise": "pilot_drawn"}


def _paired(a: list[dict[str, str]] | None, b: list[dict[str, str]] | None) -> tuple[list[int], dict[str, str]] | None:
    """The seeds two cells share and each metric's difference a − b paired on them (formatted,
    keyed ``Δ<metric>``); None when either cell is missing or they share no seed."""
    if not a or not b:
        return None
    ga, gb = grid_from_rows(a), grid_from_rows(b)
    both = [s for s in ga.seeds if s in gb.seeds]
    if not both:
        return None
    ga, gb = ga.take(both), gb.take(both)
    return both, {f"Δ{m}": fmt_interval(*difference(ga, gb, m)) for m in METRICS}


def _ladder(stage: str, runs: list[dict[str, str]], cells: dict, which: str) -> list[str]:
    """Paired differences of each rung against the rung it changes (:data:`PARENT`, else the
    one above it), for the pilot and the actor alone."""
    rungs = _order(runs, stage)
    drawn = _drawn(runs, stage)
    rows = []
    for previous, rung in zip(rungs, rungs[1:]):
        above = PARENT[rung] if PARENT.get(rung) in rungs else previous
        for evaluation in ("pilot", "alone"):
            theirs = cells.get((stage, above, evaluation, which))
            # a rung that flies draws is paired with its parent's networks flown by draws where
            # they were (make pilot-sampling), so that the difference is the rung's change alone
            if rung in drawn and above not in drawn and (stage, above, f"{evaluation}_sample", which) in cells:
                theirs = cells[(stage, above, f"{evaluation}_sample", which)]
            deltas = _paired(cells.get((stage, rung, evaluation, which)), theirs)
            if deltas is not None:
                rows.append({"rung vs the one it changes": f"{rung} vs {above}",
                             "flown": _flown(evaluation, rung in drawn), **deltas[1]})
    return markdown_table(rows, ["rung vs the one it changes", "flown", *(f"Δ{m}" for m in METRICS)])


def _draws(stage: str, runs: list[dict[str, str]], cells: dict, which: str) -> list[str]:
    """Paired differences of each rung's networks flown by draws from their policy against the
    same networks flown by their mean action (the same seeds and scenarios)."""
    rows = []
    for rung in _order(runs, stage):
        for drawn, mean in (("pilot_sample", "pilot"), ("alone_sample", "alone")):
            deltas = _paired(cells.get((stage, rung, drawn, which)), cells.get((stage, rung, mean, which)))
            if deltas is not None:
                rows.append({"rung": rung, "seeds": " ".join(map(str, deltas[0])),
                             "draw − mean": "through the filter" if mean == "pilot" else "actor alone", **deltas[1]})
    return markdown_table(rows, ["rung", "seeds", "draw − mean", *(f"Δ{m}" for m in METRICS)])


def build(records: Path) -> Path:
    """``report.md`` in ``records`` from its CSV files (module doc)."""
    runs, episodes, curves = (read_rows(records / n) for n in ("runs.csv", "episodes.csv", "curves.csv"))
    cells = _cells(episodes)
    lines = ["# The pilot study", "",
             "Generated by `python -m uavlae.experiments.pilot report results/pilot` from the CSV records "
             "beside it (`make pilot-records` writes them from the runs). SPEC's world (`env=default`), "
             "B = 64, 0.25 gradient steps a frame, compiled env. Each rung changes one ingredient of the "
             "rung named beside it in the differences (uavlae/experiments/README.md lists the ladder's keys).", "",
             f"Intervals: {METHOD_NAME.format(n=2000)}. Differences are paired on the seeds both rungs ran "
             "and on the same scenarios.", "",
             "Floors of a deployable pilot: " + ", ".join(f"{m} {op} {b}" for m, (op, b) in FLOORS.items())
             + ", ECR no worse than the greedy heuristic's on the same scenarios.", ""]
    refs = sorted({(k[1], k[3]) for k in cells if k[0] == "references"}, key=lambda k: (k[1], k[0]))
    for which in SETS:
        rows = [r for r, w in refs if w == which]
        if rows:
            lines += [f"## References on the {SET_NAMES[which]} set", "",
                      "Flown once each (no learning; `python -m uavlae.experiments.pilot references`): the greedy "
                      "heuristic, the global planner, uniform random (and through the filter), and the follower of "
                      "the planner's geodesic direction (`env=shaped_geodesic_soft`'s column; what planner knowledge "
                      "buys, not a pilot) alone and through the filter.", "",
                      "| policy | " + " | ".join(METRICS) + " |", "|---|" + "---|" * len(METRICS)]
            for rung in rows:
                g = grid_from_rows(cells[("references", rung, "alone", which)])
                lines.append(f"| {rung} | " + " | ".join(fmt_interval(*interval(g, m)) for m in METRICS) + " |")
            lines.append("")
    stages = [s for s in dict.fromkeys(r["stage"] for r in runs) if s != "references"]
    for stage in stages:
        ref = {ev: cells.get((stage, _order(runs, stage)[0], ev, "selection")) for ev in ("heuristic", "random")}
        # the ECR floor is the greedy heuristic's: the references' copy where flown (a run taught by
        # the planner flies the planner as its own heuristic baseline), else the run's baseline
        flown = cells.get(("references", "greedy", "alone", "selection")) or ref["heuristic"]
        ecr = interval(grid_from_rows(flown), "ECR")[0] if flown else None
        for which, title in SET_TITLES.items():
            if not any(k[0] == stage and k[3] == which for k in cells):
                continue
            lines += [f"## {stage}: {title}", "", *_table(stage, runs, cells, curves, which, ecr), ""]
            if which == "selection":
                grids = {ev: grid_from_rows([{**r, "seed": 0} for r in rows if r["seed"] == rows[0]["seed"]])
                         for ev, rows in ref.items() if rows}
                lines += ["References on the same scenarios (flown in every run; the first rung's copy; `heuristic` is "
                          "the run's own baseline: the greedy heuristic, or the planner in a run taught by it, as "
                          "`+exp=pilot`):", "",
                          *markdown_table([{"policy": ev, **{m: fmt_interval(*interval(g, m)) for m in METRICS}}
                                           for ev, g in grids.items()], ["policy", *METRICS]), ""]
            moved = _ladder(stage, runs, cells, which)
            if len(moved) > 2:  # more than the header: the stage has a rung to compare with
                lines += [f"### {stage}: what each ingredient moved ({which})", "", *moved, ""]
            drawn = _draws(stage, runs, cells, which)
            if len(drawn) > 2:
                lines += [f"### {stage}: a draw from the policy against its mean action ({which})", "",
                          "The same networks (each run's end) flown by draws from their tanh-normal policy "
                          "(`trainer.eval_actor=sample`, `make pilot-sampling`) minus flown by their mean action, "
                          "paired on seeds and scenarios:", "", *drawn, ""]
        if stage == "verdict":  # each recipe's gate, as its model card would state it
            for rung in _order(runs, stage):
                seeds = sorted(int(r["seed"]) for r in runs if r["stage"] == stage and r["rung"] == rung)
                for which in ("heldout", "confirm"):
                    gate = _gate(cells, stage, rung, seeds, which, heading="###")
                    if gate:
                        gate[0] = gate[0].replace("### The gate", f"### verdict, {rung}: the gate")
                        lines += gate
    target = records / "report.md"
    write_text(target, "\n".join(lines) + "\n")
    return target


# ---------------------------------------------------------------------------- the model card

GUARANTEE = (
    "**What the filter guarantees** (docs/model.md §10). Hovering is always admissible, so whatever "
    "the actor proposes: no building collision, no no-fly-zone entry, no boundary exit and no RZ "
    "speeding, under the world's own motion model. **What it does not.** Other UAVs are avoided only "
    "while every one that could reach the DCU within the slot is perceived (within 20 m at the slot's "
    "start), keeps its velocity of the last slot (or flies at most v_max, where a turn-proof candidate "
    "exists), and some candidate keeps clear: a UAV that redraws its velocity or turns at a wall, or two "
    "converging with no safe candidate left, can still collide. The filter does not plan: it can hold "
    "the DCU short of its target, and it knows nothing of energy or time.")


def _pooled_row(episodes: list[dict[str, str]], seeds: list[int] | None = None) -> dict[str, str]:
    g = grid_from_rows([e for e in episodes if seeds is None or int(e["seed"]) in seeds])
    return {m: fmt_interval(*interval(g, m)) for m in METRICS}


def _span(values: list[float]) -> str:
    lo, hi = f"{min(values):.0f}", f"{max(values):.0f}"
    return lo if lo == hi else f"{lo}-{hi}"


VERDICT_SEEDS = 5  # the gate is judged on the mean over this many verdict seeds


def _gate(cells: dict, stage: str, rung: str, seeds: list[int], which: str = "heldout",
          heading: str = "##") -> list[str]:
    """The gate on ``which`` set: each floor against the pilot's pooled metric (the mean over
    seeds and scenarios), ECR against the greedy heuristic's on the same scenarios, and whether
    the actor alone learned (its DCR and SLR intervals above uniform random's); then one line
    naming what is missed. Fewer seeds than the verdict's five make it provisional."""
    pilot, alone = (cells.get((stage, rung, ev, which)) for ev in ("pilot", "alone"))
    greedy, rand = (cells.get(("references", ref, "alone", which)) for ref in ("greedy", "random"))
    if not pilot:
        return []
    g = grid_from_rows(pilot)
    rows, missed = [], []
    for m, (op, bound) in FLOORS.items():
        v = interval(g, m)[0]
        ok = math.isfinite(v) and (v >= bound if op == ">=" else v <= bound)
        rows.append({"floor": f"pilot {m} {op} {bound}", "measured": f"{v:.3f}", "met": "yes" if ok else "no"})
        missed += [] if ok else [f"{m} {v:.3f}"]
    if greedy:
        v, ceiling = interval(g, "ECR")[0], interval(grid_from_rows(greedy), "ECR")[0]
        ok = v <= ceiling
        rows.append({"floor": f"pilot ECR <= greedy's {ceiling:.3f}", "measured": f"{v:.3f}", "met": "yes" if ok else "no"})
        missed += [] if ok else [f"ECR {v:.3f} against greedy's {ceiling:.3f}"]
    if alone and rand:
        ga, gr = grid_from_rows(alone), grid_from_rows(rand)
        for m in ("DCR", "SLR"):
            (v, lo, _), (_, _, rhi) = interval(ga, m), interval(gr, m)
            ok = lo > rhi
            rows.append({"floor": f"actor alone {m} interval above random's (upper {rhi:.3f})",
                         "measured": f"lower {lo:.3f}", "met": "yes" if ok else "no"})
            missed += [] if ok else [f"the actor alone's {m} (lower {lo:.3f}, random's upper {rhi:.3f})"]
    split = _energy_split(pilot, greedy)
    head = (f"Judged on {len(seeds)} of the {VERDICT_SEEDS} verdict seeds: provisional until all have run. "
            if len(seeds) < VERDICT_SEEDS else "")
    verdict = ("**Gate met.**" if not missed else "**Gate not met**: " + "; ".join(missed) + ".")
    return [f"{heading} The gate ({SET_NAMES[which]} set)", "", head + verdict, "",
            *markdown_table(rows, ["floor", "measured", "met"]), "", *([split, ""] if split else [])]


def _energy_split(pilot: list[dict[str, str]], greedy: list[dict[str, str]] | None) -> str:
    """Where the pilot's ECR goes: the share spent in episodes that did not land (they fly on to
    T_max or end early), and the mean energy of a landed mission against the greedy heuristic's."""
    def landed(rows: list[dict[str, str]]) -> list[dict[str, str]]:
        return [r for r in rows if cell_true(r["landed"])]

    total = sum(float(r["energy_total"]) for r in pilot)
    used = sum(float(r["energy_used"]) for r in pilot)
    ok = landed(pilot)
    if not total or not ok:
        return ""
    lost = used - sum(float(r["energy_used"]) for r in ok)
    text = (f"Where the pilot's ECR ({used / total:.3f}) goes: {lost / total:.3f} of it in the "
            f"{1 - len(ok) / len(pilot):.1%} of episodes that did not land; a landed mission used "
            f"{sum(float(r['energy_used']) for r in ok) / len(ok) / 1000:.1f} kJ on average")
    g_ok = landed(greedy or [])
    if g_ok:
        text += f", the greedy heuristic's {sum(float(r['energy_used']) for r in g_ok) / len(g_ok) / 1000:.1f} kJ"
    return text + "."


def _stalls_line(found: dict[str, Any]) -> str:
    if not found["unlanded"]:
        return (f"Where the committed pilot stops short (`python -m uavlae.experiments.pilot stalls`, `{found['actor']}` "
                f"on `{found['scenario']}`): nowhere; every one of its {found['episodes']} episodes landed.")
    return (f"Where the committed pilot stops short (`python -m uavlae.experiments.pilot stalls`, `{found['actor']}` on "
            f"`{found['scenario']}`): of its {found['unlanded']} episodes of {found['episodes']} that did not land, "
            f"{found['unlanded_at_obstacle']} ended within {STALL_NEAR_M:.0f} m of a building or no-fly zone, "
            f"{found['unlanded_held']} of them held there (under {STALL_STILL_M:.0f} m of net motion in their last "
            f"{found['window']} slots). There the filter changed the actor's wish by {found['unlanded_filter_change_median']:.2f} "
            f"m/s (median over those episodes), against {found['landed_filter_change_mean']:.2f} m/s on average in the "
            "landed flights" + (": the actor keeps asking to fly through the obstacle and the filter keeps it out."
                                if found["unlanded_filter_change_median"] > 2 * found["landed_filter_change_mean"] else "."))


def _full_speed_line(found: dict[str, Any], greedy_ecr: float | None = None) -> str:
    """The card's sentence from ``full_speed.json`` (``make pilot-full-speed``): the committed
    pilot as it flies against its wish flown at v_max through its filter, on the same scenarios;
    ``greedy_ecr``: the greedy heuristic's pooled ECR there, when the records hold it."""
    a, b = found["as_flown"], found["at_full_speed"]
    text = (f"At full speed (`make pilot-full-speed`, a diagnosis and not the pilot: the actor's wish flown in its "
            f"direction at v_max, then through its filter, on `{found['set']}`): ECR {a['ECR']:.3f} as it flies, "
            f"{b['ECR']:.3f} at full speed; DCR {a['DCR']:.3f} / {b['DCR']:.3f}, SLR {a['SLR']:.3f} / {b['SLR']:.3f}, "
            f"CR {a['CR']:.3f} / {b['CR']:.3f}")
    if greedy_ecr is None:
        return text + "."
    gap = a["ECR"] - greedy_ecr
    share = (a["ECR"] - b["ECR"]) / gap if gap > 0 else math.nan
    return (text + f". Greedy flies ECR {greedy_ecr:.3f} there: the wished speed costs "
            + (f"{share:.0%} of the pilot's energy above greedy's." if math.isfinite(share) else "nothing above greedy's."))


def _pace_line(found: dict[str, Any]) -> str:
    """Where the landed missions' time went, against the greedy heuristic's on the same scenarios."""
    return (f"Its landed missions took {found['landed_slots_mean']:.0f} slots on average (greedy's "
            f"{found['greedy_landed_slots_mean']:.0f}): a path of {found['landed_path_m_mean']:.0f} m (greedy's "
            f"{found['greedy_landed_path_m_mean']:.0f}) at {found['landed_m_per_slot']:.1f} m a slot (greedy's "
            f"{found['greedy_landed_m_per_slot']:.1f}), {found['landed_held_slots_mean']:.0f} slots of them held "
            f"(chunks of {found['chunk']} slots with under {STALL_STILL_M:.0f} m of net motion; greedy's "
            f"{found['greedy_landed_held_slots_mean']:.0f}). A slot costs 294-337 J whatever the DCU does, so the "
            "energy of a mission is its slots." + _pace_parts(found))


def _pace_parts(found: dict[str, Any]) -> str:
    """Where the pace went, where ``stalls`` recorded it: over residential zones (speed limit 5
    m/s), within d_min of a building or NFZ, and elsewhere; and the actor's wished speed against
    the one the filter let it fly."""
    if "landed_near_wall_slots_mean" not in found:
        return ""

    def spent(prefix: str, name: str) -> str:
        n, pace = found[f"{prefix}landed_{name}_slots_mean"], found[f"{prefix}landed_{name}_m_per_slot"]
        return f"{n:.0f} at {pace:.1f} m a slot" if math.isfinite(pace) else "none"

    def part(name: str) -> str:
        return f"{spent('', name)} (greedy: {spent('greedy_', name)})"

    out = (f" Of those slots, {part('rz')} start over a residential zone (limit 5 m/s), {part('near_wall')} "
           f"within 5 m of a building or no-fly zone, and {part('elsewhere')} elsewhere.")
    if "landed_wish_speed_mean" in found:
        out += (f" Its actor wishes {found['landed_wish_speed_mean']:.1f} m/s on average over those slots and the "
                f"filter lets it fly {found['landed_speed_mean']:.1f}.")
    return out


def card(records: Path, recipe: Path, stage: str = "verdict", rung: str = "pilot_drawn",
         pilot_file: str = "results/pilot/pilot.pt2", committed_seed: int = 0) -> Path:
    """``README.md`` in ``records``: the committed pilot's model card, from the CSV records and
    the recipe file alone: the recipe and its commit, frames and wall clock, the five metrics of
    the pilot and of the actor alone pooled over every seed (intervals) and for the committed
    seed (what ``uavlae.fly --all`` reproduces), the references on the same scenarios, the floors,
    and what the filter guarantees."""
    runs = [r for r in read_rows(records / "runs.csv") if r["stage"] == stage and r["rung"] == rung]
    if not runs:
        raise InputError(f"{records / 'runs.csv'} holds no finished run of stage {stage!r}, rung {rung!r}: "
                         "run the verdict (make pilot-verdict) and make pilot-records first")
    cells = _cells(read_rows(records / "episodes.csv"))
    seeds = sorted(int(r["seed"]) for r in runs)
    if committed_seed not in seeds:
        raise InputError(f"the committed seed {committed_seed} has no finished {stage} run (seeds {seeds})")
    frames = sorted({int(float(r["frames"])) for r in runs})
    walls = [float(r["wall_s"] or 0) / 60 for r in runs]
    commits = sorted({r.get("commit", "") for r in runs if r.get("commit")})
    lines = [f"# The committed pilot: `{pilot_file}`", "",
             f"Generated by `python -m uavlae.experiments.pilot card results/pilot` from the records beside it "
             f"(`make pilot-records`) and the recipe `{recipe.as_posix()}`.", "",
             "The pilot is a learned actor and the safety filter in one exported program: "
             f"`python -m uavlae.fly --actor {pilot_file} --scenario <set> --all` flies every scenario of a set "
             "and prints the five metrics as JSON on its last line; `--no-filter` flies the actor alone.", "",
             "## Recipe", "", "```yaml", recipe.read_text().rstrip("\n"), "```", "",
             f"Seed {committed_seed} is the committed pilot, fixed before the runs. Trained at "
             f"{' / '.join(f'{f:,}' for f in frames)} frames on seeds {' '.join(map(str, seeds))}, "
             f"{_span(walls)} min of wall clock a run (one job a core, 2-core CPU), "
             f"from commit {', '.join(commits) or 'unrecorded'}.", "",
             *([("Each seed's pilot is its best evaluation on the selection set (`trainer.keep_best`: "
                 "DCR + SLR - CR - RVR), taken at " + ", ".join(
                     f"seed {r['seed']}: {int(float(r['best_frames'])):,}" for r in sorted(runs, key=lambda r: int(r["seed"])))
                 + " frames; the held-out set judges it, and the selection-set rows below are each run's last "
                 "evaluation."), ""] if all(r.get("best_frames") not in (None, "") for r in runs) else []),
             "## Metrics", "",
             f"Intervals: {METHOD_NAME.format(n=2000)}. Floors of a deployable pilot: "
             + ", ".join(f"{m} {op} {b}" for m, (op, b) in FLOORS.items())
             + ", ECR no worse than the greedy heuristic's on the same scenarios.", ""]
    for which, title in (("heldout", "the 256 held-out scenarios (results/pilot/heldout_set_256.json)"),
                         ("confirm", "the 256 scenarios of the confirmation set (results/pilot/confirm_set_256.json)"),
                         ("selection", "the selection set (results/eval_set_32.json)")):
        rows = []
        for evaluation, flown in (("pilot", "actor + filter"), ("alone", "actor alone")):
            eps = cells.get((stage, rung, evaluation, which))
            if not eps:
                continue
            rows.append({"policy": f"pilot, {flown}", "seeds": " ".join(map(str, seeds)), **_pooled_row(eps)})
            if len(seeds) > 1:
                rows.append({"policy": f"pilot, {flown}", "seeds": str(committed_seed),
                             **_pooled_row(eps, [committed_seed])})
        for ref in ("greedy", "planner", "random"):
            eps = cells.get(("references", ref, "alone", which))
            if eps:
                rows.append({"policy": ref, "seeds": "–", **_pooled_row(eps)})
        if rows:
            lines += [f"On {title}:", "", *markdown_table(rows, ["policy", "seeds", *METRICS]), ""]
    for which in ("heldout", "confirm"):
        lines += _gate(cells, stage, rung, seeds, which)
    if (records / "stalls.json").exists():
        found = read_json(records / "stalls.json")
        lines += [_stalls_line(found), "", *([_pace_line(found), ""] if "landed_m_per_slot" in found else [])]
    if (records / "full_speed.json").exists():
        found = read_json(records / "full_speed.json")
        which = next((k for k, v in SETS.items() if Path(v).name == Path(found["set"]).name), None)
        g = cells.get(("references", "greedy", "alone", which)) if which else None
        greedy = (sum(float(r["energy_used"]) for r in g) / sum(float(r["energy_total"]) for r in g)) if g else None
        lines += [_full_speed_line(found, greedy), ""]
    lines += ["## Safety", "", GUARANTEE, ""]
    target = records / "README.md"
    write_text(target, "\n".join(lines) + "\n")
    return target


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(prog="python -m uavlae.experiments.pilot", description=__doc__.split("\n\n")[0])
    sub = p.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("records", help="the study's runs -> CSV records")
    r.add_argument("runs", type=Path)
    r.add_argument("--out", type=Path, default=Path("results/pilot"))
    f = sub.add_parser("references", help="fly the reference policies on the selection, held-out and confirmation sets")
    f.add_argument("--out", type=Path, default=Path("results/pilot"))
    f.add_argument("--set", choices=list(SETS), action="append", dest="sets",
                   help="fly only this set (repeatable; default every set): the others' records are kept")
    rep = sub.add_parser("report", help="CSV records -> report.md")
    rep.add_argument("records", type=Path, nargs="?", default=Path("results/pilot"))
    c = sub.add_parser("card", help="CSV records + the recipe -> the committed pilot's model card (README.md)")
    c.add_argument("records", type=Path, nargs="?", default=Path("results/pilot"))
    c.add_argument("--recipe", type=Path, default=Path("uavlae/conf/exp/pilot_drawn.yaml"),
                   help="the committed recipe's file (+exp=pilot composes it)")
    c.add_argument("--rung", default="pilot_drawn", help="the verdict runs' method (make pilot-verdict PILOT_RECIPE=...)")
    st = sub.add_parser("stalls", help="where an exported pilot's unlanded episodes end (-> OUT/stalls.json)")
    st.add_argument("--actor", type=Path, default=Path("results/pilot/pilot.pt2"))
    st.add_argument("--scenario", type=Path, default=SETS["heldout"])
    st.add_argument("--out", type=Path, default=Path("results/pilot"))
    args = p.parse_args(argv)
    if args.cmd == "stalls":
        found = {"actor": args.actor.as_posix(), "scenario": args.scenario.as_posix(), **stalls(args.actor, args.scenario)}
        write_text(args.out / "stalls.json", json.dumps(found, indent=1) + "\n")
        print(json.dumps(found))
    elif args.cmd == "card":
        print(card(args.records, args.recipe, rung=args.rung))
    elif args.cmd == "records":
        print(json.dumps(write_records(args.runs, args.out)))
    elif args.cmd == "references":
        print(json.dumps(write_references(args.out, {k: SETS[k] for k in args.sets} if args.sets else None)))
    else:
        print(build(args.records))


if __name__ == "__main__":
    sys.exit(command(main))
