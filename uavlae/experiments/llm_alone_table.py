"""The LLM alone's measured run (``make llm-alone``) as ``results/llm_alone.json`` and ``.md``.

Reads a ``+exp=llm`` run folder (``final_metrics.json``, ``summary.json``, ``config.json``,
the scored episodes' ``episodes.csv``) and writes the five metrics over the scored episodes,
each episode's length, decisions and outcome, the LLM's cost, and, for reference, the greedy
heuristic flown on the same scenarios with the same seeds (one scenario per chunk, as the run).

    python -m uavlae.experiments.llm_alone_table runs/llm_alone --out results/llm_alone --command "make llm-alone"
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path
from typing import Any

from uavlae.envs.metrics import PAPER_METRICS
from uavlae.experiments.reporting import markdown_table, read_json, read_rows, write_text
from uavlae.files import dump_json, train_eval_dir
from uavlae.machine import describe_machine

EPISODE_COLUMNS = ("row", "length", "llm_calls", "llm_fallbacks", "collided", "landed", "boundary_exit",
                   "rz_speeding", "data_collected", "data_total", "energy_used")
# the Markdown tables' headings: what the LLM's calls cost over every invocation, and each episode
COST_COLUMNS = ("decisions", "in scored episodes", "HTTP calls", "cache hits", "ask-again", "failures (fallback)",
                "prompt tokens", "completion tokens", "wall s", "decisions/s", "latency p50 s", "p95 s")
EPISODE_TABLE = ("scenario", "length", "decisions", "fallbacks", "collided", "landed", "left the area", "data",
                 "energy J")


def heuristic_on(run_dir: Path, cfg: dict[str, Any], rows: list[int]) -> dict[str, float]:
    """The greedy heuristic on the run's scored scenarios ``rows``, chunked and seeded as the run
    (the chunks up to the last of them are flown, so every chunk keeps its seed and rows)."""
    import torch
    from omegaconf import OmegaConf

    from uavlae.envs import make_env_config
    from uavlae.envs.metrics import aggregate
    from uavlae.envs.scenario import load_scenarios
    from uavlae.evaluate import eval_set_path, make_evaluation
    from uavlae.factories import HeuristicGroup, make_heuristic

    c = OmegaConf.create(cfg)
    # the run's chunks and seeds, none of its call budget or shards: the heuristic flies them all here
    for key, value in (("trainer.llm_call_budget", None), ("trainer.eval_shards", 1), ("trainer.eval_shard", 0),
                       ("trainer.eval_plots", 0)):
        OmegaConf.update(c, key, value, merge=False)
    env_cfg = make_env_config(c.env)
    tr = c.trainer
    scenarios = load_scenarios(eval_set_path(run_dir, tr.get("eval_set")))  # a sweep's shared set, else the run's own
    chunk = int(tr.eval_chunk or len(scenarios))
    scenarios = scenarios[: (max(rows) // chunk + 1) * chunk]
    with tempfile.TemporaryDirectory() as tmp:
        flight = make_evaluation(c, env_cfg, scenarios, chunked=True).fly(make_heuristic(HeuristicGroup.of(c), env_cfg), tmp)
        records = flight.llm_alone["records"]
    keep = torch.isin(records["row"], torch.tensor(rows))
    return aggregate({k: v[keep] for k, v in records.items()})


def in_flight(run_dir: Path) -> list[dict[str, Any]]:
    """The episodes paused in flight, so far (not scored), one a progress file (shard): their
    scenario and slot, data and energy, events."""
    import torch

    out = []
    for file in sorted(train_eval_dir(run_dir, 0).glob("progress*.pt")):
        state = torch.load(file, map_location="cpu", weights_only=False)
        fl = state["in_flight"]
        if fl is None:
            continue
        k = fl["chunk"] if "chunk" in fl else state["next_chunk"]  # format 1 had chunks in order
        nxt, acc = fl["last_next"], fl["tracker"]["acc"]
        st = nxt.get("state")
        out.append({"scenario": int(k) * int(state["chunk"]), "slot": int(fl["step"]),
                    "position": [round(float(v), 1) for v in st.get("position")[0].tolist()],
                    "data_collected": float(st.get("data_collected")[0]), "data_total": float(st.get("data_total")[0]),
                    "energy_used": float(st.get("energy_used")[0]), "collided": bool(acc["collided"][0]),
                    "boundary_exit": bool(acc["boundary_exit"][0]), "rz_speeding": bool(acc["rz_speeding"][0])})
    return out


def build(run_dir: Path, command: str | None) -> dict[str, Any]:
    final = read_json(run_dir / "final_metrics.json")
    summary = read_json(run_dir / "summary.json")
    cfg = read_json(run_dir / "config.json")
    meta = read_json(run_dir / "meta.json") if (run_dir / "meta.json").is_file() else {}
    la = summary["llm_alone"]
    episodes = read_rows(train_eval_dir(run_dir, 0) / "episodes.csv")
    n = int(la["episodes_scored"])
    return {
        "what": "the LLM alone (+exp=llm): the local model decides every step; metrics over the scored episodes",
        "command": command or meta.get("command"),
        "run_command": meta.get("command"),
        "commit": (meta.get("git") or {}).get("commit"),
        "model": cfg["llm"]["model"],
        "view": {"view": cfg["llm"]["view"], "view_radius_m": cfg["llm"]["view_radius"]},
        "fallback": cfg["advisor"]["fallback"],
        "call_budget_per_invocation": la["budget"],
        "chunk": la["chunk"],
        "episodes_scored": n,
        "episodes_total": int(la["episodes_total"]),
        "complete": bool(la["complete"]),
        "in_flight_step": la.get("in_flight_step"),
        "in_flight_so_far": in_flight(run_dir),
        "metrics": {k: final.get(f"eval/{k}") for k in (*PAPER_METRICS, "boundary_exit_rate", "mean_length")},
        "heuristic_same_scenarios": ({k: v for k, v in heuristic_on(run_dir, cfg, [int(r["row"]) for r in episodes]).items()
                                      if k in (*PAPER_METRICS, "mean_length")} if episodes else None),
        "cost": la["cost"],
        "episodes": [{"scenario": int(r["row"]), **{k: r.get(k) for k in EPISODE_COLUMNS}} for r in episodes],
        "machine": describe_machine(),
    }


def markdown(res: dict[str, Any]) -> str:
    c = res["cost"]
    m, h = res["metrics"], res["heuristic_same_scenarios"]

    def f(v: Any) -> str:
        return "n/a" if v is None else f"{float(v):.3f}"

    lines = [
        "# The LLM alone (+exp=llm)",
        "",
        f"Command: `{res['command']}` (the run: `{res['run_command']}`). Model: {res['model']} on the local "
        f"xllamacpp server; view: {res['view']['view']} ({res['view']['view_radius_m']:g} m); failed answers: "
        f"{res['fallback']}. Machine: {res['machine']['cpu']}, {res['machine']['logical_cores']} logical cores, "
        f"load {res['machine']['load_average_1_5_15']} when the table was written (the machine is shared).",
        "",
        f"Scored: {res['episodes_scored']} of {res['episodes_total']} evaluation episodes (one scenario a chunk; "
        + (f"a call budget of {res['call_budget_per_invocation']} decisions an invocation"
           if res["call_budget_per_invocation"] != 0 else
           "the last invocation asked nothing and scored what every progress file holds, trainer.llm_call_budget=0")
        + ("" if res["complete"] else (
            f"; paused at slot {res['in_flight_step']} of the episode in flight" if res["in_flight_step"] is not None
            else "; paused before the next episode") + ": the same command continues") + "). Metrics cover finished episodes only.",
        "",
        *markdown_table([{"method": name, "episodes": res["episodes_scored"],
                          **{k: f(v[k]) for k in PAPER_METRICS}, "mean length": f(v["mean_length"])}
                         for name, v in (("llm", m), ("heuristic, same scenarios", h)) if v],
                        ["method", "episodes", *PAPER_METRICS, "mean length"]),
    ]
    for fl in res.get("in_flight_so_far") or []:
        lines += ["", f"Paused episode (scenario {fl['scenario']}, not scored), after {fl['slot']} slots: at "
                  f"{tuple(fl['position'])}, data {fl['data_collected']:.2f} of {fl['data_total']:.2f}, energy "
                  f"{fl['energy_used']:.0f} J, collided {fl['collided']}, left the area {fl['boundary_exit']}, "
                  f"RZ speeding {fl['rz_speeding']}."]
    lines += [
        "",
        "Cost over every invocation:",
        "",
        *markdown_table([{
            "decisions": int(c["calls"]), "in scored episodes": int(c["calls_scored"]),
            "HTTP calls": int(c.get("http_calls", 0)), "cache hits": int(c.get("cache_hits", 0)),
            "ask-again": int(c.get("ask_again", 0)), "failures (fallback)": int(c["fallbacks"]),
            "prompt tokens": int(c.get("prompt_tokens", 0)), "completion tokens": int(c.get("completion_tokens", 0)),
            "wall s": f"{c['wall_s']:.0f}", "decisions/s": f"{c['calls_per_s']:.2f}",
            "latency p50 s": f(c.get("latency_p50_s")), "p95 s": f(c.get("latency_p95_s"))}], COST_COLUMNS),
        "",
        "Episodes:",
        "",
        *markdown_table([{
            "scenario": e["scenario"], "length": e["length"], "decisions": e["llm_calls"], "fallbacks": e["llm_fallbacks"],
            "collided": e["collided"], "landed": e["landed"], "left the area": e["boundary_exit"],
            "data": f"{float(e['data_collected']):.2f} of {float(e['data_total']):.2f}",
            "energy J": f"{float(e['energy_used']):.0f}"} for e in res["episodes"]], EPISODE_TABLE),
    ]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("run_dir", type=Path)
    p.add_argument("--out", type=Path, default=Path("results/llm_alone"), help="path stem of the .json and .md")
    p.add_argument("--command", default=None, help="the command that reproduces it (default: the run's own)")
    a = p.parse_args(argv)
    if not (a.run_dir / "final_metrics.json").is_file():
        raise SystemExit(f"{a.run_dir}: no final_metrics.json (run `make llm-alone` first)")
    res = build(a.run_dir, a.command)
    dump_json(a.out.with_suffix(".json"), res)
    text = markdown(res)
    write_text(a.out.with_suffix(".md"), text)
    print(text)


if __name__ == "__main__":
    main()
