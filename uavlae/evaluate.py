"""Evaluation on a fixed, seeded set of scenarios (SPEC.md §5; paper §6.2); no training code.

The evaluation set is sampled once with ``trainer.eval_seed`` and saved as JSON
(``<run_dir>/eval_set.json``, or ``trainer.eval_set``), then reloaded, so every evaluation of a
run (and of every method compared on it) flies the same scenarios. A learner is evaluated by
its actor alone, deterministically (``ExplorationType.DETERMINISTIC``: the tanh of the mean; no
LLM, no heuristic, as in deployment). Each evaluation writes the per-episode records
(``episodes.csv``), the aggregates (``metrics.json``: DCR, CR, SLR, RVR, ECR, the mean of every
reward term, ...) and a PNG of the first few trajectories.

``python -m uavlae.evaluate checkpoint=RUN_DIR_OR_FILE`` evaluates a training checkpoint, on its
run's world or on the world its command line changes (``env.ou.count.min=3 env.ou.count.max=3``:
the observation's padding stays the training one, so the same actor serves every setting).
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import sys
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import hydra
import torch
from omegaconf import DictConfig, OmegaConf
from torchrl.envs.utils import ExplorationType, set_exploration_type

from uavlae.envs import EnvConfig, UAVEnv, make_env_config
from uavlae.envs.metrics import PAPER_METRICS, format_metrics, rollout_metrics, save_aggregates, save_records
from uavlae.envs.scenario import Scenario, load_scenarios, sample_scenarios, save_scenarios, unstack_scenarios
from uavlae.factories import CONF_DIR, without_hydra_output
from uavlae.files import dump_json

log = logging.getLogger(__name__)


def eval_set_path(run_dir: str | os.PathLike[str], eval_set: str | None) -> Path:
    return Path(eval_set).expanduser() if eval_set else Path(run_dir) / "eval_set.json"


def load_or_make_eval_set(env_cfg: EnvConfig, path: str | os.PathLike[str], n: int, seed: int) -> list[Scenario]:
    """The scenarios at ``path``; when the file is absent, ``n`` scenarios sampled with ``seed``
    (a generator of their own: the global RNGs are untouched) and saved there first."""
    path = Path(path)
    if path.is_file():
        scenarios = load_scenarios(path)
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

    def run(self, policy: Any, out_dir: str | os.PathLike[str] | None = None, *, title: str = "") -> dict[str, float]:
        """Evaluate ``policy`` (deterministic exploration); write files under ``out_dir``."""
        self.env.set_seed(self.seed)
        with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
            records, agg, trajectories = rollout_metrics(self.env, policy, max_steps=self.max_steps, cfg=self.env_cfg)
        if out_dir is not None:
            out = Path(out_dir)
            save_records(records, out / "episodes.csv")
            save_aggregates(agg, out / "metrics.json")
            self.plot(trajectories, out, title)
        return agg

    def plot(self, trajectories: list[torch.Tensor], out: Path, title: str = "") -> None:
        from uavlae.envs.render import draw_scenario

        for i in range(min(self.n_plots, len(trajectories))):
            draw_scenario(
                self.scenarios[i], [trajectories[i]], path=out / f"trajectory_{i}.png",
                title=f"{title} scenario {i}".strip(), cfg=self.env_cfg,
            )


def deterministic_actor(learner: Any) -> Any:
    """The learner's actor alone (no exploration noise, no override)."""
    return learner.actor


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


def flatten_keys(d: Any, prefix: str = "") -> dict[str, Any]:
    """A nested dict as one level, its keys joined by dots (the run checks compare configs so)."""
    if not isinstance(d, dict):
        return {prefix: d}
    out: dict[str, Any] = {}
    for k, v in d.items():
        out.update(flatten_keys(v, f"{prefix}{k}." if isinstance(v, dict) else f"{prefix}{k}"))
    return out


def config_differences(want: Any, have: Any) -> tuple[list[str], list[str]]:
    """How a saved config ``have`` differs from this run's ``want`` (nested dicts), as sorted
    dotted keys ``(changed, added)``. ``added`` are the keys ``have`` lacks: settings added to the
    code after it was saved, whose defaults keep the earlier behaviour, so no difference. A key
    only ``have`` holds (one since removed) counts as changed."""
    from uavlae.factories import REMOVED_KEYS

    w, h = flatten_keys(want), flatten_keys(have)
    h = {k: v for k, v in h.items() if k not in REMOVED_KEYS}  # settings removed since, which had no effect
    added = sorted(set(w) - set(h))
    changed = sorted(k for k in set(w) | set(h) if k not in added and w.get(k) != h.get(k))
    return changed, added


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
            raise ValueError(f"env override {key}={value!r}: the checkpoint's env has no key {key!r}")
        OmegaConf.update(env, key, value, merge=False)
    try:
        out = make_env_config(env)
    except ValueError as err:
        raise ValueError(f"env overrides {dict(overrides)} on the checkpoint's world: {err}") from None
    obs_before, obs_after = _obs_dim(trained), _obs_dim(out)
    if obs_before != obs_after:
        raise ValueError(
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
    from uavlae.checkpoint import load_checkpoint, run_dir_of
    from uavlae.factories import make_controller, make_env, make_learner, run_metadata

    ex = cfg.experiment
    tr = cfg.trainer  # evaluation settings come from this command line (defaults: the trainer's)
    controller = cfg.controller != "learner"
    overrides = env_overrides(cfg.env, task_overrides)
    if controller:
        env_cfg, state, file, run_dir, frames = make_env_config(cfg.env), None, None, None, 0
        name = str(cfg.name)
        if not ex.eval_dir:
            raise ValueError(f"uavlae.evaluate +exp={name} (a controller) needs experiment.eval_dir=PATH")
        out = Path(ex.eval_dir)
    else:
        if not cfg.checkpoint:
            raise ValueError("uavlae.evaluate needs checkpoint=PATH (a checkpoint file or a run dir)")
        state, file = load_checkpoint(cfg.checkpoint, mmap=True)
        saved = OmegaConf.create(state["config"])
        run_dir = run_dir_of(file)
        env_cfg = overridden_env(saved.env, overrides) if overrides else make_env_config(saved.env)
        frames = int(state["counters"]["frames"])
        name = str(saved.name)
        out = Path(ex.eval_dir) if ex.eval_dir else _default_out(run_dir, file.stem, frames, overrides)
    record_file = out / "evaluation.json"
    spec = {
        "checkpoint": str(file) if file else None,
        "frames": frames,
        "method": str(ex.method) if controller else str(OmegaConf.select(saved, "experiment.method", default=name) or name),
        "env_overrides": {k: overrides[k] for k in sorted(overrides)},
        "eval_set": tr.eval_set,
        "eval_episodes": int(tr.eval_episodes),
        "eval_seed": int(tr.eval_seed),
        "eval_max_steps": tr.eval_max_steps,
        "seed": int(cfg.seed),
    }
    if ex.reuse and record_file.is_file():
        done = json.loads(record_file.read_text())
        paused = not (done.get("llm_alone") or {}).get("complete", True)  # the LLM alone continues
        if done.get("spec") == json.loads(json.dumps(spec, default=str)) and not paused:
            log.info("%s: evaluated already (experiment.reuse)", record_file)
            return done["metrics"]
    if tr.eval_set:
        set_file = Path(tr.eval_set).expanduser()
    elif overrides or controller:
        set_file = out / "eval_set.json"
    else:
        set_file = eval_set_path(run_dir, None)
    scenarios = load_or_make_eval_set(env_cfg, set_file, tr.eval_episodes, tr.eval_seed)
    evaluator = Evaluator(env_cfg, scenarios, seed=tr.eval_seed, max_steps=tr.eval_max_steps, n_plots=tr.eval_plots, device=cfg.device)
    t0 = time.perf_counter()
    if controller:
        policy = make_controller(cfg, env_cfg, action_spec=evaluator.env.action_spec)
    else:
        probe = make_env(env_cfg, 1, seed=0, device=cfg.device)
        learner = make_learner(saved.algo, probe)
        learner.load_state_dict(state["learner"])
        policy = deterministic_actor(learner)
    llm_alone = None
    try:
        if cfg.controller == "llm":  # chunks, a call budget, resumable (uavlae.llm_alone)
            from uavlae.llm_alone import LLMAloneEvaluation

            fingerprint = {"spec": spec, "llm": OmegaConf.to_container(cfg.llm, resolve=True),
                           "advisor": OmegaConf.to_container(cfg.advisor, resolve=True)}
            ev = LLMAloneEvaluation(
                env_cfg, scenarios, policy, out, seed=tr.eval_seed, chunk=tr.eval_chunk, max_steps=tr.eval_max_steps,
                budget=tr.llm_call_budget, fingerprint=fingerprint, n_plots=tr.eval_plots, device=cfg.device,
                shard=tr.eval_shard, shards=tr.eval_shards,
            )
            res = ev.run()
            ev.write(res, title=name)
            agg = res["metrics"]
            llm_alone = {k: res[k] for k in ("complete", "episodes_scored", "episodes_total", "chunks_done", "chunks",
                                             "in_flight_step", "cost")}
            stats = policy.run_totals()
        else:
            agg = evaluator.run(policy, out, title=f"{name} @ {frames} frames")
            stats = policy.snapshot() if hasattr(policy, "snapshot") else {}
    finally:
        close = getattr(policy, "close", None)
        if close is not None:
            close()
    resolved = OmegaConf.to_container(cfg, resolve=True)
    record = {
        "spec": json.loads(json.dumps(spec, default=str)),
        "name": name,
        "episodes_trained": int(state["counters"].get("episodes", 0)) if state else 0,
        "updates": int(state["counters"].get("updates", 0)) if state else 0,
        "eval_set_file": str(set_file),
        "n_scenarios": len(scenarios),
        "metrics": agg,
        "controller_stats": {k: v for k, v in stats.items() if isinstance(v, (int, float))},
        "llm_alone": llm_alone,
        "wall_s": round(time.perf_counter() - t0, 3),
        "experiment": resolved.get("experiment"),  # type: ignore[union-attr]
        "env": env_cfg.model_dump(mode="json"),
        "meta": run_metadata(resolved),  # type: ignore[arg-type]
    }
    dump_json(record_file, record)
    log.info("%s\n%s", out, format_metrics(agg))
    return agg


@hydra.main(config_path=str(CONF_DIR), config_name="config", version_base="1.3")
def main(cfg: DictConfig) -> None:
    from hydra.core.hydra_config import HydraConfig

    torch.set_num_threads(int(cfg.threads))
    agg = evaluate_checkpoint(cfg, list(HydraConfig.get().overrides.task))
    print(format_metrics(agg, PAPER_METRICS))


if __name__ == "__main__":
    from uavlae.llm.config import refuse_secret_overrides

    refuse_secret_overrides(sys.argv)  # before Hydra writes the command line down
    sys.argv = without_hydra_output(sys.argv)
    main()
