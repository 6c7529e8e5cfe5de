"""Evaluation on a fixed, seeded set of scenarios (docs/model.md §5; paper §6.2); no training code.

The evaluation set is sampled once with ``trainer.eval_seed`` and saved as JSON
(``<run_dir>/eval_set.json``, or ``trainer.eval_set``), then reloaded, so every evaluation of a
run (and of every method compared on it) flies the same scenarios. A learner is evaluated by
its actor alone, deterministically (``ExplorationType.DETERMINISTIC``: the tanh of the mean; no
LLM, no heuristic, as in deployment), or with ``trainer.eval_actor=sample`` by a draw from its
policy from a seeded stream (:mod:`uavlae.policies.sampling`). Each evaluation writes the per-episode records
(``episodes.csv``), the aggregates (``metrics.json``: DCR, CR, SLR, RVR, ECR, the mean of every
reward term, ...) and a PNG of the first few trajectories.

``python -m uavlae.evaluate checkpoint=RUN_DIR_OR_FILE`` evaluates a training checkpoint, on its
run's world or on the world its command line changes (``env.ou.count.min=3 env.ou.count.max=3``:
the observation's padding stays the training one, so the same actor serves every setting).

The controllers are evaluated here too, for every entry point: :func:`evaluate_controller` (the
``heuristic``, ``llm`` and ``random`` experiments, which train nothing) and :func:`fly_baselines`
(the heuristic and a uniform-random policy on a training run's evaluation set).
"""

from __future__ import annotations

import hashlib
import json
import logging
import math
import os
import sys
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import hydra
import torch
from omegaconf import DictConfig, OmegaConf
from torchrl.envs.utils import ExplorationType, set_exploration_type

from uavlae.envs import EnvConfig, UAVEnv, make_env_config
from uavlae.envs.metrics import PAPER_METRICS, format_metrics, rollout_metrics, save_aggregates, save_records
from uavlae.envs.scenario import Scenario, load_scenarios, sample_scenarios, save_scenarios, unstack_scenarios
from uavlae.factories import (
    CONF_DIR, HeuristicGroup, make_controller, make_env, make_heuristic, make_learner, make_safety_filter,
    make_safety_filter_config,
)
from uavlae.entry import refused_in_job
from uavlae.errors import ConfigError, InputError
from uavlae.files import dump_json, train_eval_dir
from uavlae.lifecycle import GracefulStop, RunStopped, StopRequested, flatten_keys
from uavlae.llm_alone import LLMAloneEvaluation
from uavlae.policies.override import OverridePolicy
from uavlae.policies.random import UniformRandomPolicy
from uavlae.policies.safety import FilteredPolicy
from uavlae.policies.sampling import SampledActor, eval_actor
from uavlae.preflight import check_llm, start_llm
from uavlae.progress import EpisodeProgress
from uavlae.rules import world_problems
from uavlae.runlog import log_evaluation, route_library_output, run_metadata, without_hydra_output
from uavlae.summary import pictures, write_summary

log = logging.getLogger(__name__)


def eval_set_path(run_dir: str | os.PathLike[str], eval_set: str | None) -> Path:
    return Path(eval_set).expanduser() if eval_set else Path(run_dir) / "eval_set.json"


def load_or_make_eval_set(env_cfg: EnvConfig, path: str | os.PathLike[str], n: int, seed: int,
                          sample: bool = True) -> list[Scenario]:
    """The scenarios at ``path``; when the file is absent and ``sample``, ``n`` scenarios
    sampled with ``seed`` (a generator of their own: the global RNGs are untouched) and saved
    there first (absent and not ``sample``: an error naming the path)."""
    path = Path(path)
    if not path.is_file() and not sample:
        raise FileNotFoundError(
            f"trainer.eval_set={str(path)!r} does not exist; give an existing scenarios file, or set "
            "trainer.sample_eval_set=true to sample one there (trainer.eval_episodes, trainer.eval_seed)"
        )
    if path.is_file():
        try:
            scenarios = load_scenarios(path, env_cfg)
        except ValueError as err:  # the file's own fault, named with its path and the scenario
            raise InputError(str(err)) from None
        if len(scenarios) != n:
            log.info("evaluation set %s has %d scenarios (trainer.eval_episodes=%d): using the file", path, len(scenarios), n)
        return scenarios
    g = torch.Generator().manual_seed(int(seed))
    scenarios = unstack_scenarios(sample_scenarios(env_cfg, int(n), g))
    path.parent.mkdir(parents=True, exist_ok=True)
    save_scenarios(path, scenarios)
    return scenarios


class Evaluator:
    """Runs a policy over the evaluation set, one episode per scenario, all rows at once.

    Args:
        env_cfg: the world.
        scenarios: the evaluation set.
        seed: seeds the evaluation env before every evaluation (same OU motion each time).
        max_steps: step budget per episode (``None``: ``env_cfg.t_max``).
        n_plots: trajectories drawn per evaluation.
        device: where the env runs.
        compile_step: step the evaluation env through ``torch.compile`` (``UAVEnv(compile_step=True)``:
            the same outputs; a one-off compile on the first evaluation, `docs/performance.md` for its worth).
    """

    def __init__(
        self,
        env_cfg: EnvConfig,
        scenarios: list[Scenario],
        *,
        seed: int,
        max_steps: int | None = None,
        n_plots: int = 3,
        device: str | torch.device = "cpu",
        compile_step: bool = False,
    ):
        self.env_cfg = make_env_config(env_cfg)
        self.scenarios = list(scenarios)
        self.seed = int(seed)
        self.max_steps = max_steps
        self.n_plots = int(n_plots)
        self.env = UAVEnv(
            self.env_cfg,
            batch_size=len(self.scenarios),
            device=device,
            seed=self.seed,
            scenarios=self.scenarios,
            compile_step=compile_step,
        )

    def run(self, policy: Any, out_dir: str | os.PathLike[str] | None = None, *, title: str = "",
            on_step: Any = None) -> dict[str, float]:
        """Evaluate ``policy`` (deterministic exploration); write files under ``out_dir``.
        ``on_step``: called after every env step (:func:`rollout_metrics`): progress, a stop."""
        self.env.set_seed(self.seed)
        ends = EpisodeEnds(on_step)
        with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
            records, agg, trajectories = rollout_metrics(self.env, policy, max_steps=self.max_steps, cfg=self.env_cfg,
                                                         on_step=ends)
        if out_dir is not None:
            out = Path(out_dir)
            save_records(records, out / "episodes.csv")
            save_aggregates(agg, out / "metrics.json")
            self.plot(trajectories, out, title, records, ends.ge_left)
        return agg

    def plot(self, trajectories: list[torch.Tensor], out: Path, title: str = "",
             records: Mapping[str, torch.Tensor] | None = None, ge_left: torch.Tensor | None = None) -> None:
        """The first ``n_plots`` episodes, the title saying how each ended (``records``, the
        per-episode records, row by row) and each GE drawn with the data it held then
        (``ge_left``, ``[B, G]``)."""
        from uavlae.envs.render import draw_scenario, episode_outcome

        for i in range(min(self.n_plots, len(trajectories))):
            outcome = "" if records is None else f": {episode_outcome({k: v[i] for k, v in records.items()})}"
            draw_scenario(
                self.scenarios[i], [trajectories[i]], path=out / f"trajectory_{i}.png",
                title=f"{title} scenario {i}{outcome}".strip(), cfg=self.env_cfg,
                ge_left=None if ge_left is None else ge_left[i],
            )


class EpisodeEnds:
    """A rollout's ``on_step`` that keeps what the pictures need of each episode's end, the data
    each GE holds when the row's first episode ends (``ge_left``, ``[B, G]``), then calls
    ``then`` (progress, a stop)."""

    def __init__(self, then: Any = None):
        self.then = then
        self.ge_left: torch.Tensor | None = None
        self._ended: torch.Tensor | None = None

    def __call__(self, step: int, finished: torch.Tensor, next_td: Any) -> None:
        left = next_td.get(("state", "ge_remaining")).detach().cpu()
        ended = finished.detach().cpu()
        if self.ge_left is None:
            self.ge_left = left.clone()
        else:  # the rows still flying before this step take its value: the step that ended them included
            going = ~self._ended
            self.ge_left[going] = left[going]
        self._ended = ended.clone()
        if self.then is not None:
            self.then(step, finished, next_td)


@dataclass
class Flight:
    """What one evaluation gives back: the paper's metrics and the rest of the aggregates, the
    flying policy's own counters (the override's, the LLM's), and, for the LLM alone, its
    progress and cost (``complete``, ``episodes_scored`` of ``episodes_total``, ``cost``)."""

    metrics: dict[str, float]
    stats: dict[str, Any] = field(default_factory=dict)
    llm_alone: dict[str, Any] | None = None


class Evaluation:
    """The one evaluation path: a policy flies the evaluation set, all of it at once
    (:class:`Evaluator`), or, for the LLM alone, chunk by chunk under a call budget and
    resumable (:class:`uavlae.llm_alone.LLMAloneEvaluation`). Build it with
    :func:`make_evaluation`; every entry point does (training, ``uavlae.evaluate``, the
    LLM-alone table)."""

    def __init__(self, evaluator: Evaluator, *, chunked: bool = False, chunk: int | None = None,
                 budget: int | None = None, shard: int = 0, shards: int = 1,
                 fingerprint: Mapping[str, Any] | None = None, progress_every_s: float = 0.0,
                 progress_first_s: float | None = None):
        self.evaluator = evaluator
        self.chunked = chunked
        self.chunk, self.budget, self.shard, self.shards = chunk, budget, shard, shards
        self.fingerprint = dict(fingerprint or {})
        self.progress_every_s, self.progress_first_s = float(progress_every_s), progress_first_s
        self.stop: Any = None  # the command's GracefulStop, checked at every step (set by the command)

    def watch(self, title: str, policy: Any) -> EpisodeProgress:
        """A flight's progress lines and its stop (:class:`uavlae.progress.EpisodeProgress`); an
        override's lines also count the rows it asked of its advisor, against its budget."""
        def asked() -> str:
            of = "" if policy.max_calls is None else f" of {policy.max_calls}"
            return f"advisor asked for {policy.calls_used} rows{of}"

        extra = asked if isinstance(policy, OverridePolicy) else None
        return EpisodeProgress(title or "evaluation", len(self.scenarios), every_s=self.progress_every_s,
                               first_s=self.progress_first_s, stop=self.stop, extra=extra)

    @property
    def scenarios(self) -> list[Scenario]:
        return self.evaluator.scenarios

    def fly(self, policy: Any, out_dir: str | os.PathLike[str] | None, title: str = "") -> Flight:
        """``policy`` flies the set; the records, aggregates and pictures go to ``out_dir``."""
        filtered = isinstance(policy, FilteredPolicy)
        inner = policy.policy if filtered else policy  # an advised actor may fly through the filter
        override = isinstance(inner, OverridePolicy)  # its counters come back with the metrics
        if isinstance(inner, SampledActor):
            inner.reset()  # every flight draws the same noise
        if not self.chunked:
            if filtered:
                policy.reset()  # this flight's interventions only
            agg = self.evaluator.run(policy, out_dir, title=title, on_step=self.watch(title, inner))
            stats = dict(inner.counters()) if override else {}
            if filtered:  # the pilot's filter: how often and how much it acted
                stats.update({f"safety/{k}": v for k, v in policy.stats.snapshot().items()})
            return Flight(agg, stats)
        ev = self._chunked(policy, out_dir)
        res = ev.run()
        ev.write(res, title=title)
        progress = {k: res[k] for k in ("complete", "episodes_scored", "episodes_total", "chunks_done", "chunks",
                                        "in_flight_step", "cost", "records")}
        return Flight(res["metrics"], policy.run_totals() if override else {},
                      {**progress, "chunk": ev.chunk, "shard": ev.shard, "shards": ev.shards, "budget": self.budget})

    def _chunked(self, policy: Any, out_dir: str | os.PathLike[str] | None) -> LLMAloneEvaluation:
        e = self.evaluator
        if out_dir is None:
            raise ValueError("a chunked evaluation keeps its progress in its output folder; give one")
        return LLMAloneEvaluation(
            e.env_cfg, e.scenarios, policy, out_dir, seed=e.seed, chunk=self.chunk, max_steps=e.max_steps,
            budget=self.budget, fingerprint=self.fingerprint, n_plots=e.n_plots, device=e.env.device,
            shard=self.shard, shards=self.shards, stop=lambda: self.stop is not None and self.stop.requested,
        )


def make_evaluation(cfg: DictConfig, env_cfg: EnvConfig, scenarios: list[Scenario], *, compile_step: bool = False,
                    fingerprint: Mapping[str, Any] | None = None, chunked: bool | None = None) -> Evaluation:
    """The evaluation of ``cfg`` (its ``trainer`` settings) on ``scenarios``: chunked and
    budgeted when the LLM flies alone (``controller: llm``; ``chunked`` forces either way)."""
    tr = cfg.trainer
    evaluator = Evaluator(env_cfg, scenarios, seed=int(tr.eval_seed), max_steps=tr.eval_max_steps,
                          n_plots=int(tr.eval_plots), device=cfg.device, compile_step=compile_step)
    chunked = cfg.controller == "llm" if chunked is None else chunked
    return Evaluation(evaluator, chunked=chunked, chunk=tr.eval_chunk, budget=tr.llm_call_budget,
                      shard=int(tr.eval_shard), shards=int(tr.eval_shards), fingerprint=fingerprint,
                      progress_every_s=float(tr.progress_every_s), progress_first_s=tr.progress_first_s)


def make_flyer(cfg: DictConfig, env_cfg: EnvConfig, action_spec: Any, learner: Any = None,
               safety_cfg: Any = None, actor_mode: str | None = None) -> Any:
    """Who flies an evaluation: a learner's actor (no override; its mean action, the evaluator's
    deterministic exploration, or with ``actor_mode`` ``sample`` a draw from its policy seeded with
    ``trainer.eval_seed``; default ``cfg.trainer.eval_actor``), through the safety filter of
    ``safety_cfg`` when its mode is not ``off`` (the deployed pilot), else the controller
    ``cfg.controller`` names."""
    if learner is not None:
        safety = make_safety_filter(safety_cfg, env_cfg)
        mode = str(actor_mode or cfg.trainer.eval_actor)
        actor = eval_actor(learner.actor, mode, int(cfg.trainer.eval_seed))
        return actor if safety is None else FilteredPolicy(actor, safety)
    return make_controller(cfg.controller, env_cfg, seed=int(cfg.seed), heuristic=HeuristicGroup.of(cfg),
                           action_spec=action_spec, advisor_cfg=cfg.advisor, llm_cfg=cfg.llm)


# ---------------------------------------------------------------------------- the controllers


def prefixed(prefix: str, metrics: dict[str, Any]) -> dict[str, float]:
    """The finite numbers of ``metrics`` (no booleans) as floats, keyed ``<prefix>/<key>``: what a logger takes."""
    out = {}
    for k, v in metrics.items():
        if isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(float(v)):
            out[f"{prefix}/{k}"] = float(v)
    return out


def fly_baselines(cfg: DictConfig, evaluation: Evaluation, run_dir: Path) -> dict[str, float]:
    """The greedy heuristic and a uniform-random policy on the same evaluation set."""
    env_cfg = evaluation.evaluator.env_cfg
    policies = {"heuristic": make_heuristic(HeuristicGroup.of(cfg), env_cfg),
                "random": UniformRandomPolicy(evaluation.evaluator.env.action_spec, seed=int(cfg.trainer.eval_seed))}
    out: dict[str, float] = {}
    for name, policy in policies.items():
        flight = evaluation.fly(policy, run_dir / "eval" / f"baseline_{name}", title=name)
        out.update(prefixed(f"baseline/{name}", flight.metrics))
    return out


def trajectory_images(eval_dir: Path) -> dict[str, Path]:
    """An evaluation's trajectory pictures, keyed as the dashboard shows them."""
    return {f"eval/trajectory_{p.stem.rsplit('_', 1)[-1]}": p for p in sorted(eval_dir.glob("trajectory_*.png"))}


def evaluate_controller(cfg: DictConfig, evaluation: Evaluation, logger: Any, run_dir: Path,
                        stop: GracefulStop | None = None) -> dict[str, Any]:
    """``heuristic`` / ``random`` / ``llm``: no learner; the controller flies the evaluation set
    (the LLM chunk by chunk under its call budget, resumable: :mod:`uavlae.llm_alone`; a run
    paused by its budget, or by a stop, writes its final metrics with ``eval/complete`` 0, and
    the same command continues it)."""
    env_cfg = evaluation.evaluator.env_cfg
    controller = make_flyer(cfg, env_cfg, evaluation.evaluator.env.action_spec)
    out = train_eval_dir(run_dir, 0)
    t0 = time.perf_counter()
    try:
        if stop is not None:
            start_llm(controller, stop)
        flight = evaluation.fly(controller, out, title=str(cfg.name))
        totals = controller.run_totals() if cfg.controller == "llm" else None
    finally:
        if isinstance(controller, OverridePolicy):
            controller.close()  # the LLM's client, and the local server it started
    metrics = {**prefixed("eval", flight.metrics), **prefixed("override", flight.stats),
               "time/eval_s": time.perf_counter() - t0}
    la = flight.llm_alone
    if la is not None:
        progress = {k: la[k] for k in ("complete", "episodes_scored", "episodes_total", "chunks_done", "chunks")}
        metrics.update({**prefixed("eval", {k: int(v) for k, v in progress.items()}), **prefixed("llm", la["cost"]),
                        "time/eval_s": la["cost"]["wall_s"]})
    logger.log_metrics(metrics, step=0)
    logger.log_images(trajectory_images(out), step=0)
    final = {"frames": 0, **metrics}
    dump_json(run_dir / "final_metrics.json", final)
    write_summary(run_dir, {
        "name": str(cfg.name), "controller": str(cfg.controller), "run_dir": str(run_dir), "frames": 0,
        "eval_episodes": la["episodes_scored"] if la else len(evaluation.scenarios), "metrics": {str(cfg.name): flight.metrics},
        "advisor_kind": str(cfg.advisor.kind), "override": totals, "pictures": pictures(run_dir, 0),
        "llm_alone": None if la is None else {k: v for k, v in la.items() if k != "records"},
    })
    _log_controller(cfg, flight)
    if stop is not None and stop.requested and la is not None and not la["complete"]:
        raise RunStopped(f"stopped by signal {stop.signum}: the LLM alone's progress is saved (eval/complete 0); the "
                         "same command continues it", int(stop.signum))
    return final


def _log_controller(cfg: DictConfig, flight: Flight) -> None:
    agg, la = flight.metrics, flight.llm_alone
    if la is None:
        log.info("%s: %s", cfg.name, {k: round(agg[k], 4) for k in PAPER_METRICS})
        return
    state = "complete" if la["complete"] else (
        f"paused by the call budget ({la['chunks_done']}/{la['chunks']} chunks done); run the same command to continue")
    log.info("%s: %d of %d episodes scored, %s: %s", cfg.name, la["episodes_scored"], la["episodes_total"], state,
             {k: round(agg[k], 4) for k in PAPER_METRICS})


# ---------------------------------------------------------------------------- a checkpoint's world


# The entity counts of the world, as (config path, key of its count node): their padding fixes
# the observation's size, which a trained actor's input layer cannot change.
COUNT_KEYS = ("zones.n_nfz", "zones.n_rz", "zones.n_bz", "ge.count", "ou.count")


def env_overrides(cfg_env: Any, task_overrides: Sequence[str] = ()) -> dict[str, Any]:
    """What a command line changes in the world, as ``{dotted key: value}``: every key where
    ``cfg_env`` (the command line's composed ``env``) differs from ``conf/env/default.yaml``,
    and every ``env.KEY=VALUE`` the command line names (so a default value can be asked for)."""
    default = flatten_keys(OmegaConf.to_container(OmegaConf.load(CONF_DIR / "env" / "default.yaml"), resolve=True))
    given = flatten_keys(OmegaConf.to_container(cfg_env, resolve=True))
    out = {k: v for k, v in given.items() if k not in default or default[k] != v}
    for o in task_overrides:
        key = o.split("=", 1)[0].lstrip("+~")
        if key.startswith("env.") and key[4:] in given:
            out[key[4:]] = given[key[4:]]
    return out


def overridden_env(saved_env: Any, overrides: Mapping[str, Any]) -> EnvConfig:
    """The checkpoint's world with ``overrides`` applied, its observation padding kept: every
    count's ``pad`` is set to what the trained actor saw before the overrides apply, so
    ``ou.count.max=3`` evaluates three OUs in an observation padded to the training maximum.
    A count above that padding, or any change of the observation's size, is an error."""
    trained = make_env_config(saved_env)
    env = OmegaConf.create(OmegaConf.to_container(saved_env, resolve=True))
    for key in COUNT_KEYS:
        node = OmegaConf.select(env, key)
        OmegaConf.update(env, f"{key}.pad", int(node.pad if node.pad is not None else node.max), merge=False)
    for key, value in overrides.items():
        if OmegaConf.select(env, key, default="__missing__") == "__missing__":
            raise ConfigError(f"env override {key}={value!r}: the checkpoint's env has no key {key!r}")
        OmegaConf.update(env, key, value, merge=False)
    try:
        out = make_env_config(env)
    except ValueError as err:
        raise ConfigError(f"env overrides {dict(overrides)} on the checkpoint's world: {err}") from None
    obs_before, obs_after = _obs_dim(trained), _obs_dim(out)
    if obs_before != obs_after:
        raise ConfigError(
            f"env overrides {dict(overrides)} change the observation from {obs_before} to {obs_after} "
            "columns; the trained actor needs the training padding (keep env.*.pad and the feature flags)"
        )
    return out


def _obs_dim(env_cfg: EnvConfig) -> int:
    from uavlae.envs.world import ObservationLayout

    return int(ObservationLayout(env_cfg).size)


def _default_out(run_dir: Path, stem: str, frames: int, overrides: Mapping[str, Any]) -> Path:
    name = f"{stem}_frames{frames}"
    if overrides:  # another world: its own folder, named by what changed
        name += "_" + hashlib.sha1(json.dumps(sorted(overrides.items()), default=str).encode()).hexdigest()[:8]
    return run_dir / "evaluate" / name


@dataclass
class Target:
    """What ``uavlae.evaluate`` flies: a checkpoint's actor or a controller, on which world, into which folder."""

    name: str
    method: str
    env_cfg: EnvConfig
    out: Path
    frames: int = 0
    file: Path | None = None
    state: dict[str, Any] | None = None
    saved: DictConfig | None = None
    run_dir: Path | None = None
    safety: Any = None  # the safety_filter node the actor flies through (mode off: the actor alone)
    actor_mode: str = "mean"  # trainer.eval_actor: the actor's mean action or a draw from its policy


def actor_mode_of(cfg: DictConfig, saved: DictConfig | None, task_overrides: Sequence[str]) -> str:
    """How an evaluated actor acts (``trainer.eval_actor``): the command line's when it names the
    key, else the one the run was trained with (none recorded: its mean)."""
    named = any(o.split("=", 1)[0].lstrip("+~") == "trainer.eval_actor" for o in task_overrides)
    if named or saved is None:
        return str(cfg.trainer.eval_actor)
    return str(OmegaConf.select(saved, "trainer.eval_actor", default="mean"))


def safety_of(cfg: DictConfig, saved: DictConfig | None, task_overrides: Sequence[str]) -> Any:
    """The ``safety_filter`` an evaluated actor flies through: the command line's when it names
    any ``safety_filter.*`` key, else the one the run was trained with (none recorded: off)."""
    named = any(o.split("=", 1)[0].lstrip("+~").startswith("safety_filter") for o in task_overrides)
    if named or saved is None:
        return cfg.get("safety_filter")
    return saved.get("safety_filter")


def _target(cfg: DictConfig, overrides: Mapping[str, Any]) -> Target:
    """The checkpoint (a file or a run dir) and its world with the command line's env
    overrides, or an evaluation-only controller (``heuristic``, ``llm``, ``random``)."""
    from uavlae.checkpoint import load_checkpoint, run_dir_of

    ex = cfg.experiment
    if cfg.controller != "learner":
        if not ex.eval_dir:
            raise ConfigError(f"uavlae.evaluate +exp={cfg.name} (a controller) needs experiment.eval_dir=PATH")
        return Target(str(cfg.name), str(ex.method), make_env_config(cfg.env), Path(ex.eval_dir))
    if not cfg.checkpoint:
        raise ConfigError("uavlae.evaluate needs checkpoint=PATH (a checkpoint file or a run dir)")
    state, file = load_checkpoint(cfg.checkpoint, mmap=True)
    saved = OmegaConf.create(state["config"])
    run_dir = run_dir_of(file)
    env_cfg = overridden_env(saved.env, overrides) if overrides else make_env_config(saved.env)
    frames = int(state["counters"]["frames"])
    name = str(saved.name)
    out = Path(ex.eval_dir) if ex.eval_dir else _default_out(run_dir, file.stem, frames, overrides)
    method = str(OmegaConf.select(saved, "experiment.method", default=name) or name)
    return Target(name, method, env_cfg, out, frames, file, state, saved, run_dir)


def _eval_set_file(cfg: DictConfig, t: Target, overrides: Mapping[str, Any]) -> Path:
    if cfg.trainer.eval_set:
        return Path(cfg.trainer.eval_set).expanduser()
    if overrides or t.state is None:
        return t.out / "eval_set.json"  # another world (or a controller): a set of its own
    return eval_set_path(t.run_dir, None)  # type: ignore[arg-type]


def _flyer(cfg: DictConfig, t: Target, evaluation: Evaluation) -> Any:
    learner = None
    if t.state is not None:
        probe = make_env(t.env_cfg, 1, seed=0, device=cfg.device)
        learner = make_learner(t.saved.algo, probe)  # type: ignore[union-attr]
        learner.load_state_dict(t.state["learner"])
    return make_flyer(cfg, t.env_cfg, evaluation.evaluator.env.action_spec, learner, t.safety, t.actor_mode)


def evaluate_checkpoint(cfg: DictConfig, task_overrides: Sequence[str] = ()) -> dict[str, float]:
    """Evaluate ``cfg.checkpoint`` (a file or a run dir), or the controller of an
    evaluation-only ``+exp`` (``heuristic``, ``llm``, ``random``: no checkpoint).

    The world is the checkpoint's, with the command line's env overrides on top
    (:func:`env_overrides`, padding kept: :func:`overridden_env`). The evaluation set is
    ``trainer.eval_set`` when given; else the run's own set for the run's world, or one sampled
    for the overridden world (``trainer.eval_episodes``, ``trainer.eval_seed``) in the output
    folder. Writes ``episodes.csv``, ``metrics.json``, trajectory PNGs and ``evaluation.json``
    (what was evaluated, on which world, by which code) to ``experiment.eval_dir`` (default:
    ``<run_dir>/evaluate/<checkpoint>_frames<N>[_<hash of the overrides>]``)."""
    tr = cfg.trainer  # evaluation settings come from this command line (defaults: the trainer's)
    overrides = env_overrides(cfg.env, task_overrides)
    t = _target(cfg, overrides)
    problems = world_problems(t.env_cfg)
    if problems:
        raise ConfigError("\n".join(problems))
    check_llm(cfg, t.env_cfg)
    t.safety = safety_of(cfg, t.saved, task_overrides)
    t.actor_mode = actor_mode_of(cfg, t.saved, task_overrides) if t.state is not None else "mean"
    if t.actor_mode != "mean" and not cfg.experiment.eval_dir:  # its own folder beside the mean's
        t.out = t.out.with_name(f"{t.out.name}_{t.actor_mode}")
    filtered = t.state is not None and make_safety_filter_config(t.safety).mode != "off"
    spec = json.loads(json.dumps({
        "checkpoint": str(t.file) if t.file else None, "frames": t.frames, "method": t.method,
        "env_overrides": {k: overrides[k] for k in sorted(overrides)}, "eval_set": tr.eval_set,
        "eval_episodes": int(tr.eval_episodes), "eval_seed": int(tr.eval_seed), "eval_max_steps": tr.eval_max_steps,
        "seed": int(cfg.seed),
        **({"safety_filter": OmegaConf.to_container(t.safety, resolve=True)} if filtered else {}),
        **({"eval_actor": t.actor_mode} if t.actor_mode != "mean" else {}),
    }, default=str))
    done = _done(t.out / "evaluation.json", spec) if cfg.experiment.reuse else None
    if done is not None:
        return done
    set_file = _eval_set_file(cfg, t, overrides)
    scenarios = load_or_make_eval_set(t.env_cfg, set_file, tr.eval_episodes, tr.eval_seed,
                                      sample=bool(tr.sample_eval_set) or not tr.eval_set)
    fingerprint = {"spec": spec, "llm": OmegaConf.to_container(cfg.llm, resolve=True),
                   "advisor": OmegaConf.to_container(cfg.advisor, resolve=True)}
    evaluation = make_evaluation(cfg, t.env_cfg, scenarios, fingerprint=fingerprint)
    t0 = time.perf_counter()
    policy = _flyer(cfg, t, evaluation)
    try:
        with GracefulStop() as stop:  # a stop ends the flight at its current step; nothing is written
            evaluation.stop = stop
            start_llm(policy, stop)
            flight = evaluation.fly(policy, t.out, title=f"{t.name} @ {t.frames} frames")
    finally:
        if isinstance(policy, OverridePolicy):
            policy.close()  # the LLM's client, and the local server it started
    _record(cfg, t, spec, set_file, len(scenarios), flight, time.perf_counter() - t0)
    if stop.requested:  # the LLM alone paused at its saved step: recorded as paused, then the stop
        raise StopRequested(int(stop.signum))  # type: ignore[arg-type]
    log_evaluation(cfg, t.out)
    log.info("%s: %d episodes flown, written to %s", t.name, len(scenarios), t.out)
    return flight.metrics


def _done(record_file: Path, spec: Mapping[str, Any]) -> dict[str, float] | None:
    """A finished evaluation of the same spec (the LLM alone paused by its budget continues)."""
    if not record_file.is_file():
        return None
    done = json.loads(record_file.read_text())
    paused = not (done.get("llm_alone") or {}).get("complete", True)
    if done.get("spec") == spec and not paused:
        log.info("%s: evaluated already (experiment.reuse)", record_file)
        return done["metrics"]
    return None


def _record(cfg: DictConfig, t: Target, spec: Mapping[str, Any], set_file: Path, n: int, flight: Flight,
            wall_s: float) -> None:
    resolved = OmegaConf.to_container(cfg, resolve=True)
    counters = (t.state or {}).get("counters", {})
    llm_alone = None if flight.llm_alone is None else {k: v for k, v in flight.llm_alone.items() if k != "records"}
    dump_json(t.out / "evaluation.json", {
        "spec": dict(spec), "name": t.name,
        "episodes_trained": int(counters.get("episodes", 0)), "updates": int(counters.get("updates", 0)),
        "eval_set_file": str(set_file), "n_scenarios": n, "metrics": flight.metrics,
        "controller_stats": {k: v for k, v in flight.stats.items() if isinstance(v, (int, float))},
        "llm_alone": llm_alone, "wall_s": round(wall_s, 3),
        "experiment": resolved.get("experiment"),  # type: ignore[union-attr]
        "env": t.env_cfg.model_dump(mode="json"), "meta": run_metadata(resolved),  # type: ignore[arg-type]
    })


@hydra.main(config_path="conf", config_name="config", version_base="1.3")
def main(cfg: DictConfig) -> None:
    from hydra.core.hydra_config import HydraConfig

    torch.set_num_threads(int(cfg.threads))
    route_library_output(bool(OmegaConf.select(cfg, "logger.library_output", default=False)))
    try:
        with refused_in_job():
            agg = evaluate_checkpoint(cfg, list(HydraConfig.get().overrides.task))
    except StopRequested as s:
        print(f"stopped by signal {s.signum}: run the same command again (the LLM alone goes on from its saved "
              "progress; any other evaluation starts over)", file=sys.stderr)
        sys.exit(128 + s.signum)
    print(f"The paper metrics ({int(agg.get('n_episodes', 0))} episodes, one per scenario):")
    print(format_metrics(agg, PAPER_METRICS))


if __name__ == "__main__":
    from uavlae.entry import command
    from uavlae.llm.config import refuse_secret_overrides

    refuse_secret_overrides(sys.argv)  # before Hydra writes the command line down
    sys.argv = without_hydra_output(sys.argv)
    command(main)
