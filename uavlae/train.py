"""``python -m uavlae.train +exp=NAME``: train (or, for ``heuristic`` / ``llm`` / ``random``, evaluate) one method.

The loop (:func:`train`), top to bottom, in the shape of TorchRL's ``sota-implementations``::

    while the frame budget is not spent:
        off-policy (sac, ddpg, crossq), one env step at a time for a batch of T steps:
            collector.begin_step()      the triggered rows' advice requests go out
            updates.pay()               the gradient steps owed so far run while they are in flight
            collector.finish_step()     the (updated) actor acts, the answers are merged, the env steps
            updates.store()             the transition goes to the replay buffer; utd_ratio * B steps are owed
        on-policy (ppo, cpo, wang, theile): T collector.step()s, then learner.update(batch)
        log the batch; evaluate the actor alone every eval_every_frames; checkpoint every
        checkpoint_every_frames (and when SIGTERM or SIGINT asks the run to stop)
    at the end: the owed gradient steps, a final evaluation, the actor with its advisor (advised
    runs), the heuristic and a random policy on the same set (``trainer.baselines``),
    final_metrics.json and a summary for the reader

Every off-policy method gets the same schedule (``sac`` and ``sac_llm`` differ only in who
acts), and it does not depend on when the answers arrive: with ``llm.cache_mode=replay_only``
a run replays exactly, and ``trainer.overlap_advice=false`` (the updates before the requests
go out) gives the same numbers.

The run folder belongs to this process while it runs, and what the command does with it (a new
run, a resumed one, nothing because it is finished) is decided in one place,
:func:`uavlae.lifecycle.plan`. ``run(cfg)`` is importable (the tests call it in-process) and
returns the final metrics. ``resume=RUN_DIR_OR_CHECKPOINT`` continues a run exactly: same
config, frames, RNG states, replay buffer, CSV files and wandb run.
"""

from __future__ import annotations

import json
import logging
import sys
import time
import uuid
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import hydra
import torch
from omegaconf import DictConfig, OmegaConf
from tensordict import TensorDictBase

from uavlae.algos import OFF_POLICY
from uavlae.checkpoint import (LAST, checkpoint_dir, resolve_checkpoint, rng_state, run_dir_of, save_best,
                               save_checkpoint, seed_everything, set_rng_state)
from uavlae.collect import TRANSITION_KEYS, UAVCollector, make_replay_buffer
from uavlae.envs import make_env_config
from uavlae.envs.metrics import PAPER_METRICS
from uavlae.evaluate import (  # noqa: F401  (evaluate_controller: re-exported, the controllers' evaluation lived here)
    Evaluation,
    eval_set_path,
    evaluate_controller,
    fly_baselines,
    load_or_make_eval_set,
    make_evaluation,
    prefixed,
    trajectory_images,
)
from uavlae.factories import (
    CONF_DIR,
    HeuristicGroup,
    dump_json,
    make_env,
    make_learner,
    make_policy,
    make_safety_filter,
    make_trainer_config,
    check_device,
    validate_config,
)
from uavlae.entry import ERROR_FILE, recorded, refused_in_job
from uavlae.errors import ConfigError
from uavlae.files import atomic_write, finite, train_eval_dir
from uavlae.lifecycle import (RESUMABLE_KEYS, GracefulStop, Plan, RunFolder, RunStopped, StopRequested, flatten_keys,
                              lock_name, plan)
from uavlae.policies.safety import FilteredPolicy, SafetyFilter
from uavlae.policies.sampling import eval_actor
from uavlae.preflight import check_llm, start_llm
from uavlae.progress import progress_for
from uavlae.rules import run_problems
from uavlae.runlog import make_logger, redact_secrets, route_library_output, run_metadata, trim_csv_scalars
from uavlae.selection import selection_score
from uavlae.summary import advised_row, baseline_rows, format_summary, full_run_frames, pictures, write_summary

log = logging.getLogger(__name__)

# What the replay buffer keeps of a transition (the collector already dropped the raw state).
REPLAY_KEYS = (
    "observation", "action", "action_source", "advice", "advice_ok",  # the teacher's labels: advisor.label_all
    ("next", "observation"), ("next", "reward"), ("next", "cost"), ("next", "done"),
    ("next", "terminated"), ("next", "truncated"),
)


# ---------------------------------------------------------------------------- config


def _resolved(cfg: DictConfig) -> dict[str, Any]:
    return redact_secrets(OmegaConf.to_container(cfg, resolve=True))  # type: ignore[arg-type]


def command_line_keys(cfg: DictConfig, overrides: Sequence[str] | None = None) -> list[str]:
    """The keys a command line sets: where ``cfg`` differs from the default config, and every
    key ``overrides`` names (a value typed equal to its default still counts)."""
    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    if GlobalHydra.instance().is_initialized():
        default = compose("config")
    else:
        with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
            default = compose("config")
    want = flatten_keys(OmegaConf.to_container(cfg, resolve=True))
    base = flatten_keys(OmegaConf.to_container(default, resolve=True))
    keys = {k for k in set(want) | set(base) if want.get(k) != base.get(k) and not k.startswith("hydra.")}
    for o in overrides or ():
        key = o.split("=", 1)[0].lstrip("+~")
        keys.update(k for k in want if k == key or k.startswith(key + "."))
    return sorted(keys)


def check_run(cfg: DictConfig, budgets: bool = True) -> None:
    """What makes a run compute something else than it says, refused before anything is
    written with one :class:`ConfigError` that names each key: a value out of its range, the
    rules of meaning (:mod:`uavlae.rules`: no GE, no GE that could be served, ...), a frame
    budget below one collector batch or below the random warm-up (``budgets``; a resume checks
    them once merged with the recorded run), and a device this machine does not have."""
    try:
        validate_config(cfg)
        check_device(cfg.device)
    except ConfigError:
        raise
    except ValueError as err:  # the config models' own checks: each names its key
        raise ConfigError(str(err)) from None
    tr = make_trainer_config(cfg.trainer)
    problems = run_problems(cfg, make_env_config(cfg.env))
    if cfg.controller == "learner" and budgets and tr.total_frames < tr.frames_per_batch:
        problems.append(f"trainer.total_frames={tr.total_frames} is below one collector batch "
                        f"(trainer.frames_per_batch={tr.frames_per_batch}): raise the budget or lower the batch")
    if (cfg.controller == "learner" and budgets and cfg.algo.name in OFF_POLICY
            and tr.init_random_frames >= tr.total_frames):
        problems.append(f"trainer.total_frames={tr.total_frames} does not exceed the random warm-up "
                        f"(trainer.init_random_frames={tr.init_random_frames}): no gradient step would run")
    if problems:
        raise ConfigError(problems[0] if len(problems) == 1 else
                          f"the config breaks {len(problems)} rules:\n  " + "\n  ".join(problems))


def _fingerprint(cfg: DictConfig) -> dict[str, Any]:
    """What an LLM-alone evaluation's progress files must match: the config, less how it is
    split into invocations and processes, and where it lies."""
    c = OmegaConf.create(_resolved(cfg))
    for key in (*RESUMABLE_KEYS, "resume", "experiment.reuse"):
        if OmegaConf.select(c, key) is not None:
            OmegaConf.update(c, key, None, merge=False)
    out = OmegaConf.to_container(c)
    out.pop("run_dir", None)  # type: ignore[union-attr]
    return out  # type: ignore[return-value]


# ---------------------------------------------------------------------------- the scheduled updates


class Updates:
    """The off-policy schedule: each env step's ``B`` transitions go to the replay buffer and,
    once ``frames >= init_random_frames`` and the buffer holds a sample, owe ``utd_ratio * B``
    gradient steps (fractions carried in ``counters["utd_debt"]``), paid at the next env step
    while its advice is in flight; :meth:`flush` pays what is left at the end of training."""

    def __init__(self, learner: Any, replay: Any, tr: Any, counters: dict[str, Any]):
        self.learner, self.replay, self.tr, self.counters = learner, replay, tr, counters
        self.logs: dict[str, float] = {}
        self.seconds = self.overlap_seconds = 0.0  # in this batch

    def store(self, transition: TensorDictBase) -> None:
        self.replay.extend(transition.select(*REPLAY_KEYS, strict=False).reshape(-1))
        frames = self.counters["frames"] + transition.batch_size[0]
        self.counters["frames"] = frames
        if frames >= self.tr.init_random_frames and len(self.replay) >= self.tr.batch_size:
            self.counters["utd_debt"] += self.tr.utd_ratio * transition.batch_size[0]

    def pay(self, in_flight: Any = None) -> None:
        """The gradient steps owed so far; ``in_flight``: the step whose advice is out, to count
        how much of this work ran before its answers arrived."""
        t0 = time.perf_counter()
        self.learner.anneal(self.counters["frames"])
        n = int(self.counters["utd_debt"])
        self.counters["utd_debt"] -= n
        for _ in range(n):
            self.logs = self.learner.update(self.replay.sample())
        self.counters["updates"] += n
        t1 = time.perf_counter()
        self.seconds += t1 - t0
        pending = in_flight.pending if in_flight is not None else None
        if pending is not None and pending.handle is not None:
            done = pending.done_at
            self.overlap_seconds += max(0.0, min(t1, done if done is not None else t1) - t0)

    def flush(self) -> None:
        self.pay()


# ---------------------------------------------------------------------------- a training run


@dataclass
class Training:
    """A training run's parts and bookkeeping; :func:`train` is its loop."""

    cfg: DictConfig
    tr: Any  # the validated trainer config
    run_dir: Path
    logger: Any
    evaluation: Evaluation
    env: Any
    learner: Any
    policy: Any
    collector: UAVCollector
    replay: Any
    updates: Updates | None
    counters: dict[str, Any]
    safety: SafetyFilter | None = None  # the deployed pilot's filter (safety_filter.mode not off)
    bar: Any = None
    last_eval: dict[str, float] = field(default_factory=dict)
    train_logs: dict[str, float] = field(default_factory=dict)
    frames_start: int = 0
    t_start: float = field(default_factory=time.perf_counter)

    @property
    def frames(self) -> int:
        return int(self.counters["frames"])

    def budget_spent(self) -> bool:
        """The frame budget, or the episode budget (paper: 4000 episodes) when one is set."""
        tr = self.tr
        episodes_done = tr.total_episodes is not None and self.counters["episodes"] >= tr.total_episodes
        return self.frames >= tr.total_frames or episodes_done

    def collect_off_policy(self) -> TensorDictBase:
        """T env steps, the scheduled gradient steps inside each (module doc)."""
        steps, overlap = [], self.tr.overlap_advice
        for _ in range(self.collector.T):
            if not overlap:
                self.updates.pay()
            handle = self.collector.begin_step()
            if overlap:
                self.updates.pay(handle)
            transition = self.collector.finish_step(handle)
            self.updates.store(transition)
            steps.append(transition)
            self.bar.update(transition.batch_size[0])
        if self.budget_spent():
            self.updates.flush()  # the last step's gradient steps have no next step to run in
        return self.collector.batch_of(steps)

    def collect_on_policy(self) -> TensorDictBase:
        """T env steps: the rollout an on-policy update learns from."""
        steps = []
        for _ in range(self.collector.T):
            steps.append(self.collector.step())
            self.bar.update(self.collector.B)
        return self.collector.batch_of(steps)

    def update_on_policy(self, batch: TensorDictBase) -> float:
        t0 = time.perf_counter()
        self.learner.anneal(self.collector.frames)
        self.train_logs = self.learner.update(batch)
        self.counters["updates"] += 1
        return time.perf_counter() - t0

    def log_batch(self, batch: TensorDictBase, update_s: float, overlap_s: float) -> None:
        c = self.counters
        c["frames"] = self.collector.frames
        c["batches"] += 1
        c["episodes"] += int(batch.get(("next", "done")).sum())
        c["update_s"] += update_s
        c["overlap_s"] += overlap_s
        if c["batches"] % self.tr.log_every_batches:
            return
        _, episodes = self.collector.episode_metrics()
        elapsed = time.perf_counter() - self.t_start
        advised = self.cfg.advisor.kind != "none"
        self.logger.log_metrics({
            **prefixed("train", self.train_logs), **prefixed("episode", episodes),
            **(prefixed("override", self.collector.override_stats(reset=True)) if advised else {}),
            **(prefixed("safety", self.collector.safety_stats.snapshot(reset=True)) if self.collector.safety else {}),
            "time/fps": (self.frames - self.frames_start) / max(elapsed, 1e-9), "time/update_s": update_s,
            "time/update_overlap_s": overlap_s, "train/updates": c["updates"], "train/episodes": c["episodes"],
            "train/replay_size": len(self.replay) if self.replay is not None else 0,
        }, step=self.frames)

    def evaluate(self) -> None:
        """The deployed policy on the evaluation set (``eval/``): the actor alone, or with
        ``safety_filter`` on, the actor through its filter, and then the actor alone beside it
        (``eval_actor/``)."""
        out = train_eval_dir(self.run_dir, self.frames)
        title = f"{self.cfg.name} @ {self.frames} frames"
        before = rng_state()
        try:
            self._fly_evaluation(out, title)
        except StopRequested:  # thrown away: the RNGs as they were, so a resume evaluates from the same state
            set_rng_state(before)
            raise
        if self.tr.keep_best:
            self.keep_if_best()
        self.logger.log_metrics({**prefixed("eval", self.last_eval), "eval/episodes_trained": self.counters["episodes"],
                                 "eval/train_wall_s": float(self.counters["wall_s"])}, step=self.frames)
        self.logger.log_images(trajectory_images(out), step=self.frames)
        self.counters["last_eval_frames"] = self.frames
        every = self.tr.eval_every_frames or self.tr.total_frames
        self.counters["next_eval"] = (self.frames // every + 1) * every

    def keep_if_best(self) -> None:
        """``checkpoints/best.pt`` when this evaluation's :func:`selection_score` beats every
        earlier one (ties keep the earlier); the best so far is in the counters, so a resumed
        run goes on comparing against it."""
        score = selection_score(self.last_eval)
        best = self.counters.get("best_score")
        if best is not None and not score > best:
            return
        self.counters["best_score"], self.counters["best_frames"] = score, self.frames
        save_best({"learner": self.learner.state_dict(), "counters": dict(self.counters),
                   "last_eval": dict(self.last_eval), "config": _resolved(self.cfg)}, self.run_dir)

    def evaluation_owed(self) -> bool:
        """An evaluation a stop cut short before this run's last checkpoint: due, not made."""
        return self.counters.get("last_eval_frames") != self.frames and self.frames >= self.counters["next_eval"]

    def _fly_evaluation(self, out: Path, title: str) -> None:
        # the actor as it is deployed (trainer.eval_actor): its mean action or a draw from its policy
        actor = eval_actor(self.learner.actor, str(self.tr.eval_actor), int(self.tr.eval_seed))
        if self.safety is None:
            flight = self.evaluation.fly(actor, out, title=title)
            self.last_eval = flight.metrics
        else:
            pilot = FilteredPolicy(actor, self.safety)
            flight = self.evaluation.fly(pilot, out, title=f"{title}, filtered")
            self.last_eval = {**flight.metrics, **flight.stats}
            alone = self.evaluation.fly(actor, out / "actor_alone", title=f"{title}, actor alone")
            self.last_eval.update(prefixed("actor", alone.metrics))

    def checkpoint(self, final: bool = False) -> Path:
        """An atomic checkpoint at this batch boundary (exact resume). A finished run keeps its
        networks and, with ``trainer.keep_replay_at_end``, its buffer (to extend it later)."""
        tr = self.tr
        every = tr.checkpoint_every_frames or tr.total_frames
        self.counters["next_ckpt"] = (self.frames // every + 1) * every
        keep_replay = tr.checkpoint_replay_buffer and (not final or tr.keep_replay_at_end)
        state = {
            "learner": self.learner.state_dict(), "collector": self.collector.state_dict(),
            "replay_buffer": self.replay.state_dict() if (self.replay is not None and keep_replay) else None,
            "rng": rng_state(), "counters": dict(self.counters), "last_eval": dict(self.last_eval),
            "logger": self.logger.state_dict(), "config": _resolved(self.cfg),
        }
        path = save_checkpoint(state, self.run_dir, keep=tr.keep_checkpoints)
        if final and not keep_replay:
            (path.parent / "prev.pt").unlink(missing_ok=True)  # the one before still holds a buffer
        return path

    def progress_note(self) -> None:
        self.bar.batch_done(self.frames, self.last_eval, self.counters.get("last_eval_frames"))


def train(t: Training, stop: GracefulStop) -> dict[str, Any]:
    """The local LLM server's start (advised runs), the training loop (module doc) and the final
    evaluations; returns the final metrics. The advisor stays up until the end: the actor flies
    with it once more after training."""
    try:
        start_llm(t.policy, stop)
        t.bar = progress_for(t.cfg, t.tr, t.frames)  # a bar on a terminal, else a line every progress_every_s
        try:
            _loop(t, stop)
        finally:
            t.bar.close()
        return finish(t)
    finally:
        t.collector.shutdown()


def _stopped(t: Training, signum: int) -> RunStopped:
    return RunStopped(f"stopped by signal {signum} at {t.frames:,} frames after a checkpoint; continue "
                      f"with: python -m uavlae.train resume={t.run_dir}", int(signum))


def _evaluate_or_stop(t: Training, finished: bool) -> None:
    """The evaluation due at this batch's end; a stop during it keeps the batch (a checkpoint
    without the evaluation, which a resume makes first) and ends the run."""
    try:
        t.evaluate()
    except StopRequested as s:
        t.checkpoint(final=finished)
        raise _stopped(t, s.signum) from None


def _loop(t: Training, stop: GracefulStop) -> None:
    wall0, t0 = float(t.counters["wall_s"]), time.perf_counter()
    if t.evaluation_owed() and not t.budget_spent():  # the one a stop cut short (the last is finish's)
        _evaluate_or_stop(t, False)
    while not t.budget_spent():
        t_batch = time.perf_counter()
        if t.updates is not None:
            t.updates.seconds = t.updates.overlap_seconds = 0.0
            batch = t.collect_off_policy()
            update_s, overlap_s, t.train_logs = t.updates.seconds, t.updates.overlap_seconds, t.updates.logs
        else:
            batch = t.collect_on_policy()
            update_s, overlap_s = t.update_on_policy(batch), 0.0
        t.counters["wall_s"] = wall0 + (time.perf_counter() - t0)  # over every resumed part
        t.counters["train_s"] = t.counters.get("train_s", 0.0) + (time.perf_counter() - t_batch)
        t.log_batch(batch, update_s, overlap_s)
        finished = t.budget_spent()
        if t.frames >= t.counters["next_eval"] or finished:
            _evaluate_or_stop(t, finished)
        if t.frames >= t.counters["next_ckpt"] or finished or stop.requested:
            t.checkpoint(final=finished)
        t.progress_note()
        if stop.requested and not finished:
            raise _stopped(t, int(stop.signum))


def finish(t: Training) -> dict[str, Any]:
    """After the last batch: the final evaluation (unless the last batch made it), the actor
    with its advisor, the baselines, ``final_metrics.json`` and ``summary.json``. A stop during
    any of them ends the run with the resume line: the checkpoint holds the finished training,
    and the resumed run makes these evaluations again."""
    try:
        return _finish(t)
    except StopRequested as s:
        raise RunStopped(f"stopped by signal {s.signum} during the final evaluations, after training {t.frames:,} "
                         f"frames (checkpointed); continue with: python -m uavlae.train resume={t.run_dir}",
                         s.signum) from None


def _finish(t: Training) -> dict[str, Any]:
    tr, cfg, c = t.tr, t.cfg, t.counters
    if c.get("last_eval_frames") != t.frames:  # resumed after the final batch
        t.evaluate()
    final = {
        "frames": t.frames, "episodes": c["episodes"], "updates": c["updates"], "wall_s": round(float(c["wall_s"]), 1),
        **prefixed("eval", t.last_eval),
        "actor_param_sum": float(sum(p.detach().double().abs().sum() for p in t.learner.actor.parameters())),
    }
    advised = cfg.advisor.kind != "none"
    # training's, measured (not replayed): before the evaluation with the advisor adds its own calls
    cost = t.policy.cost() if advised else {}
    totals = t.policy.run_totals() if advised else None
    if t.collector.safety is not None:
        final.update(prefixed("safety/train", t.collector.safety_totals.snapshot()))
    if tr.keep_best and "best_frames" in c:
        final.update({"best/frames": c["best_frames"], "best/score": c["best_score"]})
    advised_eval = None
    if advised:
        final.update(prefixed("override", _deterministic_counts(totals)))  # type: ignore[arg-type]
        final.update(prefixed("cost", cost))
        if tr.eval_with_advisor:
            final.update(_advised_evaluation(t))
            advised_eval = _advised_eval_counts(tr, final, totals, t.policy.run_totals())  # type: ignore[arg-type]
    t_base = time.perf_counter()
    if tr.baselines:
        final.update(fly_baselines(cfg, t.evaluation, t.run_dir))
    dump_json(t.run_dir / "final_metrics.json", final)
    train_s = c.get("train_s", 0.0)
    write_summary(t.run_dir, {
        "name": str(cfg.name), "controller": "learner", "run_dir": str(t.run_dir), "frames": t.frames,
        "full_run_frames": full_run_frames(), "updates": c["updates"], "train_s": train_s,
        "fps": t.frames / train_s if train_s else None, "update_s": c["update_s"], "overlap_s": c["overlap_s"],
        "baselines_s": time.perf_counter() - t_base, "eval_episodes": len(t.evaluation.scenarios),
        "metrics": {**_actor_rows(t), **advised_row(final, str(cfg.name)), **baseline_rows(final)},
        "advisor_kind": str(cfg.advisor.kind), "override": totals,
        "cost": {**cost, "currency": t.policy.currency()} if cost else None, "advised_eval": advised_eval,
        "pictures": pictures(t.run_dir, t.frames),
    })
    log.info("%s done at %d frames: %s", cfg.name, t.frames,
             {k: round(t.last_eval.get(k, float("nan")), 4) for k in PAPER_METRICS})
    return final


def _actor_rows(t: Training) -> dict[str, dict[str, float]]:
    """The summary's rows of the trained actor: alone, or through its safety filter and alone."""
    if t.safety is None:
        return {f"{t.cfg.name} (trained actor)": t.last_eval}
    alone = {k.removeprefix("actor/"): v for k, v in t.last_eval.items() if k.startswith("actor/")}
    pilot = {k: v for k, v in t.last_eval.items() if not k.startswith(("actor/", "safety/"))}
    return {f"{t.cfg.name} (actor + safety filter)": pilot, f"{t.cfg.name} (actor alone)": alone}


def _deterministic_counts(totals: dict[str, Any]) -> dict[str, Any]:
    """The override's run counters that a replay reproduces: no timings, none of the
    advisor's transport counts (a replayed answer is a cache hit, a live one a call)."""
    return {k: v for k, v in totals.items()  # the student learns from the answers alone: replayed exactly
            if (not k.startswith("advisor/") or k.startswith("advisor/student/")) and not k.endswith("_s")}


def _advised_evaluation(t: Training) -> dict[str, float]:
    """The actor *with* its advisor on the same evaluation set as the actor alone: the
    override at its full trigger (no phase-out), the actor acting as it is evaluated, at most
    ``trainer.eval_advisor_max_calls`` rows asked. Beside ``eval/``, this tells what the actor
    owes to its advisor. A filtered run flies it through its filter, as its pilot, so the two
    compare. Training state is untouched (``OverridePolicy.advised``)."""
    flyer = t.policy if t.safety is None else FilteredPolicy(t.policy, t.safety)
    # the actor acts as in the evaluation without the advisor (trainer.eval_actor), from the
    # start of the same noise stream, so the two rows differ by the advisor alone
    actor = eval_actor(t.learner.actor, str(t.tr.eval_actor), int(t.tr.eval_seed))
    with t.policy.advised(max_calls=t.tr.eval_advisor_max_calls, actor=None if actor is t.learner.actor else actor):
        flight = t.evaluation.fly(flyer, t.run_dir / "eval" / "with_advisor", title=f"{t.cfg.name} with its advisor")
    # who answered there: the LLM through its student answers this evaluation too (from the cache
    # where it asked the same before), so its share here is the evaluation's own cost
    keep = ("trigger_rate", "advised_fraction", "advice_fail_rate", "actor_gap", "actor_agree", "triggered",
            "advised", "budget_skipped", "frames", "source/llm", "source/student", "source/fallback")
    safety = {k.removeprefix("safety/"): v for k, v in flight.stats.items() if k.startswith("safety/")}
    return {**prefixed("advised", flight.metrics), **prefixed("advised/override", {k: flight.stats[k] for k in keep}),
            **prefixed("advised/safety", safety)}


def _advised_eval_counts(tr: Any, final: dict[str, Any], before: dict[str, Any],
                         after: dict[str, Any]) -> dict[str, Any]:
    """The evaluation with the advisor for the summary: its budget, its triggered rows, those it
    asked and those the budget left to the actor, and the LLM's rows and HTTP calls it cost (the
    advisor's counters after it less before: the training's stay apart)."""
    out = {"max_calls": tr.eval_advisor_max_calls,
           **{k: final.get(f"advised/override/{k}") for k in ("triggered", "advised", "budget_skipped")}}
    for k in ("requests", "calls"):
        out[f"llm_{k}"] = float(after.get(f"advisor/{k}", 0) or 0) - float(before.get(f"advisor/{k}", 0) or 0)
    return out



# ---------------------------------------------------------------------------- building a run


def build_training(cfg: DictConfig, run_dir: Path, logger: Any, evaluation: Evaluation,
                   ckpt: dict[str, Any] | None) -> Training:
    """The env, learner, collection policy, replay buffer and collector of ``cfg``, restored
    from ``ckpt`` when resuming."""
    tr = make_trainer_config(cfg.trainer)
    seed = int(cfg.seed)
    seed_everything(seed)
    env = make_env(cfg.env, tr.env_batch_size, seed=seed, device=cfg.device, compile_step=tr.compile_env)
    learner = make_learner(cfg.algo, env)
    env_cfg = make_env_config(cfg.env)
    policy = make_policy(cfg.advisor, learner.behaviour, env_cfg, seed=seed, heuristic=HeuristicGroup.of(cfg),
                         llm_cfg=cfg.llm)
    safety = make_safety_filter(cfg.get("safety_filter"), env_cfg)
    in_training = safety is not None and safety.cfg.mode == "train_and_deploy"
    replay = make_replay_buffer(tr.replay_capacity, tr.batch_size, cfg.device, seed=seed) if learner.off_policy else None
    counters: dict[str, Any] = {"frames": 0, "episodes": 0, "batches": 0, "updates": 0, "utd_debt": 0.0,
                                "next_eval": tr.eval_every_frames or tr.total_frames,
                                "next_ckpt": tr.checkpoint_every_frames or tr.total_frames,
                                "update_s": 0.0, "overlap_s": 0.0, "wall_s": 0.0}
    # not "loc"/"scale": the random warm-up does not write them, and a batch that straddles
    # init_random_frames would then stack steps with different keys
    collector = UAVCollector(env, policy, frames_per_batch=tr.frames_per_batch, total_frames=tr.total_frames,
                             init_random_frames=tr.init_random_frames if learner.off_policy else 0,
                             keep_keys=TRANSITION_KEYS, seed=seed, safety=safety if in_training else None)
    updates = Updates(learner, replay, tr, counters) if learner.off_policy else None
    t = Training(cfg, tr, run_dir, logger, evaluation, env, learner, policy, collector, replay, updates, counters,
                 safety)
    if ckpt:
        _restore(t, ckpt)
    t.frames_start = t.frames
    return t


def _restore(t: Training, ckpt: dict[str, Any]) -> None:
    if t.replay is not None and ckpt.get("replay_buffer") is None and ckpt["counters"]["frames"] < t.tr.total_frames:
        raise ConfigError(
            f"{t.run_dir}: its checkpoint holds no replay buffer (the run finished with "
            "trainer.keep_replay_at_end=false), so it cannot continue exactly; train it anew, or keep the buffer "
            "of runs meant to be extended"
        )
    t.learner.load_state_dict(ckpt["learner"])
    t.collector.load_state_dict(ckpt["collector"])
    t.collector.total_frames = t.tr.total_frames
    if t.replay is not None:
        t.replay.load_state_dict(ckpt["replay_buffer"])
    t.counters.update(ckpt["counters"])
    t.last_eval = dict(ckpt.get("last_eval", {}))
    set_rng_state(ckpt["rng"])  # last: building the modules above drew from the global RNG


def _open_run(cfg: DictConfig, run_dir: Path, ckpt: dict[str, Any] | None) -> tuple[Any, Any]:
    """Write the run's config and metadata; the logger (continuing a resumed run's) and the
    evaluation on the run's fixed set."""
    tr = make_trainer_config(cfg.trainer)
    env_cfg = make_env_config(cfg.env)
    scenarios = load_or_make_eval_set(env_cfg, eval_set_path(run_dir, tr.eval_set), tr.eval_episodes, tr.eval_seed,
                                      sample=tr.sample_eval_set or tr.eval_set is None)
    resolved = _resolved(cfg)
    dump_json(run_dir / "config.json", resolved)
    (run_dir / ERROR_FILE).unlink(missing_ok=True)  # what ended an earlier attempt: this one goes on
    yaml_text = OmegaConf.to_yaml(OmegaConf.create(resolved))
    atomic_write(run_dir / "config.yaml", lambda fh: fh.write(yaml_text.encode("utf-8")))
    meta = run_metadata(resolved)
    dump_json(run_dir / "meta.json", meta)
    run_id = ckpt["logger"]["run_id"] if ckpt else f"{cfg.name}-{uuid.uuid4().hex[:10]}"
    if ckpt:
        trim_csv_scalars(run_dir / "logs", int(ckpt["counters"]["frames"]))
    logger = make_logger(cfg, run_dir, run_id, {**resolved, "meta": meta}, resume=ckpt is not None)
    if ckpt:
        logger.load_state_dict(ckpt["logger"])
    fingerprint = _fingerprint(cfg) if cfg.controller == "llm" else None
    evaluation = make_evaluation(cfg, env_cfg, scenarios, compile_step=tr.compile_env, fingerprint=fingerprint)
    return logger, evaluation


def run(cfg: DictConfig, overrides: Sequence[str] | None = None) -> dict[str, Any]:
    """Train (or evaluate a controller) as ``cfg`` says; returns the final metrics.
    ``overrides``: the command line's ``key=value`` list, checked against a resumed run."""
    # A multirun worker runs job after job in one process: the graphs compiled for an earlier
    # job's env would count against this job's recompile limit (and fail it under fullgraph).
    torch.compiler.reset()
    keys = command_line_keys(cfg, overrides) if cfg.resume else None
    cfg = OmegaConf.create(_resolved(cfg))
    OmegaConf.set_struct(cfg, True)
    check_run(cfg, budgets=not cfg.resume)
    run_dir = run_dir_of(resolve_checkpoint(cfg.resume)) if cfg.resume else Path(cfg.run_dir)
    with RunFolder(run_dir, lock_name(cfg)) as folder:
        p = plan(cfg, keys)
        if p.kind == "done":
            log.info("%s: finished already: %s", p.cfg.name, run_dir / "final_metrics.json")
            return p.final  # type: ignore[return-value]
        if p.clean:
            folder.clean()
        cfg = p.cfg
        OmegaConf.set_struct(cfg, True)
        check_run(cfg)
        check_llm(cfg, make_env_config(cfg.env))  # an LLM that cannot answer stops the run before it writes
        if p.ckpt:
            log.info("resuming %s from %s at %d frames", cfg.name, cfg.resume, p.ckpt["counters"]["frames"])
        torch.set_num_threads(int(cfg.threads))
        with GracefulStop() as stop:  # every phase from here on: a stop is honoured (lifecycle doc)
            logger, evaluation = _open_run(cfg, run_dir, p.ckpt)
            evaluation.stop = stop
            try:
                if cfg.controller != "learner":
                    return evaluate_controller(cfg, evaluation, logger, run_dir, stop)
                return train(build_training(cfg, run_dir, logger, evaluation, p.ckpt), stop)
            except StopRequested as s:  # a phase with nothing to keep (a controller's flight, a server start)
                raise RunStopped(_stop_message(cfg, run_dir, s.signum), s.signum) from None
            finally:
                logger.close()


def _stop_message(cfg: DictConfig, run_dir: Path, signum: int) -> str:
    """What a stop outside the training loop's batches leaves, and the command that goes on."""
    if cfg.controller == "learner" and (checkpoint_dir(run_dir) / LAST).is_file():
        return f"stopped by signal {signum}; continue from the last checkpoint with: python -m uavlae.train resume={run_dir}"
    return f"stopped by signal {signum} before there was anything to keep; run the same command again to start over"


def reuse_state(cfg: DictConfig) -> tuple[str, dict[str, Any] | None]:
    """What :func:`uavlae.lifecycle.plan` decides for ``cfg`` (a sweep re-run): ``("done",
    final metrics)``, ``("resume", None)`` or ``("new", None)``."""
    cfg = OmegaConf.create(_resolved(cfg))
    p: Plan = plan(cfg)
    return p.kind, p.final


def _run_dir(cfg: DictConfig) -> Path:
    return run_dir_of(resolve_checkpoint(cfg.resume)) if cfg.resume else Path(cfg.run_dir)


@hydra.main(config_path="conf", config_name="config", version_base="1.3")
def main(cfg: DictConfig) -> None:
    from hydra.core.hydra_config import HydraConfig

    # one INFO line per HTTP request buries the progress bar; the LLM counters are in the logs
    logging.getLogger("httpx").setLevel(logging.WARNING)
    route_library_output(bool(OmegaConf.select(cfg, "logger.library_output", default=False)))
    hc = HydraConfig.get()
    hydra_dir = Path(hc.runtime.output_dir) if hc.output_subdir is not None else None
    with refused_in_job(), recorded(hydra_dir, lambda: _run_dir(cfg), f"{hc.job.name}.log"):
        try:
            final = run(cfg, list(hc.overrides.task))
        except RunStopped as stopped:
            print(str(stopped), file=sys.stderr)
            sys.exit(128 + stopped.signum)
    summary = _run_dir(cfg) / "summary.json"
    if summary.is_file():
        print(format_summary(json.loads(summary.read_text())))
    else:
        print(json.dumps(finite(final), indent=1))


if __name__ == "__main__":
    from uavlae.entry import command
    from uavlae.llm.config import refuse_secret_overrides

    refuse_secret_overrides(sys.argv)  # before Hydra writes the command line into the run folder
    command(main)
