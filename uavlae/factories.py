"""``make_*`` factories, one per config group, each fed by its own group (docs/style.md rule 5).

``conf/env`` -> :func:`make_env`, ``conf/algo`` -> :func:`make_learner`, ``conf/advisor`` ->
:func:`make_advisor` and the override around the actor, :func:`make_policy`; ``heuristic_kind``
with the node of its numbers (:class:`HeuristicGroup`) -> :func:`make_heuristic`; ``conf/llm``
-> :func:`make_llm_advisor`; ``controller`` -> :func:`make_controller`; ``conf/safety_filter``
-> :func:`make_safety_filter`; ``conf/trainer`` -> :func:`make_trainer_config`. A factory that
composes what another group builds (the override's heuristic and LLM) is handed that group by
the entry point, which alone reads the composed config. Each validates its node with a pydantic
model (unknown keys and out-of-range values are errors that name the field); the env, algo,
heuristic, LLM, logger and experiment models live with their code.

The run's metadata, logger and secret redaction are :mod:`uavlae.runlog`'s; they are imported
here too, where the entry points have always found them.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Literal, NamedTuple

import torch
from omegaconf import DictConfig
from pydantic import Field, model_validator

from uavlae.algos import CONFIG_MAKERS, MAKERS, OFF_POLICY, make_learner as _make_learner
from uavlae.envs import EnvConfig, UAVEnv, make_env_config
from uavlae.files import dump_json
from uavlae.llm import LLMAdvisor, make_llm_config
from uavlae.policies.advisor import Advisor, HeuristicAdvisor, LLMAdvisorAdapter, ScriptedAdvisor
from uavlae.policies.greedy import GreedyPolicy, make_greedy_config
from uavlae.policies.heuristic import HeuristicPolicy, make_heuristic_config
from uavlae.policies.override import OverridePolicy
from uavlae.policies.random import UniformRandomPolicy
from uavlae.policies.safety import make_safety_filter, make_safety_filter_config  # the safety_filter group's
from uavlae.policies.student import AmortizedAdvisor, StudentConfig
from uavlae.runlog import (
    NO_HYDRA_OUTPUT,
    REPO_ROOT,
    ExperimentConfig,
    LoggerConfig,
    RunLogger,
    WandbConfig,
    git_info,
    log_evaluation,
    make_experiment_config,
    make_logger,
    make_logger_config,
    package_versions,
    redact_secrets,
    run_metadata,
    trim_csv_scalars,
    without_hydra_output,
)
from uavlae.validation import StrictModel, parse_model

__all__ = [
    # the factories, their configs and the groups they are fed
    "AdvisorConfig", "CONF_DIR", "HeuristicGroup", "PACKAGE_DIR", "RunConfig", "TrainerConfig", "check_device",
    "make_advisor", "make_advisor_config", "make_controller", "make_env", "make_heuristic", "make_learner",
    "make_llm_advisor", "make_policy", "make_safety_filter", "make_safety_filter_config", "make_trainer_config",
    "validate_config",
    # uavlae.runlog's and uavlae.files', where the entry points first imported them
    "ExperimentConfig", "LoggerConfig", "NO_HYDRA_OUTPUT", "REPO_ROOT", "RunLogger", "WandbConfig", "dump_json",
    "git_info", "log_evaluation", "make_experiment_config", "make_logger", "make_logger_config", "package_versions",
    "redact_secrets", "run_metadata", "trim_csv_scalars", "without_hydra_output",
]

PACKAGE_DIR = Path(__file__).resolve().parent
# The configs ship inside the package, so an installed uavlae composes the same runs as a checkout.
CONF_DIR = PACKAGE_DIR / "conf"
# heuristic_kind -> the root node that holds that heuristic's numbers (conf/config.yaml)
HEURISTIC_NODES = {"greedy": "greedy", "planner": "heuristic"}
# the scripted advisor's and the student's generators, apart from the trigger's stream (seed)
SCRIPTED_SEED_OFFSET = 7919
STUDENT_SEED_OFFSET = 7907


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
    # the learner's actor in evaluations and in the exported pilot: its mean action, or a draw from
    # its tanh-normal policy from a stream seeded with eval_seed (uavlae.policies.sampling)
    eval_actor: Literal["mean", "sample"] = "mean"
    checkpoint_every_frames: int = Field(ge=0)
    keep_checkpoints: int = Field(ge=1, le=2)
    # also keep checkpoints/best.pt: the networks of the evaluation with the highest
    # selection_score (uavlae.selection) of the deployed policy on the evaluation set
    keep_best: bool = False
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
    # beyond the paper: the advisor labels every row, the actor's own too, for the cloning term (DAgger)
    label_all: bool = False
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
        if self.label_all and self.kind != "heuristic":
            raise ValueError(f"advisor.label_all labels every row with the advisor's answer, which only the heuristic "
                             f"gives at no cost; advisor.kind={self.kind!r} (use it with +exp=sac_heuristic_planner)")
        if self.phase_out_frames is not None and self.mode not in ("proximity", "fixed_prob"):
            raise ValueError(f"advisor.phase_out_frames anneals d_th (proximity) or fp (fixed_prob); "
                             f"advisor.mode={self.mode!r} has neither")
        return self

    @property
    def needs_heuristic(self) -> bool:
        """A heuristic acts: as the advisor, or where the advisor fails (``fallback``)."""
        return self.kind == "heuristic" or self.fallback == "heuristic"


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
    return parse_model(TrainerConfig, cfg, prefix="trainer", title="trainer")


def make_advisor_config(cfg: Any) -> AdvisorConfig:
    return parse_model(AdvisorConfig, cfg, prefix="advisor", title="advisor")


def validate_config(cfg: DictConfig) -> None:
    """Validate every group of a composed config; ``ValueError`` names the bad field."""
    root = {k: cfg[k] for k in RunConfig.model_fields}
    run = parse_model(RunConfig, root, prefix="config", title="config")
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
    make_heuristic_config(cfg.heuristic)
    make_greedy_config(cfg.greedy)
    make_safety_filter_config(cfg.get("safety_filter"))
    if run.controller == "learner":
        if cfg.get("algo") is None:
            raise ValueError("controller=learner needs an algo (algo=sac|sac_lag|ppo|ddpg|cpo|wang|theile|crossq)")
        name = cfg.algo.name
        if name not in MAKERS:
            raise ValueError(f"algo.name must be one of {sorted(MAKERS)}, got {name!r}")
        CONFIG_MAKERS[name](cfg.algo)
        if float(cfg.algo.get("clone_weight", 0.0) or 0.0) > 0 and adv.kind == "none":
            raise ValueError(
                f"algo.clone_weight={cfg.algo.clone_weight} clones the executed advice, but advisor.kind is 'none': "
                "there is none to clone (use +exp=sac_heuristic, sac_llm, ... or clone_weight=0)"
            )
        if adv.label_all and not float(cfg.algo.get("clone_weight", 0.0) or 0.0) > 0:
            raise ValueError("advisor.label_all labels every row for the cloning term, but algo.clone_weight is 0 "
                             f"(algo {name!r}): set algo.clone_weight > 0, or advisor.label_all=false")
        if adv.kind != "none" and name not in OFF_POLICY:
            raise ValueError(
                f"advisor.kind={adv.kind!r} with algo {name!r}: the override stores executed actions for an "
                "off-policy learner; on-policy PPO/CPO would need the advisor's log-probabilities"
            )
    if run.controller == "llm" and adv.amortize:
        raise ValueError("advisor.amortize with controller=llm: the LLM alone is the LLM at every step, not a student")
    if cfg.get("llm") is not None:  # always: a key given in its place is refused before anything is written
        make_llm_config(cfg.llm)


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


class HeuristicGroup(NamedTuple):
    """The heuristic's config group: ``heuristic_kind`` and the node of that kind's numbers
    (``greedy`` for the paper's greedy controller, ``heuristic`` for the planner)."""

    kind: Literal["greedy", "planner"]
    cfg: Any

    @classmethod
    def of(cls, cfg: DictConfig) -> "HeuristicGroup":
        """The group in a composed config."""
        return cls(cfg.heuristic_kind, cfg[HEURISTIC_NODES[cfg.heuristic_kind]])


def make_heuristic(group: HeuristicGroup, env_cfg: EnvConfig) -> Any:
    """``heuristic_kind`` -> the paper's greedy controller (:class:`uavlae.policies.greedy.GreedyPolicy`,
    the ``greedy`` node) or the visibility-graph planner beyond the paper
    (:class:`uavlae.policies.heuristic.HeuristicPolicy`, the ``heuristic`` node)."""
    if group.kind == "greedy":
        return GreedyPolicy(env_cfg, group.cfg)
    return HeuristicPolicy(env_cfg, group.cfg)


def make_llm_advisor(llm_cfg: Any) -> LLMAdvisor:
    """``conf/llm`` -> :class:`uavlae.llm.LLMAdvisor` (it starts the local server on first use
    when ``llm.base_url`` is null; the API key is read from ``llm.api_key_env`` only)."""
    return LLMAdvisor(make_llm_config(llm_cfg))


def make_advisor(advisor_cfg: Any, env_cfg: EnvConfig, *, seed: int, heuristic: Any = None,
                 llm_cfg: Any = None) -> Advisor | None:
    """``conf/advisor`` -> who answers the triggered rows (None for ``kind: none``): ``heuristic``
    (built by :func:`make_heuristic`) as an advisor, a scripted advisor, or the LLM of ``llm_cfg``
    (``conf/llm``), through its student with ``amortize``."""
    adv = make_advisor_config(advisor_cfg)
    if adv.kind == "none":
        return None
    if adv.kind == "heuristic":
        return HeuristicAdvisor(heuristic)
    if adv.kind in ScriptedAdvisor.KINDS:
        return ScriptedAdvisor(adv.kind, seed=seed + SCRIPTED_SEED_OFFSET)
    llm = LLMAdvisorAdapter(make_llm_advisor(llm_cfg), env_cfg)
    return AmortizedAdvisor(llm, adv.student, seed=seed + STUDENT_SEED_OFFSET) if adv.amortize else llm


def make_policy(advisor_cfg: Any, actor: Any, env_cfg: EnvConfig, *, seed: int,
                heuristic: HeuristicGroup | None = None, llm_cfg: Any = None) -> OverridePolicy:
    """``conf/advisor`` -> the collection policy: ``actor`` wrapped by
    :class:`uavlae.policies.override.OverridePolicy`, alone (``kind: none``) or with its advisor;
    ``heuristic`` (its group) builds the heuristic that advises or acts where advice fails,
    ``llm_cfg`` the LLM."""
    adv = make_advisor_config(advisor_cfg)
    if adv.kind == "none":
        # wrapped all the same: one policy type for the collector (action_source, resume state)
        return OverridePolicy(actor, None, mode="never", fallback="policy", seed=seed)
    if adv.needs_heuristic and heuristic is None:
        raise ValueError(f"advisor.kind={adv.kind!r}, advisor.fallback={adv.fallback!r}: a heuristic acts, so "
                         "make_policy needs its group (heuristic=HeuristicGroup.of(cfg))")
    h = make_heuristic(heuristic, env_cfg) if adv.needs_heuristic else None
    return OverridePolicy(
        actor,
        make_advisor(adv, env_cfg, seed=seed, heuristic=h, llm_cfg=llm_cfg),
        mode=adv.mode,
        d_th=adv.d_th,
        fp=adv.fp,
        fallback=adv.fallback,
        heuristic=h,
        seed=seed,
        hold_steps=adv.hold_steps,
        max_calls=adv.max_calls,
        perception_radius=env_cfg.safety.perception_radius,
        phase_out_frames=adv.phase_out_frames,
        agree_tol=adv.agree_tol,
        label_all=adv.label_all,
    )


def make_controller(controller: str, env_cfg: EnvConfig, *, seed: int, heuristic: HeuristicGroup | None = None,
                    action_spec: Any = None, advisor_cfg: Any = None, llm_cfg: Any = None) -> Any:
    """``controller`` -> the evaluation-only controllers: ``heuristic`` (the greedy baseline),
    ``llm`` (the LLM of ``advisor_cfg`` and ``llm_cfg`` at every step, the heuristic for failed
    answers when ``advisor.fallback=heuristic``) or ``random`` (uniform in ``action_spec``'s box,
    seeded by ``seed``)."""
    if controller == "random":
        if action_spec is None:
            raise ValueError("controller=random needs the env's action_spec")
        return UniformRandomPolicy(action_spec, seed=seed)
    if heuristic is None:
        raise ValueError(f"controller={controller!r} flies a heuristic: make_controller needs its group "
                         "(heuristic=HeuristicGroup.of(cfg))")
    acting = make_heuristic(heuristic, env_cfg)
    if controller == "heuristic":
        return acting
    if controller == "llm":
        return make_policy(advisor_cfg, acting, env_cfg, seed=seed, heuristic=heuristic, llm_cfg=llm_cfg)
    raise ValueError(f"controller must be heuristic, llm or random here, got {controller!r}")
