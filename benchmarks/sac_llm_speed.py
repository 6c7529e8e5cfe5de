"""SAC+LLM's training speed beside SAC's, at ``make run``'s settings, side by side in one run.

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/sac_llm_speed.py     (make bench-sac-llm)

Trains, in this process and one after another, with the Makefile's ``RUN_ARGS`` (1024 frames,
B = 16, 256 random frames, 8 evaluation episodes): ``+exp=sac``; ``+exp=sac_llm`` with the
paper's behaviour (``advisor.hold_steps=1``); ``+exp=sac_llm`` with ``advisor.hold_steps=4``
plus ``--hold4-args`` (e.g. the rounded cache key's setting); and ``+exp=sac`` again (this
machine's speed drifts within minutes; SAC's two runs bracket the LLM's). Every LLM run starts
with a new, empty cache file (cold: only what the run itself asked can hit) against one local
server started first (its start-up, reported as ``server_start_s``, is not in any run's time),
with the server settings of ``uavlae/conf/llm/local.yaml``. ``--overlap-ab`` adds the hold_steps=1
run with ``trainer.overlap_advice=false`` (the gradient steps before the requests, not while
they are in flight).

frames/s = frames / the loop's training time (collection, advice, gradient steps; the final
evaluation and the baselines excluded: ``summary.json``'s ``train_s``). Per LLM run: calls per
1000 frames (HTTP calls and rows asked), trigger rate, latency quantiles, tokens per call, the
time the loop waited for answers and the gradient steps' time run while requests were in flight
(``overlap_s``: what the overlap saved against running them before sending the requests).
Writes ``sac_llm_speed.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shlex
import sys
import tempfile
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def make_run_args() -> list[str]:
    """``RUN_ARGS`` as the Makefile sets it (one source for `make run` and this benchmark)."""
    m = re.search(r"^RUN_ARGS \?= (.*)$", (ROOT / "Makefile").read_text(), re.MULTILINE)
    if m is None:
        raise RuntimeError("no `RUN_ARGS ?= ...` line in the Makefile")
    return shlex.split(m.group(1))


def train(exp: str, run_dir: Path, args: list[str]) -> dict:
    from hydra import compose, initialize_config_dir

    from uavlae.factories import CONF_DIR
    from uavlae.train import run

    overrides = [f"+exp={exp}", f"run_dir={run_dir}", *args, "trainer.progress_bar=false",
                 "trainer.baselines=false", "logger.wandb.mode=disabled"]
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        cfg = compose("config", overrides=overrides)
    t0 = time.perf_counter()
    final = run(cfg)
    wall = time.perf_counter() - t0
    s = json.loads((run_dir / "summary.json").read_text())
    row = {
        "overrides": [o for o in overrides if not o.startswith(("run_dir=", "llm.cache_path=", "llm.base_url="))],
        "frames": s["frames"], "updates": s["updates"],
        "train_s": round(s["train_s"], 2), "frames_per_s": round(s["frames"] / s["train_s"], 2),
        "update_s": round(s["update_s"], 2), "wall_s_with_eval": round(wall, 1),
        "eval_DCR": final.get("eval/DCR"), "eval_CR": final.get("eval/CR"),
    }
    ov = s.get("override")
    if ov:
        f = max(ov["frames"], 1)
        calls = ov.get("advisor/calls", 0)
        row.update({
            "trigger_rate": round(ov["trigger_rate"], 4),
            "rows_asked": int(ov["advised"]), "held": int(ov["held"]),
            "http_calls": int(calls), "cache_hits": int(ov.get("advisor/cache_hits", 0)),
            "failures": int(ov.get("advisor/failures", 0)),
            "calls_per_1000_frames": round(1000 * calls / f, 1),
            "rows_asked_per_1000_frames": round(1000 * ov["advised"] / f, 1),
            "latency_p50_s": ov.get("advisor/latency_p50_s"), "latency_p95_s": ov.get("advisor/latency_p95_s"),
            "prompt_tokens_per_call": round(ov.get("advisor/prompt_tokens", 0) / max(calls, 1), 1),
            "completion_tokens_per_call": round(ov.get("advisor/completion_tokens", 0) / max(calls, 1), 1),
            "advice_wait_s": round(ov["advice_wait_s"], 2),
            "overlap_s": round(s["overlap_s"], 3),
        })
    print(exp, json.dumps(row), flush=True)
    return row


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--hold4-args", default="", help="more overrides of the hold_steps=4 run (quoted)")
    ap.add_argument("--overlap-ab", action="store_true", help="also hold_steps=1 with trainer.overlap_advice=false")
    ap.add_argument("--extra", default="", help="overrides of every run, after RUN_ARGS (quoted)")
    ap.add_argument("--note", default="", help="a line recorded with the result (what branch state ran)")
    ap.add_argument("--out", default=str(ROOT / "benchmarks" / "sac_llm_speed.json"))
    args = ap.parse_args()
    torch.set_num_threads(1)
    os.environ.setdefault("WANDB_MODE", "disabled")

    from omegaconf import OmegaConf

    from uavlae.factories import CONF_DIR, git_info
    from uavlae.files import dump_json
    from uavlae.llm.config import ServerConfig
    from uavlae.llm.server import local_server
    from uavlae.machine import describe_machine

    base = make_run_args() + shlex.split(args.extra)
    server_cfg = ServerConfig(**OmegaConf.to_container(OmegaConf.load(CONF_DIR / "llm" / "local.yaml").server))
    rows: dict[str, dict] = {}
    with tempfile.TemporaryDirectory() as tmp:
        tmp_path = Path(tmp)
        rows["sac"] = train("sac", tmp_path / "sac", base)
        t0 = time.perf_counter()
        with local_server(server_cfg) as srv:
            server_start_s = time.perf_counter() - t0

            def llm_args(name: str) -> list[str]:  # a new, empty cache per run
                return [f"llm.base_url={srv.base_url}", f"llm.cache_path={tmp_path / name / 'cache.sqlite'}",
                        "llm.cache_mode=read_write"]

            rows["sac_llm_hold1"] = train("sac_llm", tmp_path / "h1", base + llm_args("h1") + ["advisor.hold_steps=1"])
            if args.overlap_ab:
                rows["sac_llm_hold1_no_overlap"] = train(
                    "sac_llm", tmp_path / "h1s", base + llm_args("h1s") + ["advisor.hold_steps=1", "trainer.overlap_advice=false"])
            rows["sac_llm_hold4"] = train(
                "sac_llm", tmp_path / "h4", base + llm_args("h4") + ["advisor.hold_steps=4", *shlex.split(args.hold4_args)])
        rows["sac_again"] = train("sac", tmp_path / "sac2", base)
    sac_fps = (rows["sac"]["frames_per_s"] + rows["sac_again"]["frames_per_s"]) / 2
    ratios = {f"sac_over_{k}": round(sac_fps / r["frames_per_s"], 2) for k, r in rows.items() if k.startswith("sac_llm")}
    out = {
        "measured_at": time.strftime("%Y-%m-%d %H:%M:%S %Z"),
        "machine": describe_machine(),
        "git": git_info(),
        "command": "python benchmarks/sac_llm_speed.py " + " ".join(shlex.quote(a) for a in sys.argv[1:]),
        "note": args.note,
        "run_args": base,
        "llm_server": server_cfg.model_dump(),
        "server_start_s": round(server_start_s, 1),
        "sac_frames_per_s_mean_of_two": round(sac_fps, 1),
        "ratios": ratios,
        "runs": rows,
    }
    dump_json(Path(args.out), out)
    print(json.dumps({"sac_fps": out["sac_frames_per_s_mean_of_two"], **ratios,
                      **{k: r["frames_per_s"] for k, r in rows.items()}}))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
