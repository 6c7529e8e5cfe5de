"""``python -m uavlae.train +exp=NAME``: train (or, for ``heuristic`` / ``llm``, evaluate) one method.

The loop, top to bottom (every number in ``conf/``)::

    for batch in collector:                      # [B, T] executed transitions, step = env frames
        off-policy (sac, ddpg), inside every env step of the batch (OffPolicyUpdates):
            the triggered rows' advice is sent; the gradient steps owed so far run while it is
            in flight; the (updated) actor acts; the answers are merged; the env steps;
            replay.extend(transition); utd_ratio * B gradient steps owed once past the warm-up
        on-policy (ppo, cpo):   learner.update(batch)
        log train metrics, episode metrics, override / LLM counters, fps
        every eval_every_frames:       evaluate the deterministic actor on the fixed set
        every checkpoint_every_frames: atomic checkpoint (exact resume at this batch boundary)
    at the end: the owed gradient steps, a final evaluation, the heuristic and a random policy
    on the same set (``trainer.baselines``), final_metrics.json and a summary for the reader

Every off-policy method gets the same schedule (``sac`` and ``sac_llm`` differ only in who
acts), and it does not depend on when the answers arrive: with ``llm.cache_mode=replay_only``
a run replays exactly, and ``trainer.overlap_advice=false`` gives the same numbers.

``run(cfg)`` is importable (the tests call it in-process) and returns the final metrics.
``resume=RUN_DIR_OR_CHECKPOINT`` continues a run: same config, frames, RNG states, replay
buffer, CSV files and wandb run id.
"""

from __future__ import annotations

import json
import logging
import math
import time
import uuid
from pathlib import Path
from typing import Any

import hydra
import torch
from omegaconf import DictConfig, OmegaConf

from uavlae.algos import OFF_POLICY
from uavlae.checkpoint import (
    load_checkpoint, resolve_checkpoint, rng_state, run_dir_of, save_checkpoint, seed_everything, set_rng_state,
)
from uavlae.collect import TRANSITION_KEYS, UAVCollector, make_replay_buffer
from uavlae.envs import make_env_config
from uavlae.envs.metrics import PAPER_METRICS
from uavlae.evaluate import Evaluator, config_differences, flatten_keys, deterministic_actor, eval_set_path, load_or_make_eval_set
from uavlae.factories import (
    CONF_DIR,
    behaviour_actor,
    dump_json,
    make_controller,
    make_env,
    make_learner,
    make_logger,
    make_policy,
    make_trainer_config,
    redact_secrets,
    run_metadata,
    trim_csv_scalars,
    validate_config,
    without_removed_keys,
)
from uavlae.files import atomic_write, train_eval_dir

log = logging.getLogger(__name__)

# What a resumed run may take from the new command line; everything else is the saved config.
RESUME_RUNTIME_KEYS = ("threads", "trainer.progress_bar", "logger.wandb.mode")
# What the replay buffer keeps of a transition (the collector already dropped the raw state).
REPLAY_KEYS = (
    "observation", "action", "action_source",
    ("next", "observation"), ("next", "reward"), ("next", "cost"), ("next", "done"),
    ("next", "terminated"), ("next", "truncated"),
)


def _resolved(cfg: DictConfig) -> dict[str, Any]:
    return redact_secrets(OmegaConf.to_container(cfg, resolve=True))  # type: ignore[arg-type]


# Keys that may differ between a sweep's re-run and the run it finds in its run_dir (the LLM
# alone's call budget is what one invocation may spend: a re-run with another continues).
# the LLM alone's budget and shards: how a run is split into invocations and processes, not what it is
REUSE_IGNORED_KEYS = ("resume", "experiment.reuse", "trainer.llm_call_budget", "trainer.eval_shard",
                      "trainer.eval_shards", *RESUME_RUNTIME_KEYS)


def _comparable(cfg_dict: dict[str, Any]) -> dict[str, Any]:
    c = OmegaConf.create(cfg_dict)
    c.run_dir = str(Path(c.run_dir).resolve())  # a resumed run saves its run_dir resolved
    for key in REUSE_IGNORED_KEYS:
        if OmegaConf.select(c, key) is not None:
            OmegaConf.update(c, key, None, merge=False)
    return OmegaConf.to_container(c)  # type: ignore[return-value]


def reuse_state(cfg: DictConfig) -> tuple[str, dict[str, Any] | None]:
    """With ``experiment.reuse``: what ``cfg.run_dir`` holds of this run. ``("done", final
    metrics)`` for a finished run, ``("resume", None)`` for one with a checkpoint, ``("new",
    None)`` otherwise. A run_dir that holds a run of another config is an error (a sweep re-run
    with changed settings must not mix the two). Settings the saved config lacks (added to the
    code after the run was made, with defaults that keep the earlier behaviour) do not count as
    a difference; they are logged."""
    run_dir = Path(cfg.run_dir)
    saved_file = run_dir / "config.json"
    if not cfg.experiment.reuse or not saved_file.is_file():
        return "new", None
    want = _comparable(_resolved(cfg))
    changed, added = config_differences(want, _comparable(json.loads(saved_file.read_text())))
    if added:
        flat = flatten_keys(want)
        log.warning("%s was made before these settings existed; reusing it as if at their values now: %s",
                    run_dir, {k: flat[k] for k in added})
    if changed:
        raise ValueError(
            f"{run_dir} holds a run of another config (differs in {changed[:8]}); "
            "remove it or set experiment.root elsewhere"
        )
    final = run_dir / "final_metrics.json"
    if final.is_file():
        done = json.loads(final.read_text())
        if done.get("eval/complete", 1) == 0:  # the LLM alone paused by its call budget: continue it
            return "new", None
        return "done", done
    if (run_dir / "checkpoints" / "last.pt").is_file() or (run_dir / "checkpoints" / "prev.pt").is_file():
        return "resume", None
    return "new", None


def _prepare(cfg: DictConfig) -> tuple[DictConfig, dict[str, Any] | None]:
    """Resolve the config; on ``resume`` load the checkpoint and continue with its config."""
    ckpt = None
    if cfg.resume:
        ckpt, file = load_checkpoint(cfg.resume)
        saved = OmegaConf.create(without_removed_keys(ckpt["config"]))
        for key in RESUME_RUNTIME_KEYS:
            OmegaConf.update(saved, key, OmegaConf.select(cfg, key), merge=False)
        saved.resume = str(file)
        saved.run_dir = str(run_dir_of(file))
        cfg = saved
        log.info("resuming %s from %s at %d frames", cfg.name, file, ckpt["counters"]["frames"])
    else:
        cfg = OmegaConf.create(_resolved(cfg))
    OmegaConf.set_struct(cfg, True)
    validate_config(cfg)
    return cfg, ckpt


def _prefixed(prefix: str, metrics: dict[str, Any]) -> dict[str, float]:
    out = {}
    for k, v in metrics.items():
        if isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(float(v)):
            out[f"{prefix}/{k}"] = float(v)
    return out


class OffPolicyUpdates:
    """The off-policy schedule, per env step: each step's ``B`` transitions go to the replay
    buffer and, once ``frames >= init_random_frames`` and the buffer holds a sample, owe
    ``utd_ratio * B`` gradient steps (fractions carried in ``counters["utd_debt"]``), which run
    at the next env step while its advice is in flight (:class:`uavlae.collect.UAVCollector`'s
    ``between``); :meth:`flush` pays what is left at the end of training."""

    def __init__(self, learner: Any, replay: Any, tr: Any, counters: dict[str, Any]):
        self.learner, self.replay, self.tr, self.counters = learner, replay, tr, counters
        self.logs: dict[str, float] = {}

    def add(self, transition: Any) -> None:
        """The collector's ``on_step``: store the step, count what it owes."""
        self.replay.extend(transition.select(*REPLAY_KEYS, strict=False).reshape(-1))
        frames = self.counters["frames"] + transition.batch_size[0]
        self.counters["frames"] = frames
        if frames >= self.tr.init_random_frames and len(self.replay) >= self.tr.batch_size:
            self.counters["utd_debt"] += self.tr.utd_ratio * transition.batch_size[0]

    def run(self) -> None:
        """The collector's ``between``: the gradient steps owed so far."""
        n = int(self.counters["utd_debt"])
        self.counters["utd_debt"] -= n
        self.learner.anneal(self.counters["frames"])
        for _ in range(n):
            self.logs = self.learner.update(self.replay.sample())
        self.counters["updates"] += n

    def flush(self) -> None:
        with torch.enable_grad():
            self.run()


# What the closing summary says of each paper metric (SPEC.md §5).
METRIC_MEANINGS = {
    "DCR": "data collected / data there, higher is better",
    "CR": "episodes with a collision, lower is better",
    "SLR": "episodes that landed, higher is better",
    "RVR": "episodes speeding in a residential zone, lower is better",
    "ECR": "energy used / energy limit, lower is better",
}


def _deterministic_counts(totals: dict[str, Any]) -> dict[str, Any]:
    """The override's run counters that a replay reproduces: no timings, none of the
    advisor's transport counts (a replayed answer is a cache hit, a live one a call)."""
    return {k: v for k, v in totals.items()  # the student learns from the answers alone: replayed exactly
            if (not k.startswith("advisor/") or k.startswith("advisor/student/")) and not k.endswith("_s")}


def _baselines(cfg: DictConfig, env_cfg: Any, evaluator: Evaluator, run_dir: Path) -> dict[str, float]:
    """The greedy heuristic and a uniform-random policy on the same evaluation set."""
    from uavlae.collect import _UniformRandom
    from uavlae.factories import make_heuristic

    generator = torch.Generator()
    generator.manual_seed(int(cfg.trainer.eval_seed))
    policies = {"heuristic": make_heuristic(cfg, env_cfg), "random": _UniformRandom(evaluator.env.action_spec, generator)}
    out: dict[str, float] = {}
    for name, policy in policies.items():
        agg = evaluator.run(policy, run_dir / "eval" / f"baseline_{name}", title=name)
        out.update(_prefixed(f"baseline/{name}", agg))
    return out


def _advised_evaluation(policy: Any, evaluator: Evaluator, run_dir: Path, tr: Any, name: str) -> dict[str, float]:
    """The actor *with* its advisor on the same evaluation set as the actor alone: the
    override at its full trigger (no phase-out), the actor deterministic, at most
    ``trainer.eval_advisor_max_calls`` rows asked. Beside ``eval/``, this tells what the actor
    owes to its advisor. Training state is untouched (``OverridePolicy.advised``)."""
    with policy.advised(max_calls=tr.eval_advisor_max_calls):
        agg = evaluator.run(policy, run_dir / "eval" / "with_advisor", title=f"{name} with its advisor")
        counts = policy.counters()
    keep = ("trigger_rate", "advised_fraction", "advice_fail_rate", "actor_gap", "actor_agree", "triggered",
            "advised", "budget_skipped", "frames")
    return {**_prefixed("advised", agg), **_prefixed("advised/override", {k: counts[k] for k in keep})}


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
            f"`make run RUN_ARGS=` trains all of it) with {int(summary['updates']):,} gradient steps"
            + (f", {summary['train_s']:.1f} s at {fps:.1f} frames/s (evaluation not counted)" if fps else "") + "."
        )
    else:
        lines.append(f"{name}: evaluated (no training).")
    rows = summary["metrics"]
    n_eps = summary.get("eval_episodes")
    lines.append("")
    who_flies = ("the trained actor flies alone, deterministically" if summary.get("controller", "learner") == "learner"
                 else f"{summary.get('controller')} flies")
    lines.append(f"The five paper metrics on the fixed evaluation set ({n_eps} episodes, one per scenario; {who_flies}):")
    width = max(len(k) for k in rows) + 2
    lines.append(" " * width + "".join(f"{k:>8}" for k in PAPER_METRICS))
    for who, agg in rows.items():
        lines.append(f"{who:<{width}}" + "".join(f"{agg.get(k, float('nan')):8.3f}" for k in PAPER_METRICS))
    lines.extend(f"  {k}: {v}" for k, v in METRIC_MEANINGS.items())
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
            gap, agree = ov.get("actor_gap", float("nan")), ov.get("actor_agree", float("nan"))
            lines.append(
                f"  Dependence: {100 * ov['advised_fraction']:.1f}% of the stored transitions are the advisor's; "
                f"where it acted, the actor's own action lay {gap:.2f} from it on average "
                f"(within {ov.get('agree_tol', 0.1):g} in {100 * agree:.0f}% of rows)"
                + (f"; trigger phased out to {ov['phase']:.2f} of d_th / fp" if ov.get("phase", 1.0) < 1.0 else "") + "."
            )
        calls = ov.get("advisor/calls")
        if kind == "llm" and calls is not None:
            n = max(float(calls), 1.0)
            lines.append(
                f"  LLM: {int(calls):,} HTTP calls ({1000 * calls / f_:.1f} per 1000 frames), "
                f"{int(ov.get('advisor/cache_hits', 0)):,} cache hits; per call p50 {ov.get('advisor/latency_p50_s', float('nan')):.2f} s, "
                f"p95 {ov.get('advisor/latency_p95_s', float('nan')):.2f} s, "
                f"{ov.get('advisor/prompt_tokens', 0) / n:.0f} prompt + {ov.get('advisor/completion_tokens', 0) / n:.0f} "
                f"completion tokens; the loop waited {ov.get('advice_wait_s', 0.0):.1f} s for answers"
                + (f" after {summary.get('overlap_s', 0.0):.1f} s of gradient steps run while they were in flight"
                   if summary.get("overlap_s") else "") + "."
            )
    cost = summary.get("cost")
    if cost and cost.get("triggered") is not None:
        money = cost.get("money", float("nan"))
        lines.append(
            f"  Cost: {int(cost['triggered']):,} triggered rows; executed from the LLM's answer {int(cost['rows_llm']):,}, "
            f"the student's {int(cost['rows_student']):,}, a held answer {int(cost['rows_held']):,}, the fallback "
            f"{int(cost['rows_fallback']):,}; {int(cost['tokens_in']):,} tokens in ({int(cost['tokens_in_cached']):,} cached), "
            f"{int(cost['tokens_out']):,} out; the LLM answered for {cost['llm_s']:.0f} s, the loop waited {cost['wait_s']:.0f} s"
            + (f"; {money:.4g} {cost.get('currency')}" if money == money else "; no price in the llm config") + ".")
        if ov and ov.get("advisor/student/rows"):
            lines.append(
                f"  Student: the LLM was asked for {int(ov['advisor/student/llm_rows']):,} of {int(ov['advisor/student/rows']):,} "
                f"rows (warm-up {int(ov['advisor/student/asked_warmup']):,}, unsure {int(ov['advisor/student/asked_unsure']):,}, "
                f"novel {int(ov['advisor/student/asked_novel']):,}, audit {int(ov['advisor/student/asked_audit']):,}); on the "
                f"audited rows its velocity lay {ov.get('advisor/student/audit_err_mps', float('nan')):.2f} m/s from the LLM's.")
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


def _pictures(run_dir: Path, frames: int) -> list[str]:
    out = []
    for d in (train_eval_dir(run_dir, frames), run_dir / "eval" / "baseline_heuristic", run_dir / "eval" / "baseline_random"):
        if any(d.glob("trajectory_*.png")):
            out.append(str(d / "trajectory_*.png"))
    return out


def _advised_row(final: dict[str, Any], name: str) -> dict[str, dict[str, float]]:
    agg = {k.split("/", 1)[1]: v for k, v in final.items() if k.startswith("advised/") and k.count("/") == 1}
    return {f"{name} (actor with its advisor)": agg} if agg else {}


def _baseline_rows(final: dict[str, Any]) -> dict[str, dict[str, float]]:
    rows: dict[str, dict[str, float]] = {}
    for key, v in final.items():
        if key.startswith("baseline/"):
            _, who, metric = key.split("/", 2)
            rows.setdefault(who, {})[metric] = v
    return {("uniform random" if who == "random" else who): agg for who, agg in rows.items()}


def _full_run_frames() -> int:
    return int(OmegaConf.load(CONF_DIR / "trainer" / "default.yaml").total_frames)


def run(cfg: DictConfig) -> dict[str, Any]:
    """Train (or evaluate a controller) as ``cfg`` says; returns the final metrics."""
    # A multirun worker runs job after job in one process: the graphs compiled for an earlier
    # job's env would count against this job's recompile limit (and fail it under fullgraph).
    torch.compiler.reset()
    state, final = reuse_state(cfg)
    if state == "done":
        log.info("%s: finished already (experiment.reuse): %s", cfg.name, Path(cfg.run_dir) / "final_metrics.json")
        return final  # type: ignore[return-value]
    if state == "resume":
        cfg = cfg.copy()
        OmegaConf.set_struct(cfg, False)
        cfg.resume = str(cfg.run_dir)
        OmegaConf.set_struct(cfg, True)
    cfg, ckpt = _prepare(cfg)
    torch.set_num_threads(int(cfg.threads))
    tr = make_trainer_config(cfg.trainer)
    env_cfg = make_env_config(cfg.env)
    run_dir = Path(cfg.run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    resolved = _resolved(cfg)
    dump_json(run_dir / "config.json", resolved)
    yaml_text = OmegaConf.to_yaml(OmegaConf.create(resolved))
    atomic_write(run_dir / "config.yaml", lambda fh: fh.write(yaml_text.encode("utf-8")))
    meta = run_metadata(resolved)
    dump_json(run_dir / "meta.json", meta)

    run_id = ckpt["logger"]["run_id"] if ckpt else f"{cfg.name}-{uuid.uuid4().hex[:10]}"
    if ckpt:
        trim_csv_scalars(run_dir / "logs", int(ckpt["counters"]["frames"]))
    logger = make_logger(cfg, run_dir, run_id, {**resolved, "meta": meta})
    if ckpt:
        logger.load_state_dict(ckpt["logger"])

    scenarios = load_or_make_eval_set(env_cfg, eval_set_path(run_dir, tr.eval_set), tr.eval_episodes, tr.eval_seed)
    evaluator = Evaluator(
        env_cfg,
        scenarios,
        seed=tr.eval_seed,
        max_steps=tr.eval_max_steps,
        n_plots=tr.eval_plots,
        device=cfg.device,
        compile_step=tr.compile_env,
    )
    try:
        if cfg.controller != "learner":
            return _evaluate_controller(cfg, env_cfg, evaluator, logger, run_dir)
        return _train(cfg, tr, env_cfg, evaluator, logger, run_dir, ckpt)
    finally:
        logger.close()


def _evaluate_controller(cfg: DictConfig, env_cfg: Any, evaluator: Evaluator, logger: Any, run_dir: Path) -> dict[str, Any]:
    """``heuristic`` / ``random`` / ``llm``: no learner; the controller flies the evaluation set
    (the LLM chunk by chunk under its call budget, resumable: :mod:`uavlae.llm_alone`)."""
    if cfg.controller == "llm":
        return _evaluate_llm_alone(cfg, env_cfg, evaluator, logger, run_dir)
    controller = make_controller(cfg, env_cfg, action_spec=evaluator.env.action_spec)
    t0 = time.perf_counter()
    try:
        agg = evaluator.run(controller, train_eval_dir(run_dir, 0), title=str(cfg.name))
        totals = controller.run_totals() if hasattr(controller, "run_totals") else None
        stats = controller.snapshot() if hasattr(controller, "snapshot") else {}
    finally:
        close = getattr(controller, "close", None)
        if close is not None:
            close()
    metrics = {**_prefixed("eval", agg), **_prefixed("override", stats), "time/eval_s": time.perf_counter() - t0}
    logger.log_metrics(metrics, step=0)
    logger.log_images(_trajectory_images(train_eval_dir(run_dir, 0)), step=0)
    final = {"frames": 0, **metrics}
    dump_json(run_dir / "final_metrics.json", final)
    write_summary(run_dir, {
        "name": str(cfg.name), "controller": str(cfg.controller), "run_dir": str(run_dir), "frames": 0,
        "eval_episodes": len(evaluator.scenarios), "metrics": {str(cfg.name): agg},
        "advisor_kind": str(cfg.advisor.kind), "override": totals, "pictures": _pictures(run_dir, 0),
    })
    log.info("%s: %s", cfg.name, {k: round(agg[k], 4) for k in PAPER_METRICS})
    return final


def _evaluate_llm_alone(cfg: DictConfig, env_cfg: Any, evaluator: Evaluator, logger: Any, run_dir: Path) -> dict[str, Any]:
    """``+exp=llm``: :class:`uavlae.llm_alone.LLMAloneEvaluation` on the run's evaluation set.
    A run paused by its call budget writes its final metrics with ``eval/complete`` 0 (the
    scored episodes only, ``eval/episodes_scored`` of ``eval/episodes_total``); the same
    command continues it. The cost goes under ``llm/``."""
    from uavlae.llm_alone import LLMAloneEvaluation

    tr = make_trainer_config(cfg.trainer)
    fingerprint = _comparable(_resolved(cfg))
    fingerprint.pop("run_dir", None)  # a moved run folder still continues
    out = train_eval_dir(run_dir, 0)
    controller = make_controller(cfg, env_cfg, action_spec=evaluator.env.action_spec)
    try:
        ev = LLMAloneEvaluation(
            env_cfg, evaluator.scenarios, controller, out, seed=tr.eval_seed, chunk=tr.eval_chunk,
            max_steps=tr.eval_max_steps, budget=tr.llm_call_budget, fingerprint=fingerprint,
            n_plots=tr.eval_plots, device=cfg.device, shard=tr.eval_shard, shards=tr.eval_shards,
        )
        res = ev.run()
        totals = controller.run_totals()
    finally:
        controller.close()
    ev.write(res, title=str(cfg.name))
    agg = res["metrics"]
    progress = {"complete": int(res["complete"]), "episodes_scored": res["episodes_scored"],
                "episodes_total": res["episodes_total"], "chunks_done": res["chunks_done"], "chunks": res["chunks"]}
    metrics = {**_prefixed("eval", {**agg, **progress}), **_prefixed("llm", res["cost"]),
               **_prefixed("override", totals), "time/eval_s": res["cost"]["wall_s"]}
    logger.log_metrics(metrics, step=0)
    if res["trajectories"]:
        logger.log_images(_trajectory_images(out), step=0)
    final = {"frames": 0, **metrics}
    dump_json(run_dir / "final_metrics.json", final)
    write_summary(run_dir, {
        "name": str(cfg.name), "controller": str(cfg.controller), "run_dir": str(run_dir), "frames": 0,
        "eval_episodes": res["episodes_scored"], "metrics": {str(cfg.name): agg},
        "advisor_kind": str(cfg.advisor.kind), "override": totals, "pictures": _pictures(run_dir, 0),
        "llm_alone": {**progress, "in_flight_step": res["in_flight_step"], "cost": res["cost"],
                      "budget": tr.llm_call_budget, "chunk": ev.chunk, "shard": ev.shard, "shards": ev.shards},
    })
    state = "complete" if res["complete"] else (
        f"paused by the call budget ({res['chunks_done']}/{res['chunks']} chunks done); run the same command to continue")
    log.info("%s: %d of %d episodes scored, %s: %s", cfg.name, res["episodes_scored"], res["episodes_total"], state,
             {k: round(agg[k], 4) for k in PAPER_METRICS})
    return final


def _train(
    cfg: DictConfig, tr: Any, env_cfg: Any, evaluator: Evaluator, logger: Any, run_dir: Path, ckpt: dict[str, Any] | None
) -> dict[str, Any]:
    from tqdm.auto import tqdm

    seed_everything(int(cfg.seed))
    env = make_env(env_cfg, tr.env_batch_size, seed=int(cfg.seed), device=cfg.device, compile_step=tr.compile_env)
    learner = make_learner(cfg.algo, env)
    off_policy = cfg.algo.name in OFF_POLICY
    has_advisor = cfg.advisor.kind != "none"
    policy = make_policy(cfg, behaviour_actor(learner), env_cfg)
    replay = make_replay_buffer(tr.replay_capacity, tr.batch_size, cfg.device, seed=int(cfg.seed)) if off_policy else None
    counters: dict[str, Any] = {"frames": 0, "episodes": 0, "batches": 0, "updates": 0, "utd_debt": 0.0, "next_eval": 0,
                                "next_ckpt": 0, "update_s": 0.0, "overlap_s": 0.0, "wall_s": 0.0}
    counters["next_eval"] = tr.eval_every_frames or tr.total_frames
    counters["next_ckpt"] = tr.checkpoint_every_frames or tr.total_frames
    updates = OffPolicyUpdates(learner, replay, tr, counters) if off_policy else None
    collector = UAVCollector(
        env,
        policy,
        frames_per_batch=tr.frames_per_batch,
        total_frames=tr.total_frames,
        init_random_frames=tr.init_random_frames if off_policy else 0,
        # not "loc"/"scale": the random warm-up does not write them, and a batch that straddles
        # init_random_frames would then stack steps with different keys
        keep_keys=TRANSITION_KEYS,
        seed=int(cfg.seed),
        between=updates.run if updates is not None else None,
        on_step=updates.add if updates is not None else None,
        overlap=tr.overlap_advice,
    )
    last_eval: dict[str, float] = {}
    if ckpt:
        learner.load_state_dict(ckpt["learner"])
        collector.load_state_dict(ckpt["collector"])
        if replay is not None and ckpt.get("replay_buffer") is not None:
            replay.load_state_dict(ckpt["replay_buffer"])
        counters.update(ckpt["counters"])
        last_eval = dict(ckpt.get("last_eval", {}))
        set_rng_state(ckpt["rng"])  # last: building the modules above drew from the global RNG

    def checkpoint(final: bool = False) -> Path:
        # a finished run keeps its networks, not its buffer (gigabytes), unless asked to
        keep_replay = tr.checkpoint_replay_buffer and (not final or tr.keep_replay_at_end)
        state = {
            "learner": learner.state_dict(),
            "collector": collector.state_dict(),
            "replay_buffer": replay.state_dict() if (replay is not None and keep_replay) else None,
            "rng": rng_state(),
            "counters": dict(counters),
            "last_eval": dict(last_eval),
            "logger": logger.state_dict(),
            "config": _resolved(cfg),
        }
        path = save_checkpoint(state, run_dir, keep=tr.keep_checkpoints)
        if final and not keep_replay:
            (path.parent / "prev.pt").unlink(missing_ok=True)  # the one before still holds a buffer
        return path

    def evaluate(frames: int) -> dict[str, float]:
        out = train_eval_dir(run_dir, frames)
        agg = evaluator.run(deterministic_actor(learner), out, title=f"{cfg.name} @ {frames} frames")
        logger.log_metrics({**_prefixed("eval", agg), "eval/episodes_trained": counters["episodes"]}, step=frames)
        logger.log_images(_trajectory_images(out), step=frames)
        return agg

    def budget_spent() -> bool:
        """The frame budget, or the episode budget (paper: 4000 episodes) when one is set."""
        episodes_done = tr.total_episodes is not None and counters["episodes"] >= tr.total_episodes
        return counters["frames"] >= tr.total_frames or episodes_done

    bar = tqdm(total=tr.total_frames, initial=counters["frames"], unit="frame", disable=not tr.progress_bar, dynamic_ncols=True)
    t_start, frames_start, wall_start = time.perf_counter(), counters["frames"], float(counters["wall_s"])
    train_logs: dict[str, float] = {}
    timing = dict(collector.timing)
    t_iter = time.perf_counter()  # collection and updates count as training time; evaluation does not
    try:
        for batch in () if budget_spent() else collector:
            t_batch = time.perf_counter()
            frames = collector.frames
            n_new = batch.numel()
            counters["frames"] = frames
            counters["batches"] += 1
            counters["episodes"] += int(batch.get(("next", "done")).sum())
            counters["wall_s"] = wall_start + (t_batch - t_start)  # training wall clock over every resumed part
            if off_policy:
                noise = getattr(learner, "noise", None)
                if noise is not None and hasattr(noise, "step"):
                    noise.step(n_new)  # DDPG: anneal the exploration noise by frames
                if budget_spent():
                    updates.flush()  # the last step's gradient steps have no next step to run in
                train_logs = updates.logs
            else:
                train_logs = learner.update(batch)
                counters["updates"] += 1
            # the updates ran inside the batch's steps (off-policy) or just now (on-policy)
            t_update = collector.timing["between_s"] - timing["between_s"] + (time.perf_counter() - t_batch)
            t_overlap = collector.timing["overlap_s"] - timing["overlap_s"]
            timing = dict(collector.timing)
            counters["update_s"] += t_update
            counters["overlap_s"] += t_overlap

            if counters["batches"] % tr.log_every_batches == 0:
                _, episodes = collector.episode_metrics()
                elapsed = time.perf_counter() - t_start
                metrics = {
                    **_prefixed("train", train_logs),
                    **_prefixed("episode", episodes),
                    **(_prefixed("override", collector.override_stats(reset=True)) if has_advisor else {}),
                    "time/fps": (frames - frames_start) / max(elapsed, 1e-9),
                    "time/update_s": t_update,
                    "time/update_overlap_s": t_overlap,
                    "train/updates": counters["updates"],
                    "train/episodes": counters["episodes"],
                    "train/replay_size": len(replay) if replay is not None else 0,
                }
                logger.log_metrics(metrics, step=frames)
            counters["train_s"] = counters.get("train_s", 0.0) + (time.perf_counter() - t_iter)
            finished = budget_spent()
            if frames >= counters["next_eval"] or finished:
                last_eval = evaluate(frames)
                counters["last_eval_frames"] = frames
                every = tr.eval_every_frames or tr.total_frames
                counters["next_eval"] = (frames // every + 1) * every
            if frames >= counters["next_ckpt"] or finished:
                every = tr.checkpoint_every_frames or tr.total_frames
                counters["next_ckpt"] = (frames // every + 1) * every
                checkpoint(final=finished)
            bar.update(n_new)
            post = {"fps": f"{(frames - frames_start) / max(time.perf_counter() - t_start, 1e-9):.0f}"}
            post.update({k: f"{last_eval[k]:.3f}" for k in ("DCR", "CR", "SLR") if k in last_eval})
            bar.set_postfix(post, refresh=False)
            t_iter = time.perf_counter()
            if finished:
                break
    finally:
        bar.close()
        collector.shutdown()

    if counters.get("last_eval_frames") != counters["frames"]:  # resumed after the final batch
        last_eval = evaluate(counters["frames"])
        counters["last_eval_frames"] = counters["frames"]
    final = {
        "frames": counters["frames"],
        "episodes": counters["episodes"],
        "updates": counters["updates"],
        "wall_s": round(float(counters["wall_s"]), 1),
        **_prefixed("eval", last_eval),
        "actor_param_sum": float(sum(p.detach().double().abs().sum() for p in learner.actor.parameters())),
    }
    cost = policy.cost() if has_advisor else {}  # training's: measured, not replayed; before the advised evaluation
    if has_advisor:
        final.update(_prefixed("override", _deterministic_counts(policy.run_totals())))
        final.update(_prefixed("cost", cost))
        if tr.eval_with_advisor:
            final.update(_advised_evaluation(policy, evaluator, run_dir, tr, str(cfg.name)))
    t_base = time.perf_counter()
    if tr.baselines:
        final.update(_baselines(cfg, env_cfg, evaluator, run_dir))
    dump_json(run_dir / "final_metrics.json", final)
    baselines_s = time.perf_counter() - t_base
    train_s = counters.get("train_s", 0.0)
    write_summary(run_dir, {
        "name": str(cfg.name), "controller": "learner", "run_dir": str(run_dir), "frames": counters["frames"],
        "full_run_frames": _full_run_frames(), "updates": counters["updates"], "train_s": train_s,
        "fps": counters["frames"] / train_s if train_s else None,
        "update_s": counters["update_s"], "overlap_s": counters["overlap_s"], "baselines_s": baselines_s,
        "eval_episodes": len(evaluator.scenarios),
        "metrics": {f"{cfg.name} (trained actor)": last_eval, **_advised_row(final, str(cfg.name)), **_baseline_rows(final)},
        "advisor_kind": str(cfg.advisor.kind), "override": policy.run_totals() if has_advisor else None,
        "cost": {**cost, "currency": policy.currency()} if cost else None,
        "pictures": _pictures(run_dir, counters["frames"]),
    })
    log.info("%s done at %d frames: %s", cfg.name, counters["frames"], {k: round(last_eval.get(k, float("nan")), 4) for k in PAPER_METRICS})
    return final


def _trajectory_images(eval_dir: Path) -> dict[str, Path]:
    return {f"eval/trajectory_{p.stem.rsplit('_', 1)[-1]}": p for p in sorted(eval_dir.glob("trajectory_*.png"))}


@hydra.main(config_path=str(CONF_DIR), config_name="config", version_base="1.3")
def main(cfg: DictConfig) -> None:
    # one INFO line per HTTP request buries the progress bar; the LLM counters are in the logs
    logging.getLogger("httpx").setLevel(logging.WARNING)
    final = run(cfg)
    summary = (run_dir_of(resolve_checkpoint(cfg.resume)) if cfg.resume else Path(cfg.run_dir)) / "summary.json"
    if summary.is_file():
        print(format_summary(json.loads(summary.read_text())))
    else:
        print(json.dumps(final, indent=1))


if __name__ == "__main__":
    import sys

    from uavlae.llm.config import refuse_secret_overrides

    refuse_secret_overrides(sys.argv)  # before Hydra writes the command line into the run folder
    main()
