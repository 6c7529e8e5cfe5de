"""``make_*`` factories for the entry points, one per config group (docs/style.md rule 5).

``conf/env`` -> :func:`make_env`, ``conf/algo`` -> :func:`make_learner`, ``conf/advisor`` (+ the
``heuristic`` and ``llm`` nodes) -> :func:`make_policy` / :func:`make_controller`,
``conf/logger`` -> :func:`make_logger`, ``conf/trainer`` -> :func:`make_trainer_config`.
Each validates its node with a pydantic model (unknown keys and out-of-range values are errors
that name the field); the env, algo, heuristic and LLM models live with their code.
"""

from __future__ import annotations

import importlib.metadata as metadata
import json
import os
import subprocess
import sys
import uuid
from collections.abc import Mapping
from pathlib import Path
from typing import Any, Literal

import torch
from omegaconf import DictConfig, OmegaConf
from pydantic import BaseModel, Field, ValidationError, model_validator

from uavlae.algos import OFF_POLICY, make_learner as _make_learner
from uavlae.envs import EnvConfig, UAVEnv, make_env_config
from uavlae.errors import ConfigError
from uavlae.files import dump_json  # noqa: F401  (re-exported: the entry points write JSON through it)
from uavlae.policies.safety import make_safety_filter, make_safety_filter_config  # noqa: F401  (a factory of its own group)
from uavlae.policies.student import StudentConfig
from uavlae.validation import StrictModel, error_lines

PACKAGE_DIR = Path(__file__).resolve().parent
# The configs ship inside the package, so an installed uavlae composes the same runs as a checkout.
CONF_DIR = PACKAGE_DIR / "conf"
# The checkout the package sits in (its parent folder); installed, this is site-packages, no checkout.
REPO_ROOT = PACKAGE_DIR.parent


def _container(cfg: Any) -> dict[str, Any]:
    if cfg is None:
        return {}
    if isinstance(cfg, DictConfig):
        return OmegaConf.to_container(cfg, resolve=True)  # type: ignore[return-value]
    if isinstance(cfg, BaseModel):
        return cfg.model_dump()
    return dict(cfg)


def _validate(model: type[BaseModel], cfg: Any, group: str) -> Any:
    if isinstance(cfg, model):
        return cfg
    try:
        return model.model_validate(_container(cfg))
    except ValidationError as e:
        raise ConfigError(f"invalid {group} config:\n  " + "\n  ".join(error_lines(e, group))) from None


# ---------------------------------------------------------------------------- configs

class TrainerConfig(StrictModel):
    """``conf/trainer``: the loop's numbers."""

    total_frames: int = Field(ge=1)
    total_episodes: int | None = Field(default=None, ge=1)
    env_batch_size: int = Field(ge=1)
    frames_per_batch: int = Field(ge=1)
    init_random_frames: int = Field(ge=0)
    utd_ratio: float = Field(gt=0)
    replay_capacity: int = Field(ge=1)
    batch_size: int = Field(ge=1)
    checkpoint_replay_buffer: bool
    keep_replay_at_end: bool = True  # a finished run's checkpoint keeps the replay buffer too (to extend it)
    eval_every_frames: int = Field(ge=0)
    eval_episodes: int = Field(ge=1)
    eval_seed: int
    eval_set: str | None
    sample_eval_set: bool = False  # a missing eval_set file is sampled and saved there (else an error)
    eval_max_steps: int | None = Field(ge=1)
    eval_plots: int = Field(ge=0)
    checkpoint_every_frames: int = Field(ge=0)
    keep_checkpoints: int = Field(ge=1, le=2)
    progress_bar: bool
    progress_every_s: float = Field(default=60.0, ge=0)  # a progress line this often where no bar shows (0: none)
    progress_first_s: float = Field(default=10.0, ge=0)  # the first line this soon (never later than progress_every_s)
    log_every_batches: int = Field(ge=1)
    compile_env: bool = False  # UAVEnv(compile_step=True) for the training and evaluation envs
    overlap_advice: bool = True  # run a step's gradient steps while its advice is in flight
    baselines: bool = True  # evaluate the heuristic and a uniform-random policy on the evaluation set at the end
    eval_with_advisor: bool = True  # advised runs: at the end also fly the actor with its advisor (full trigger)
    eval_advisor_max_calls: int | None = Field(default=64, ge=0)  # rows that evaluation may ask (None: no budget)
    eval_chunk: int | None = Field(default=None, ge=1)  # controller=llm: scenarios flown together (None: all)
    llm_call_budget: int | None = Field(default=None, ge=0)  # controller=llm: LLM decisions this invocation may ask (0: only score)
    eval_shards: int = Field(default=1, ge=1)  # controller=llm: processes that fly the evaluation side by side
    eval_shard: int = Field(default=0, ge=0)  # controller=llm: which of them this one is

    @model_validator(mode="after")
    def _divisible(self) -> "TrainerConfig":
        if self.eval_shard >= self.eval_shards:
            raise ValueError(f"trainer.eval_shard={self.eval_shard} must be below trainer.eval_shards={self.eval_shards}")
        if self.frames_per_batch % self.env_batch_size:
            raise ValueError(
                f"trainer.frames_per_batch={self.frames_per_batch} must be a multiple of "
                f"trainer.env_batch_size={self.env_batch_size} (each batch is [B, T])"
            )
        return self


class AdvisorConfig(StrictModel):
    """``conf/advisor``: who overrides the learner's action, and when (docs/model.md §8)."""

    mode: Literal["proximity", "fixed_prob", "always", "never"]
    # heuristic: the one of heuristic_kind; hover and random: scripted advisors of known, poor
    # quality (beyond the paper), for measuring what advice is worth
    kind: Literal["none", "llm", "heuristic", "hover", "random"]
    d_th: float = Field(ge=0)  # m
    fp: float = Field(ge=0, le=1)
    fallback: Literal["policy", "heuristic", "end_episode"]
    hold_steps: int = Field(1, ge=1)  # slots a valid answer is executed while its row stays triggered
    max_calls: int | None = Field(None, ge=0)  # rows asked of the advisor in the run; None: no budget
    phase_out_frames: int | None = Field(None, ge=1)  # anneal d_th / fp to 0 over these frames; None: never
    agree_tol: float = Field(0.1, gt=0)  # action units: the actor agrees with executed advice within this
    # beyond the paper: a student network trained on the LLM's answers answers where it is sure,
    # the LLM where it is not (uavlae.policies.student)
    amortize: bool = False
    student: StudentConfig = StudentConfig()

    @model_validator(mode="after")
    def _consistent(self) -> "AdvisorConfig":
        if (self.kind == "none") != (self.mode == "never"):
            raise ValueError(f"advisor.kind={self.kind!r} and advisor.mode={self.mode!r}: kind none goes with mode never")
        if self.amortize and self.kind != "llm":
            raise ValueError(f"advisor.amortize learns from an LLM's answers; advisor.kind={self.kind!r} has none "
                             "(use it with +exp=sac_llm or sac_llm_fp)")
        if self.phase_out_frames is not None and self.mode not in ("proximity", "fixed_prob"):
            raise ValueError(f"advisor.phase_out_frames anneals d_th (proximity) or fp (fixed_prob); "
                             f"advisor.mode={self.mode!r} has neither")
        return self


class WandbConfig(StrictModel):
    mode: Literal["offline", "online", "disabled"]
    project: str
    entity: str | None
    group: str | None
    tags: tuple[str, ...]


class LoggerConfig(StrictModel):
    """``conf/logger``."""

    csv: bool
    wandb: WandbConfig
    library_output: bool = False  # wandb's and torchrl's own messages on the terminal too (else the run's log only)


class ExperimentConfig(StrictModel):
    """The root ``experiment`` node: where a run sits in a sweep (conf/sweep/)."""

    sweep: str | None
    profile: str | None
    root: str = Field(min_length=1)
    point: str = Field(min_length=1)
    method: str = Field(min_length=1)
    tags: tuple[str, ...]
    reuse: bool
    eval_dir: str | None


class RunConfig(StrictModel):
    """The root keys of ``conf/config.yaml``."""

    name: str = Field(min_length=1)
    controller: Literal["learner", "heuristic", "llm", "random"]
    heuristic_kind: Literal["greedy", "planner"]
    seed: int
    device: str
    threads: int = Field(ge=1)
    run_dir: str
    resume: str | None
    checkpoint: str | None
    out: str | None


def make_trainer_config(cfg: Any) -> TrainerConfig:
    return _validate(TrainerConfig, cfg, "trainer")


def make_advisor_config(cfg: Any) -> AdvisorConfig:
    return _validate(AdvisorConfig, cfg, "advisor")


def make_experiment_config(cfg: Any) -> ExperimentConfig:
    return _validate(ExperimentConfig, cfg, "experiment")


def make_logger_config(cfg: Any) -> LoggerConfig:
    return _validate(LoggerConfig, cfg, "logger")


def validate_config(cfg: DictConfig) -> None:
    """Validate every group of a composed config; ``ValueError`` names the bad field."""
    root = {k: cfg[k] for k in RunConfig.model_fields}
    run = _validate(RunConfig, root, "config")
    known = set(RunConfig.model_fields) | {"env", "algo", "advisor", "llm", "logger", "trainer", "heuristic", "greedy",
                                           "experiment", "safety_filter"}
    unknown = sorted(set(cfg.keys()) - known - {"hydra"})
    if unknown:
        raise ValueError(f"unknown top-level config keys {unknown}")
    make_env_config(cfg.env)
    make_experiment_config(cfg.experiment)
    make_trainer_config(cfg.trainer)
    make_logger_config(cfg.logger)
    adv = make_advisor_config(cfg.advisor)
    from uavlae.policies.greedy import make_greedy_config
    from uavlae.policies.heuristic import make_heuristic_config

    make_heuristic_config(cfg.heuristic)
    make_greedy_config(cfg.greedy)
    make_safety_filter_config(cfg.get("safety_filter"))
    if run.controller == "learner":
        if cfg.get("algo") is None:
            raise ValueError("controller=learner needs an algo (algo=sac|sac_lag|ppo|ddpg|cpo|wang|theile|crossq)")
        from uavlae.algos import MAKERS

        name = cfg.algo.name
        if name not in MAKERS:
            raise ValueError(f"algo.name must be one of {sorted(MAKERS)}, got {name!r}")
        _algo_config(cfg.algo)
        if float(cfg.algo.get("clone_weight", 0.0) or 0.0) > 0 and adv.kind == "none":
            raise ValueError(
                f"algo.clone_weight={cfg.algo.clone_weight} clones the executed advice, but advisor.kind is 'none': "
                "there is none to clone (use +exp=sac_heuristic, sac_llm, ... or clone_weight=0)"
            )
        if adv.kind != "none" and name not in OFF_POLICY:
            raise ValueError(
                f"advisor.kind={adv.kind!r} with algo {name!r}: the override stores executed actions for an "
                "off-policy learner; on-policy PPO/CPO would need the advisor's log-probabilities"
            )
    if run.controller == "llm" and adv.amortize:
        raise ValueError("advisor.amortize with controller=llm: the LLM alone is the LLM at every step, not a student")
    if cfg.get("llm") is not None:  # always: a key given in its place is refused before anything is written
        from uavlae.llm import make_llm_config

        make_llm_config(cfg.llm)


def _algo_config(cfg: Any) -> Any:
    from uavlae.algos.crossq import make_crossq_config
    from uavlae.algos.ddpg import make_ddpg_config
    from uavlae.algos.ppo import make_ppo_config
    from uavlae.algos.ppo_lagrangian import make_cpo_config
    from uavlae.algos.sac import make_sac_config
    from uavlae.algos.sac_lag import make_sac_lag_config
    from uavlae.algos.theile import make_theile_config
    from uavlae.algos.wang import make_wang_config

    makers = {
        "sac": make_sac_config, "sac_lag": make_sac_lag_config, "ddpg": make_ddpg_config, "ppo": make_ppo_config,
        "cpo": make_cpo_config, "wang": make_wang_config, "theile": make_theile_config, "crossq": make_crossq_config,
    }
    return makers[cfg.name](cfg)


# ---------------------------------------------------------------------------- env


def check_device(device: str) -> None:
    """A device this machine has, or an error naming it (before a run writes anything)."""
    try:
        dev = torch.device(device)
    except RuntimeError as err:
        raise ValueError(f"device={device!r} is not a device torch knows: {err}") from None
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise ValueError(f"device={device!r}: this torch ({torch.__version__}) sees no CUDA device; use device=cpu")
    if dev.type == "mps" and not torch.backends.mps.is_available():
        raise ValueError(f"device={device!r}: no MPS device here; use device=cpu")


def make_env(
    env_cfg: EnvConfig | Any,
    batch_size: int,
    *,
    seed: int,
    device: str | torch.device = "cpu",
    scenarios: Any = None,
    compile_step: bool = False,
) -> UAVEnv:
    """``conf/env`` -> the batched world (its own generator seeded with ``seed``; ``compile_step``:
    the step through ``torch.compile``, see :class:`UAVEnv`)."""
    return UAVEnv(
        make_env_config(env_cfg), batch_size=batch_size, device=device, seed=seed, scenarios=scenarios,
        compile_step=compile_step,
    )


# ---------------------------------------------------------------------------- learner and policies


def make_learner(algo_cfg: Any, env: UAVEnv) -> Any:
    """``conf/algo`` -> a learner (``actor``, ``update``, ``state_dict``) sized for ``env``."""
    obs_dim = env.observation_spec["observation"].shape[-1]
    return _make_learner(algo_cfg, obs_dim, env.action_spec, layout=env.layout)


def make_heuristic(cfg: DictConfig, env_cfg: EnvConfig) -> Any:
    """``heuristic_kind`` -> the paper's greedy controller (:class:`uavlae.policies.greedy.GreedyPolicy`,
    the ``greedy`` node) or the visibility-graph planner beyond the paper
    (:class:`uavlae.policies.heuristic.HeuristicPolicy`, the ``heuristic`` node)."""
    if cfg.heuristic_kind == "greedy":
        from uavlae.policies.greedy import GreedyPolicy

        return GreedyPolicy(env_cfg, _container(cfg.greedy))
    from uavlae.policies.heuristic import HeuristicPolicy

    return HeuristicPolicy(env_cfg, _container(cfg.heuristic))


def make_llm_advisor(cfg: DictConfig) -> Any:
    """``conf/llm`` -> :class:`uavlae.llm.LLMAdvisor` (it starts the local server on first use
    when ``llm.base_url`` is null; the API key is read from ``llm.api_key_env`` only)."""
    from uavlae.llm import LLMAdvisor, make_llm_config

    return LLMAdvisor(make_llm_config(cfg.llm))


def make_policy(cfg: DictConfig, actor: Any, env_cfg: EnvConfig, *, seed: int | None = None) -> Any:
    """``conf/advisor`` -> the collection policy: ``actor`` alone, or wrapped by
    :class:`uavlae.policies.override.OverridePolicy` with an LLM or heuristic advisor."""
    from uavlae.policies.override import HeuristicAdvisor, LLMAdvisorAdapter, OverridePolicy, ScriptedAdvisor

    adv = make_advisor_config(cfg.advisor)
    if adv.kind == "none":
        # wrapped all the same: one policy type for the collector (action_source, resume state)
        return OverridePolicy(actor, None, mode="never", fallback="policy", seed=int(cfg.seed if seed is None else seed))

    heuristic = make_heuristic(cfg, env_cfg) if (adv.kind == "heuristic" or adv.fallback == "heuristic") else None
    seed = int(cfg.seed if seed is None else seed)
    if adv.kind == "heuristic":
        advisor: Any = HeuristicAdvisor(heuristic)
    elif adv.kind in ScriptedAdvisor.KINDS:
        advisor = ScriptedAdvisor(adv.kind, seed=seed + 7919)  # its own stream, apart from the trigger's
    else:
        advisor = LLMAdvisorAdapter(make_llm_advisor(cfg), env_cfg)
        if adv.amortize:
            from uavlae.policies.student import AmortizedAdvisor

            advisor = AmortizedAdvisor(advisor, adv.student, seed=seed + 7907)  # apart from the trigger's stream
    return OverridePolicy(
        actor,
        advisor,
        mode=adv.mode,
        d_th=adv.d_th,
        fp=adv.fp,
        fallback=adv.fallback,
        heuristic=heuristic,
        seed=seed,
        hold_steps=adv.hold_steps,
        max_calls=adv.max_calls,
        perception_radius=env_cfg.safety.perception_radius,
        phase_out_frames=adv.phase_out_frames,
        agree_tol=adv.agree_tol,
    )


def make_controller(cfg: DictConfig, env_cfg: EnvConfig, action_spec: Any = None) -> Any:
    """The evaluation-only controllers: ``heuristic`` (the greedy baseline), ``llm`` (the
    LLM at every step, the heuristic for failed answers when ``advisor.fallback=heuristic``)
    or ``random`` (uniform in ``action_spec``'s box, seeded by ``cfg.seed``)."""
    if cfg.controller == "random":
        from uavlae.policies.random import UniformRandomPolicy

        if action_spec is None:
            raise ValueError("controller=random needs the env's action_spec")
        return UniformRandomPolicy(action_spec, seed=int(cfg.seed))
    heuristic = make_heuristic(cfg, env_cfg)
    if cfg.controller == "heuristic":
        return heuristic
    if cfg.controller == "llm":
        return make_policy(cfg, heuristic, env_cfg)
    raise ValueError(f"controller must be heuristic, llm or random here, got {cfg.controller!r}")


# ---------------------------------------------------------------------------- logging


def git_info() -> dict[str, Any]:
    """The commit of the code that ran, and whether tracked files differed from it. ``results/``
    does not count: it holds outputs (a regenerated report), never code that runs. An installed
    package has no checkout of its own: ``None`` for both, and the package's version (in
    :func:`package_versions`) tells which code ran. A checkout counts only when it is the one
    that holds this package, not a repository that happens to contain site-packages."""

    def git(*args: str) -> str | None:
        try:
            out = subprocess.run(["git", *args], cwd=REPO_ROOT, capture_output=True, text=True, timeout=10)
        except (OSError, subprocess.SubprocessError):
            return None
        return out.stdout.strip() if out.returncode == 0 else None

    top = git("rev-parse", "--show-toplevel")
    if top is None or Path(top).resolve() != Path(REPO_ROOT).resolve():
        return {"commit": None, "dirty": None}
    commit = git("rev-parse", "HEAD")
    status = git("status", "--porcelain", "--untracked-files=no", "--", ".", ":(exclude)results")
    return {"commit": commit, "dirty": bool(status) if status is not None else None}


def package_versions() -> dict[str, str | None]:
    out: dict[str, str | None] = {"python": sys.version.split()[0]}
    for name in ("uavlae", "torch", "torchrl", "tensordict", "hydra-core", "omegaconf", "numpy", "pydantic", "wandb",
                 "matplotlib", "xllamacpp"):
        try:
            out[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            out[name] = None
    return out


class RunLogger:
    """torchrl's ``CSVLogger`` (always) and ``WandbLogger`` (unless disabled) behind one call.

    Every metric goes with ``step`` = environment frames. ``state_dict`` holds what resuming
    needs: the CSV logger's counters and the wandb run id. Closing it after the run has written
    its ``final_metrics.json`` publishes them to the wandb run's summary, with the final and
    baseline evaluations' per-episode records as tables (:func:`uavlae.runlog.publish_final`).
    """

    def __init__(self, loggers: Mapping[str, Any], run_id: str, run_dir: str | os.PathLike[str] | None = None):
        self.loggers = dict(loggers)
        self.run_id = run_id
        self.run_dir = None if run_dir is None else Path(run_dir)

    def log_metrics(self, metrics: Mapping[str, float], step: int) -> None:
        clean = {k: float(v) for k, v in metrics.items() if isinstance(v, (int, float)) and not isinstance(v, bool)}
        if not clean:
            return
        for lg in self.loggers.values():
            lg.log_metrics(clean, step=int(step))

    def log_images(self, images: Mapping[str, Path], step: int) -> None:
        """PNG files (the evaluation trajectories) as wandb images at ``step``; the CSV logger
        has them on disk already."""
        lg = self.loggers.get("wandb")
        if lg is None or not images:
            return
        import wandb

        prefix = next(iter(images)).rpartition("/")[0]
        payload: dict[str, Any] = {k: wandb.Image(str(p)) for k, p in images.items()}
        payload[f"{prefix}/step" if prefix else "step"] = int(step)  # the group's step, as torchrl's logger keys it
        lg.experiment.log(payload)

    def log_hparams(self, cfg: Mapping[str, Any]) -> None:
        for name, lg in self.loggers.items():
            if name == "wandb":
                lg.log_hparams(dict(cfg))

    def state_dict(self) -> dict[str, Any]:
        return {"run_id": self.run_id, **{k: lg.state_dict() for k, lg in self.loggers.items()}}

    def load_state_dict(self, state: Mapping[str, Any]) -> None:
        for k, lg in self.loggers.items():
            if k in state:
                lg.load_state_dict(state[k])

    def close(self) -> None:
        lg = self.loggers.get("wandb")
        if lg is not None and self.run_dir is not None:
            from uavlae.runlog import publish_final

            publish_final(lg.experiment, self.run_dir)
        for lg in self.loggers.values():
            close = getattr(lg, "close", None)
            if close is not None:
                close()


def trim_csv_scalars(log_dir: Path, max_step: int) -> None:
    """Drop CSV rows logged after ``max_step`` (a resumed run logs those frames again)."""
    for f in Path(log_dir).rglob("*.csv"):
        lines = f.read_text().splitlines()
        kept = [ln for ln in lines if ln and int(float(ln.split(",", 1)[0])) <= max_step]
        if len(kept) != len(lines):
            f.write_text("".join(ln + "\n" for ln in kept))


# Commands that only read a run (evaluate, export) write next to the checkpoint: no Hydra run
# folder, no .hydra/ copy and no log file in the working directory.
NO_HYDRA_OUTPUT = ("hydra.output_subdir=null", "hydra.run.dir=.", "hydra/job_logging=stdout")


def without_hydra_output(argv: list[str]) -> list[str]:
    """``argv`` plus :data:`NO_HYDRA_OUTPUT` (a setting the user typed wins)."""
    given = {a.split("=", 1)[0] for a in argv[1:]}
    return argv + [o for o in NO_HYDRA_OUTPUT if o.split("=", 1)[0] not in given]


def make_logger(cfg: DictConfig, run_dir: Path, run_id: str, hparams: Mapping[str, Any],
                resume: bool = False) -> RunLogger:
    """``conf/logger`` -> :class:`RunLogger`; CSV under ``<run_dir>/logs/scalars``, the wandb
    run (offline by default) under ``<run_dir>/wandb`` with the resolved config, the git
    commit and the package versions, grouped, named and tagged as :mod:`uavlae.runlog` says.
    ``resume``: the wandb run of that id continues (the same run, its steps going on from the
    checkpoint's frames)."""
    from torchrl.record.loggers import CSVLogger

    from uavlae.runlog import wandb_group, wandb_name, wandb_tags

    lc = make_logger_config(cfg.logger)
    ex = make_experiment_config(cfg.experiment)
    loggers: dict[str, Any] = {}
    if lc.csv:
        loggers["csv"] = CSVLogger(exp_name="logs", log_dir=str(run_dir))
    if lc.wandb.mode != "disabled":
        from torchrl.record.loggers import WandbLogger

        loggers["wandb"] = WandbLogger(
            exp_name=wandb_name(ex.method, int(cfg.seed), ex),
            offline=lc.wandb.mode == "offline",
            # absolute: a wandb service this process joins (WANDB_SERVICE, inherited from a parent
            # that runs wandb) resolves a relative folder against its own working directory
            save_dir=str(Path(run_dir).resolve()),
            id=run_id,
            project=lc.wandb.project,
            entity=lc.wandb.entity,
            group=wandb_group(lc.wandb.group, ex),
            tags=wandb_tags(lc.wandb.tags, ex, int(cfg.seed)),
            job_type="train",
            config=dict(hparams),
            mode=lc.wandb.mode,
            **({"resume": "allow"} if resume else {}),
        )
    return RunLogger(loggers, run_id, run_dir)


def log_evaluation(cfg: Any, out_dir: Path, record: Mapping[str, Any] | None = None) -> None:
    """One ``uavlae.evaluate`` (a point of a scenario sweep) as its own wandb run, in the group of
    its invocation: the metrics at the checkpoint's frames, in the summary, the per-episode records
    as a table and the trajectory pictures. ``record``: the evaluation's ``evaluation.json``
    (default: read from ``out_dir``). Nothing when ``logger.wandb.mode=disabled``."""
    from uavlae.runlog import episodes_table, numbers, wandb_group, wandb_name, wandb_tags

    lc = make_logger_config(cfg.logger)
    if lc.wandb.mode == "disabled":
        return
    if record is None:
        record = json.loads((Path(out_dir) / "evaluation.json").read_text())
    from torchrl.record.loggers import WandbLogger

    ex = make_experiment_config(cfg.experiment)
    spec = record["spec"]
    method, seed, frames = str(spec["method"]), int(spec["seed"]), int(spec.get("frames") or 0)
    logger = WandbLogger(
        exp_name=wandb_name(method, seed, ex),
        offline=lc.wandb.mode == "offline",
        save_dir=str(Path(out_dir).resolve()),  # absolute, as make_logger's: a joined service has its own cwd
        id=f"eval-{method}-{uuid.uuid4().hex[:10]}"[:64],
        project=lc.wandb.project,
        entity=lc.wandb.entity,
        group=wandb_group(lc.wandb.group, ex),
        tags=wandb_tags(lc.wandb.tags, ex, seed, kind="evaluate", method=method),
        job_type="evaluate",
        config={k: record.get(k) for k in ("spec", "experiment", "env", "meta", "eval_set_file", "n_scenarios")},
        mode=lc.wandb.mode,
    )
    try:
        metrics = numbers(record["metrics"], "eval/")
        logger.log_metrics(metrics, step=frames)
        payload: dict[str, Any] = {}
        if (Path(out_dir) / "episodes.csv").is_file():
            payload["eval/episodes"] = episodes_table(Path(out_dir) / "episodes.csv")
        import wandb

        for p in sorted(Path(out_dir).glob("trajectory_*.png")):
            payload[f"eval/trajectory_{p.stem.rsplit('_', 1)[-1]}"] = wandb.Image(str(p))
        if payload:
            logger.experiment.log(payload)
        logger.experiment.summary.update({**metrics, "frames": frames, "wall_s": record.get("wall_s")})
    finally:
        logger.close()


def run_metadata(cfg_dict: Mapping[str, Any]) -> dict[str, Any]:
    """The commit, the package versions, the machine and the command: for a Hydra job (a sweep's too, whose
    worker's argv is the launcher's) the one command that reruns this run alone."""
    import shlex

    from uavlae.machine import describe_machine

    meta: dict[str, Any] = {"git": git_info(), "packages": package_versions(), "machine": describe_machine(),
                            "argv": list(sys.argv), "pid": os.getpid()}
    try:
        from hydra.core.hydra_config import HydraConfig

        hc = HydraConfig.get()
        task = list(hc.overrides.task)
        module = "uavlae.evaluate" if "evaluate" in str(hc.job.name) else "uavlae.train"
        meta["overrides"] = task
        meta["command"] = shlex.join(["python", "-m", module, *task])
    except ValueError:  # not a Hydra job (the tests call run() in-process)
        pass
    return meta


def redact_secrets(cfg_dict: dict[str, Any]) -> dict[str, Any]:
    """Refuse to write a config that holds the LLM API key itself (only its variable's name
    may appear): any string equal to the key's value becomes ``"***"``."""
    name = (cfg_dict.get("llm") or {}).get("api_key_env")
    secret = os.environ.get(name) if name else None
    if not secret:
        return cfg_dict

    def walk(x: Any) -> Any:
        if isinstance(x, dict):
            return {k: walk(v) for k, v in x.items()}
        if isinstance(x, list):
            return [walk(v) for v in x]
        if isinstance(x, str) and secret in x:
            return x.replace(secret, "***")
        return x

    return walk(cfg_dict)


