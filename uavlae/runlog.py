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
:func:`uavlae.factories.log_evaluation` once its record is written. This module imports nothing
of uavlae beyond plain helpers, so the factories can use it.
"""

from __future__ import annotations

import csv
import json
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
