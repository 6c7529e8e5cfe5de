"""What a run shows on its dashboard (wandb), so that a dashboard rebuilds the report's figures.

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

Training runs log through :class:`uavlae.factories.RunLogger`, which publishes the summary and the
tables when it closes after the run has written its final metrics; ``uavlae.evaluate`` calls
:func:`log_evaluation` once its record is written.
"""

from __future__ import annotations

import csv
import json
import uuid
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from uavlae.files import train_eval_dir

WANDB_TAG_CHARS = 64  # wandb refuses longer tags


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
    import wandb

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


def log_evaluation(cfg: Any, out_dir: Path, record: Mapping[str, Any] | None = None) -> None:
    """One ``uavlae.evaluate`` (a point of a scenario sweep) as its own wandb run, in the group of
    its invocation: the metrics at the checkpoint's frames, in the summary, the per-episode records
    as a table and the trajectory pictures. ``record``: the evaluation's ``evaluation.json``
    (default: read from ``out_dir``). Nothing when ``logger.wandb.mode=disabled``."""
    from uavlae.factories import make_experiment_config, make_logger_config

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
