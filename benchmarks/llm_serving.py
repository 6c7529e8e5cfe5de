"""Answered calls/s of any OpenAI-compatible endpoint at 1, 8 and 64 requests in flight: what
SAC+LLM's advice will cost there, before a run.

    python benchmarks/llm_serving.py                                   (the local server; make bench-llm-serving)
    python benchmarks/llm_serving.py --llm openai_compatible --set base_url=http://gpu-box:8000/v1 model=NAME
    python benchmarks/llm_serving.py --llm deepseek --in-flight 1 8 --states 16   (export DEEPSEEK_API_KEY=...)

For each level n: a new advisor with ``llm.max_concurrency = n`` and the advice cache off sends
``max(n, --states)`` distinct, never-asked states (``example_states``, one map each) at once, so
n requests stay in flight until the last ones; answered/s = valid answers / wall clock. One
state is asked first and not timed (the server then holds the shared system prompt, as it does
through a run). The prompt, output format and sampling are the preset's (``--llm``, with
``--set key=value`` overrides). Without ``base_url`` the local server is started with as many
slots as the largest level (``server.n_parallel``) and the preset's thread count, and stopped at
the end. The row deadline and the request timeout are raised (``--row-deadline-s``: a timed-out
request asked again would count its work twice) and a failed row does not stop the
measurement (``max_failed_rows`` off): a level where calls queue for minutes is reported, with
its failures, as what it is. Per level: answered/s, failures, seconds per 1000 rows (what 1000 triggered rows cost
when the loop keeps n in flight), latency quantiles per call, tokens per call. Writes
``benchmarks/llm_serving.json`` with the machine; the API key is read from ``api_key_env`` and
never recorded.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from uavlae.files import dump_json  # noqa: E402
from uavlae.llm import LLMAdvisor, WorldLimits, example_states, make_llm_config  # noqa: E402
from uavlae.machine import describe_machine  # noqa: E402

# SPEC's world: the states are synthetic, their size is what matters
LIM = WorldLimits(x_size=500.0, y_size=500.0, v_max=10.0, v_limit=5.0, perception_radius=20.0,
                  landing=(475.0, 0.0, 500.0, 25.0), e_limit=8e5)


def _value(text: str):
    import yaml

    return yaml.safe_load(text)  # "8" -> 8, "null" -> None, "http://..." stays a string


def level(cfg, base_url: str | None, n: int, n_states: int, deadline_s: float) -> dict:
    # what is measured is the server: a slow level is reported (its failures counted), not stopped
    cfg_n = make_llm_config(cfg, max_concurrency=n, row_deadline_s=deadline_s, timeout_s=deadline_s,
                            max_failed_rows=None)
    states = example_states(n_states, LIM, seed=1000 + n)
    with LLMAdvisor(cfg_n, base_url=base_url) as adv:
        adv.advise_sync(example_states(1, LIM, seed=999))  # the system prompt into the server's cache
        adv.stats.reset()
        t0 = time.perf_counter()
        res = adv.advise_sync(states)
        wall = time.perf_counter() - t0
        snap = adv.stats.snapshot()
    ok = sum(r.ok for r in res)
    calls = max(snap["calls"], 1)
    return {"in_flight": n, "states": n_states, "answered": ok, "failed": n_states - ok, "wall_s": round(wall, 2),
            "answered_per_s": round(ok / wall, 3), "s_per_1000_rows": round(1000 * wall / max(ok, 1), 0),
            "http_calls": snap["calls"], "ask_again": snap["ask_again"],
            "latency_p50_s": round(snap["latency_p50_s"], 3), "latency_p95_s": round(snap["latency_p95_s"], 3),
            "prompt_tokens_per_call": round(snap["prompt_tokens"] / calls, 1),
            "cached_prompt_tokens_per_call": round(snap["cached_prompt_tokens"] / calls, 1),
            "completion_tokens_per_call": round(snap["completion_tokens"] / calls, 1)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--llm", default="local", help="preset in conf/llm/ or a YAML file")
    ap.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE", help="llm settings, e.g. base_url=... model=...")
    ap.add_argument("--in-flight", nargs="+", type=int, default=[1, 8, 64])
    ap.add_argument("--states", type=int, default=4, help="states per level at least (a level sends max(n, this))")
    ap.add_argument("--row-deadline-s", type=float, default=3600.0,
                    help="llm.row_deadline_s here: at 64 in flight on a small server one call takes minutes")
    ap.add_argument("--out", default=str(ROOT / "benchmarks" / "llm_serving.json"))
    args = ap.parse_args()
    overrides = {}
    for kv in args.set:
        key, eq, value = kv.partition("=")
        if not eq:
            raise SystemExit(f"--set takes KEY=VALUE, got {kv!r}")
        overrides[key] = _value(value)
    cfg = make_llm_config(args.llm, cache_mode="off", **overrides)
    top = max(args.in_flight)
    rows = []
    server_note = None
    if cfg.base_url is None:
        from contextlib import ExitStack

        import xllamacpp

        from uavlae.llm.server import local_server

        server = cfg.server.model_copy(update={"n_parallel": max(cfg.server.n_parallel, top)})
        server_note = {"xllamacpp": xllamacpp.__version__, **server.model_dump()}
        with ExitStack() as stack:
            srv = stack.enter_context(local_server(server))
            endpoint = f"the local server ({Path(srv.model_path).name}, {server.n_threads} thread(s), {server.n_parallel} slots)"
            for n in args.in_flight:
                rows.append(level(cfg, srv.base_url, n, max(n, args.states), args.row_deadline_s))
                print(json.dumps(rows[-1]), flush=True)
    else:
        endpoint = cfg.base_url
        for n in args.in_flight:
            rows.append(level(cfg, None, n, max(n, args.states), args.row_deadline_s))
            print(json.dumps(rows[-1]), flush=True)
    base = rows[0]["answered_per_s"] if rows and rows[0]["answered_per_s"] else None
    for r in rows:
        r["speedup_over_first"] = round(r["answered_per_s"] / base, 2) if base else None
    out = {"benchmark": "llm_serving", "measured_at": time.strftime("%Y-%m-%d %H:%M:%S %Z"),
           "command": "python benchmarks/llm_serving.py " + " ".join(sys.argv[1:]),
           "endpoint": endpoint, "model": cfg.model, "response_format": cfg.response_format,
           "observation": cfg.observation, "max_tokens": cfg.max_tokens, "local_server": server_note,
           "machine": describe_machine(), "levels": rows}
    dump_json(Path(args.out), out)
    for r in rows:
        print(f"{r['in_flight']:>3} in flight: {r['answered_per_s']:.3f} answered/s ({r['answered']}/{r['states']}), "
              f"{r['s_per_1000_rows']:.0f} s per 1000 rows, p50 {r['latency_p50_s']:.2f} s a call")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
