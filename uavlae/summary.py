"""What a run tells its reader at the end: ``summary.json`` and the closing print.

The summary holds the final metrics of the trained actor beside the baselines on the same
evaluation set (and, for an advised run, the actor with its advisor), the frames and wall clock,
and the advisor's counters; :func:`format_summary` turns it into the lines ``uavlae.train``
prints last.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from omegaconf import OmegaConf

from uavlae.envs.metrics import PAPER_METRICS
from uavlae.factories import CONF_DIR, dump_json
from uavlae.files import train_eval_dir

__all__ = ["METRIC_MEANINGS", "advised_row", "baseline_rows", "format_summary", "full_run_frames", "pictures", "write_summary"]

# What the closing summary says of each paper metric (docs/model.md §5).
METRIC_MEANINGS = {
    "DCR": "data collected / data there, higher is better",
    "CR": "episodes with a collision, lower is better",
    "SLR": "episodes that landed, higher is better",
    "RVR": "episodes speeding in a residential zone, lower is better",
    "ECR": "energy used / energy limit, lower is better",
}


def write_summary(run_dir: Path, summary: dict[str, Any]) -> Path:
    path = run_dir / "summary.json"
    dump_json(path, summary)
    return path


def format_summary(summary: dict[str, Any]) -> str:
    """The closing print of a run, for a reader who has not seen the code."""
    lines = []
    name, frames = summary["name"], int(summary["frames"])
    if summary.get("controller", "learner") == "learner":
        full = int(summary["full_run_frames"])
        fps = summary.get("fps")
        lines.append(
            f"{name}: trained {frames:,} environment frames ({100 * frames / full:.2g}% of a full run's {full:,}; "
            f"trainer.total_frames sets the budget) with {int(summary['updates']):,} gradient steps"
            + (f", {summary['train_s']:.1f} s at {fps:.1f} frames/s (evaluation not counted)" if fps else "") + "."
        )
    else:
        lines.append(f"{name}: evaluated (no training).")
    rows = summary["metrics"]
    n_eps = summary.get("eval_episodes")
    lines.append("")
    filtered = any(k.endswith("(actor + safety filter)") for k in rows)
    who_flies = (f"{summary.get('controller')} flies" if summary.get("controller", "learner") != "learner"
                 else "the trained actor flies deterministically, through its safety filter and alone" if filtered
                 else "the trained actor flies alone, deterministically")
    lines.append(f"The five paper metrics on the fixed evaluation set ({n_eps} episodes, one per scenario; {who_flies}):")
    width = max(len(k) for k in rows) + 2
    lines.append(" " * width + "".join(f"{k:>8}" for k in PAPER_METRICS))
    for who, agg in rows.items():
        lines.append(f"{who:<{width}}" + "".join(f"{_num(agg.get(k)):8.3f}" for k in PAPER_METRICS))
    lines.extend(f"  {k}: {v}" for k, v in METRIC_MEANINGS.items())
    lines.extend(_budget_lines(summary.get("advised_eval")))
    ov = summary.get("override")
    if ov:
        kind = summary.get("advisor_kind", "advisor")
        f_ = max(int(ov.get("frames", 0)), 1)
        lines.append("")
        lines.append(
            f"Advisor ({kind}): triggered on {int(ov['triggered']):,} of {int(ov['frames']):,} frames "
            f"({100 * ov['triggered'] / f_:.1f}%); {int(ov.get('advised', 0)):,} rows asked, "
            f"{int(ov.get('held', 0)):,} executed a held answer (hold_steps={int(ov.get('hold_steps', 1))}), "
            f"{int(ov.get('budget_skipped', 0)):,} left to the actor by the call budget"
            + (f" (max_calls={int(ov['max_calls'])})" if ov.get("max_calls", -1) >= 0 else "") + "; "
            f"{int(ov.get('source/fallback', 0)):,} failed answers."
        )
        if ov.get("advised_fraction") is not None:
            gap, agree = _num(ov.get("actor_gap")), _num(ov.get("actor_agree"))
            lines.append(
                f"  Dependence: {100 * ov['advised_fraction']:.1f}% of the stored transitions are the advisor's; "
                f"where it acted, the actor's own action lay {gap:.2f} from it on average "
                f"(within {ov.get('agree_tol', 0.1):g} in {100 * agree:.0f}% of rows)"
                + (f"; trigger phased out to {ov['phase']:.2f} of d_th / fp" if ov.get("phase", 1.0) < 1.0 else "") + "."
            )
        if kind == "llm" and ov.get("advisor/calls") is not None:  # training's calls
            lines.append(_llm_line(ov, f_, summary.get("overlap_s")))
    lines.extend(_cost_lines(summary.get("cost"), summary.get("override")))
    la = summary.get("llm_alone")
    if la:
        c = la["cost"]
        lines.append(
            f"  LLM alone: {la['episodes_scored']} of {la['episodes_total']} episodes scored "
            f"({la['chunks_done']} of {la['chunks']} chunks of {la['chunk']} scenarios"
            + ("" if la["complete"] else f"; paused by the call budget {la['budget']}, the same command continues") + "); "
            f"{int(c['calls']):,} LLM decisions in {c['wall_s']:.0f} s ({c['calls_per_s']:.2f}/s) over "
            f"{int(c['invocations'])} invocation(s), {int(c['fallbacks']):,} answered by the fallback."
        )
    lines.append("")
    for pic in summary.get("pictures", []):
        lines.append(f"Pictures: {pic}")
    lines.append(f"All numbers: {summary['run_dir']}/final_metrics.json and summary.json; "
                 f"curves: {summary['run_dir']}/logs/scalars/")
    return "\n".join(lines)


def pictures(run_dir: Path, frames: int) -> list[str]:
    out = []
    for d in (train_eval_dir(run_dir, frames), run_dir / "eval" / "baseline_heuristic", run_dir / "eval" / "baseline_random"):
        if any(d.glob("trajectory_*.png")):
            out.append(str(d / "trajectory_*.png"))
    return out


def advised_row(final: dict[str, Any], name: str) -> dict[str, dict[str, float]]:
    agg = {k.split("/", 1)[1]: v for k, v in final.items() if k.startswith("advised/") and k.count("/") == 1}
    return {f"{name} (actor with its advisor)": agg} if agg else {}


def baseline_rows(final: dict[str, Any]) -> dict[str, dict[str, float]]:
    rows: dict[str, dict[str, float]] = {}
    for key, v in final.items():
        if key.startswith("baseline/"):
            _, who, metric = key.split("/", 2)
            rows.setdefault(who, {})[metric] = v
    return {("uniform random" if who == "random" else who): agg for who, agg in rows.items()}


def full_run_frames() -> int:
    return int(OmegaConf.load(CONF_DIR / "trainer" / "default.yaml").total_frames)


def _num(x: Any) -> float:
    """A number of the summary as a float: ``None`` (JSON's word for no value) is NaN."""
    return float("nan") if x is None else float(x)


def _llm_line(ov: dict[str, Any], frames: int, overlap_s: float | None) -> str:
    """The LLM's work in one count, HTTP calls, with its parts: the rows it was asked (less the
    ones its cache answered) each took a first call, some a call again after an answer the
    extractor rejected, some a retry after a transport error."""
    calls, asked, hits, again, retries = (int(ov.get(f"advisor/{k}") or 0)
                                          for k in ("calls", "requests", "cache_hits", "ask_again", "retries"))
    first = calls - again - retries
    n = max(float(calls), 1.0)
    return (
        f"  LLM in training: {calls:,} HTTP calls ({1000 * calls / frames:.1f} per 1000 frames) = {first:,} first calls for the "
        f"{asked:,} rows asked ({hits:,} answered from the cache, rows with the same prompt sharing one call) + "
        f"{again:,} asked again after an answer it could not use + {retries:,} transport retries; per call p50 "
        f"{_num(ov.get('advisor/latency_p50_s')):.2f} s, p95 {_num(ov.get('advisor/latency_p95_s')):.2f} s, "
        f"{ov.get('advisor/prompt_tokens', 0) / n:.0f} prompt + {ov.get('advisor/completion_tokens', 0) / n:.0f} "
        f"completion tokens; the loop waited {ov.get('advice_wait_s', 0.0):.1f} s for answers"
        + (f" after {overlap_s:.1f} s of gradient steps run while they were in flight" if overlap_s else "") + "."
    )


def _budget_lines(ev: dict[str, Any] | None) -> list[str]:
    """The with-advisor evaluation's own LLM calls (apart from training's, counted below), and
    where its call budget left triggered rows to the actor."""
    if not ev:
        return []
    out = []
    if ev.get("llm_calls"):
        out.append(f"  The actor with its advisor asked the LLM for {int(ev['llm_requests']):,} rows in "
                   f"{int(ev['llm_calls']):,} HTTP calls (not counted in the LLM line of training below).")
    if ev.get("budget_skipped"):
        out.append(f"  The actor with its advisor: trainer.eval_advisor_max_calls={ev['max_calls']} rows were asked, "
                   f"then the actor flew {int(ev['budget_skipped']):,} of the {int(ev['triggered']):,} triggered rows "
                   "itself, so that row shows less of the advisor than it would give (null asks every row, at the "
                   "LLM's cost).")
    return out


def _cost_lines(cost: dict[str, Any] | None, ov: dict[str, Any] | None) -> list[str]:
    """What the advice cost: rows by who answered, tokens, time, money; the student's share."""
    if not cost or cost.get("triggered") is None:
        return []
    money = _num(cost.get("money"))
    lines = [
        f"  Cost: {int(cost['triggered']):,} triggered rows; executed from the LLM's answer {int(cost['rows_llm']):,}, "
        f"the student's {int(cost['rows_student']):,}, a held answer {int(cost['rows_held']):,}, the fallback "
        f"{int(cost['rows_fallback']):,}; {int(cost['tokens_in']):,} tokens in ({int(cost['tokens_in_cached']):,} cached), "
        f"{int(cost['tokens_out']):,} out; the LLM answered for {cost['llm_s']:.0f} s, the loop waited {cost['wait_s']:.0f} s"
        + (f"; {money:.4g} {cost.get('currency')}" if money == money else "; no price in the llm config") + "."]
    if ov and ov.get("advisor/student/rows"):
        lines.append(
            f"  Student: the LLM was asked for {int(ov['advisor/student/llm_rows']):,} of {int(ov['advisor/student/rows']):,} "
            f"rows (warm-up {int(ov['advisor/student/asked_warmup']):,}, unsure {int(ov['advisor/student/asked_unsure']):,}, "
            f"novel {int(ov['advisor/student/asked_novel']):,}, audit {int(ov['advisor/student/asked_audit']):,}); on the "
            f"audited rows its velocity lay {_num(ov.get('advisor/student/audit_err_mps')):.2f} m/s from the LLM's.")
    return lines
