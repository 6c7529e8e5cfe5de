"""What a run records of itself beside its results: its metadata (the commit, the package
versions, the machine, the command that reruns it), its logs (CSV always, wandb unless
disabled) and what its dashboard shows, and the secrets kept out of all of them.

The dashboard (wandb), so that it rebuilds the report's figures:

- **Group**: the invocation, i.e. the profile and the sweeps' root folder (``quick:runs/quick``),
  so that two campaigns with the same sweeps (``make quick`` and ``make baselines-budget``) do not
  mix; a run outside any sweep has none unless ``logger.wandb.group`` names one.
- **Name**: the method and the seed (and the sweep's point where it is not the default):
  ``sac seed2``, ``sac seed0 n_ou=3``.
- **Tags**: ``method:``, ``seed:``, ``sweep:``, ``point:``, ``profile:`` (a figure's runs are a
  filter on them), and ``kind:train`` or ``kind:evaluate``.
- **Summary**: a training run's ``final_metrics.json`` (the final evaluation, the heuristic's and
  the uniform-random policy's on the same scenarios, the actor with its advisor, the wall clock);
  an evaluation's metrics.
- **Tables**: the per-episode records (``episodes.csv``) of the final evaluation and of each
  baseline, and of every evaluation of a sweep, as ``wandb.Table``.

Training runs log through :class:`RunLogger` (built by :func:`make_logger` from ``conf/logger``),
which publishes the summary and the tables when it closes after the run has written its final
metrics; ``uavlae.evaluate`` calls :func:`log_evaluation` once its record is written. This module
imports nothing of uavlae beyond plain helpers, so the factories and the entry points can use it.
"""

from __future__ import annotations

import csv
import importlib.metadata as metadata
import json
import os
import shlex
import subprocess
import sys
import uuid
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, Literal

from hydra.core.hydra_config import HydraConfig
from pydantic import Field
from torchrl.record.loggers import CSVLogger, WandbLogger

from uavlae.files import train_eval_dir
from uavlae.machine import describe_machine
from uavlae.validation import StrictModel, parse_model

# The checkout the package sits in (its parent folder); installed, this is site-packages, no checkout.
REPO_ROOT = Path(__file__).resolve().parent.parent
WANDB_TAG_CHARS = 64  # wandb refuses longer tags
# Commands that only read a run (evaluate, export) write next to the checkpoint: no Hydra run
# folder, no .hydra/ copy and no log file in the working directory.
NO_HYDRA_OUTPUT = ("hydra.output_subdir=null", "hydra.run.dir=.", "hydra/job_logging=stdout")


# ---------------------------------------------------------------------------- configs


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


def make_logger_config(cfg: Any) -> LoggerConfig:
    return parse_model(LoggerConfig, cfg, prefix="logger", title="logger")


def make_experiment_config(cfg: Any) -> ExperimentConfig:
    return parse_model(ExperimentConfig, cfg, prefix="experiment", title="experiment")


# ---------------------------------------------------------------------------- metadata and secrets


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


def run_metadata(cfg_dict: Mapping[str, Any]) -> dict[str, Any]:
    """The commit, the package versions, the machine and the command: for a Hydra job (a sweep's too, whose
    worker's argv is the launcher's) the one command that reruns this run alone."""
    meta: dict[str, Any] = {"git": git_info(), "packages": package_versions(), "machine": describe_machine(),
                            "argv": list(sys.argv), "pid": os.getpid()}
    try:
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


# ---------------------------------------------------------------------------- the dashboard


def wandb_group(configured: str | None, ex: Any) -> str | None:
    """The run's wandb group: ``logger.wandb.group`` when set, else the invocation
    (``<profile>:<experiment.root>``, or the root alone without a profile) for a run of a sweep."""
    if configured:
        return configured
    if not ex.sweep:
        return None
    root = str(ex.root).rstrip("/")
    return f"{ex.profile}:{root}" if ex.profile else root


def wandb_name(method: str, seed: int, ex: Any) -> str:
    """``<method> seed<seed>``, and the sweep's point where it is not the default one."""
    name = f"{method} seed{seed}"
    return f"{name} {ex.point}" if ex.sweep and ex.point != "default" else name


def wandb_tags(tags: Sequence[str], ex: Any, seed: int, kind: str = "train", method: str | None = None) -> list[str]:
    """The run's wandb tags: the configured ones, then its method, seed, sweep, point, profile and
    kind (a dashboard filters each figure's runs by these), each cut to wandb's 64 characters."""
    out = list(tags) + list(ex.tags) + [f"method:{method or ex.method}", f"seed:{seed}"]
    if ex.sweep:
        out += [f"sweep:{ex.sweep}", f"point:{ex.point}"]
    if ex.profile:
        out.append(f"profile:{ex.profile}")
    out.append(f"kind:{kind}")
    return list(dict.fromkeys(t[:WANDB_TAG_CHARS] for t in out))


def _cell(v: str) -> Any:
    if v in ("True", "False"):
        return v == "True"
    try:
        f = float(v)
    except ValueError:
        return v
    return int(f) if f.is_integer() and "." not in v and "e" not in v.lower() else f


def episodes_table(path: Path) -> Any:
    """An ``episodes.csv`` (one row per evaluation episode) as a ``wandb.Table``."""
    import wandb  # deferred: slow to import, and only a run that logs to wandb needs it

    with open(path, newline="") as fh:
        rows = list(csv.reader(fh))
    if not rows:
        raise ValueError(f"{path} is empty: no header, no episodes")
    return wandb.Table(columns=rows[0], data=[[_cell(v) for v in r] for r in rows[1:]])


def numbers(d: Mapping[str, Any], prefix: str = "") -> dict[str, float]:
    """The numeric entries of ``d`` (no booleans), their keys prefixed."""
    return {f"{prefix}{k}": v for k, v in d.items() if isinstance(v, (int, float)) and not isinstance(v, bool)}


def final_tables(run_dir: Path, frames: int) -> dict[str, Path]:
    """A training run's per-episode records: the final evaluation (``eval/episodes``), each
    baseline (``baseline/<name>/episodes``) and the actor with its advisor (``advised/episodes``)."""
    ev = Path(run_dir) / "eval"
    out = {"eval/episodes": train_eval_dir(run_dir, frames) / "episodes.csv"}
    for d in sorted(ev.glob("baseline_*")):
        out[f"baseline/{d.name.removeprefix('baseline_')}/episodes"] = d / "episodes.csv"
    out["advised/episodes"] = ev / "with_advisor" / "episodes.csv"
    return {k: p for k, p in out.items() if p.is_file()}


def publish_final(experiment: Any, run_dir: Path) -> bool:
    """Put a finished training run's ``final_metrics.json`` into the wandb run's summary and its
    per-episode records into tables; False (nothing done) while the run has no final metrics."""
    final_file = Path(run_dir) / "final_metrics.json"
    if not final_file.is_file():
        return False
    final = json.loads(final_file.read_text())
    tables = {k: episodes_table(p) for k, p in final_tables(run_dir, int(final.get("frames", 0))).items()}
    if tables:
        experiment.log(tables)
    experiment.summary.update(numbers(final))
    return True


# ---------------------------------------------------------------------------- logs


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
        import wandb  # deferred: slow to import, and only a run that logs to wandb needs it

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
            publish_final(lg.experiment, self.run_dir)
        for lg in self.loggers.values():
            close = getattr(lg, "close", None)
            if close is not None:
                close()


def make_logger(cfg: Any, run_dir: Path, run_id: str, hparams: Mapping[str, Any],
                resume: bool = False) -> RunLogger:
    """``conf/logger`` -> :class:`RunLogger`; CSV under ``<run_dir>/logs/scalars``, the wandb
    run (offline by default) under ``<run_dir>/wandb`` with the resolved config, the git
    commit and the package versions, grouped, named and tagged as :mod:`uavlae.runlog` says.
    ``resume``: the wandb run of that id continues (the same run, its steps going on from the
    checkpoint's frames)."""
    lc = make_logger_config(cfg.logger)
    ex = make_experiment_config(cfg.experiment)
    loggers: dict[str, Any] = {}
    if lc.csv:
        loggers["csv"] = CSVLogger(exp_name="logs", log_dir=str(run_dir))
    if lc.wandb.mode != "disabled":
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
    lc = make_logger_config(cfg.logger)
    if lc.wandb.mode == "disabled":
        return
    if record is None:
        record = json.loads((Path(out_dir) / "evaluation.json").read_text())
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
        import wandb  # deferred: slow to import, and only a run that logs to wandb needs it

        for p in sorted(Path(out_dir).glob("trajectory_*.png")):
            payload[f"eval/trajectory_{p.stem.rsplit('_', 1)[-1]}"] = wandb.Image(str(p))
        if payload:
            logger.experiment.log(payload)
        logger.experiment.summary.update({**metrics, "frames": frames, "wall_s": record.get("wall_s")})
    finally:
        logger.close()


def trim_csv_scalars(log_dir: Path, max_step: int) -> None:
    """Drop CSV rows logged after ``max_step`` (a resumed run logs those frames again)."""
    for f in Path(log_dir).rglob("*.csv"):
        lines = f.read_text().splitlines()
        kept = [ln for ln in lines if ln and int(float(ln.split(",", 1)[0])) <= max_step]
        if len(kept) != len(lines):
            f.write_text("".join(ln + "\n" for ln in kept))


def without_hydra_output(argv: list[str]) -> list[str]:
    """``argv`` plus :data:`NO_HYDRA_OUTPUT` (a setting the user typed wins)."""
    given = {a.split("=", 1)[0] for a in argv[1:]}
    return argv + [o for o in NO_HYDRA_OUTPUT if o.split("=", 1)[0] not in given]


def route_library_output(show: bool) -> None:
    """Where wandb's and torchrl's own messages go: the run's log only (``show`` false), or the
    terminal as well (``logger.library_output``). torchrl prints to the terminal through a handler
    of its own, with colour codes; it then writes through the file handlers of the root logger
    (Hydra's ``<job>.log`` in the run folder) instead. wandb keeps its messages in its own log in
    the run's ``wandb/`` folder when silent (``WANDB_SILENT``, unless the environment sets it)."""
    import logging
    import os

    if show:
        return
    os.environ.setdefault("WANDB_SILENT", "true")
    lg = logging.getLogger("torchrl")
    for h in list(lg.handlers):
        if isinstance(h, logging.StreamHandler) and not isinstance(h, logging.FileHandler):
            lg.removeHandler(h)
    for h in logging.getLogger().handlers:
        if isinstance(h, logging.FileHandler) and h not in lg.handlers:
            lg.addHandler(h)
