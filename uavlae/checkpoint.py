"""Atomic training checkpoints: ``<run_dir>/checkpoints/last.pt`` and the one before, ``prev.pt``.

A checkpoint is written at a collector-batch boundary and holds everything the loop needs to
continue exactly: the learner (actor, critics, targets, optimisers, alpha, Lagrange state),
the replay buffer, the collector (its env state and frame counter), the RNG states (torch,
numpy, python, the env's generator), the loop counters, the logger state (wandb run id) and
the resolved config. The write goes to a temporary file in the same folder, is fsynced and
renamed over ``last.pt`` (after the old one became ``prev.pt``), so a crash at any moment
leaves at least one complete checkpoint.

Checkpoints are pickles of our own making (numpy RNG state, tensordicts): load only trusted
files (``torch.load(weights_only=False)``).
"""

from __future__ import annotations

import os
import random
from pathlib import Path
from typing import Any

import numpy as np
import torch

from uavlae.files import atomic_write

LAST, PREV = "last.pt", "prev.pt"
BEST = "best.pt"  # trainer.keep_best: the networks of the best evaluation so far (no replay buffer)
FORMAT_VERSION = 1


def checkpoint_dir(run_dir: str | os.PathLike[str]) -> Path:
    return Path(run_dir) / "checkpoints"


def rng_state(env_generator: torch.Generator | None = None) -> dict[str, Any]:
    state = {"torch": torch.get_rng_state(), "numpy": np.random.get_state(), "python": random.getstate()}
    if env_generator is not None:
        state["env"] = env_generator.get_state()
    return state


def set_rng_state(state: dict[str, Any], env_generator: torch.Generator | None = None) -> None:
    torch.set_rng_state(state["torch"])
    np.random.set_state(state["numpy"])
    random.setstate(state["python"])
    if env_generator is not None and "env" in state:
        env_generator.set_state(state["env"])


def seed_everything(seed: int) -> None:
    torch.manual_seed(seed)
    np.random.seed(seed % 2**32)
    random.seed(seed)


def save_checkpoint(state: dict[str, Any], run_dir: str | os.PathLike[str], keep: int = 2) -> Path:
    """Write ``state`` atomically as ``last.pt`` (the previous ``last.pt`` becomes ``prev.pt``
    when ``keep`` is 2). Returns the path of ``last.pt``."""
    d = checkpoint_dir(run_dir)
    d.mkdir(parents=True, exist_ok=True)
    state = {"format_version": FORMAT_VERSION, **state}
    return atomic_write(d / LAST, lambda fh: torch.save(state, fh), previous=d / PREV if keep >= 2 else None)


def save_best(state: dict[str, Any], run_dir: str | os.PathLike[str]) -> Path:
    """Write ``state`` atomically as ``best.pt``, beside ``last.pt``; a checkpoint file that
    ``uavlae.evaluate`` and ``uavlae.export`` take as they take ``last.pt``, which a run's
    rotation never touches and a resume never reads."""
    state = {"format_version": FORMAT_VERSION, **state}
    return atomic_write(checkpoint_dir(run_dir) / BEST, lambda fh: torch.save(state, fh))


def resolve_checkpoint(path: str | os.PathLike[str]) -> Path:
    """A checkpoint file, or a run dir / its checkpoints dir -> the newest complete checkpoint."""
    p = Path(path).expanduser()
    if p.is_file():
        return p
    for d in (checkpoint_dir(p), p):
        for name in (LAST, PREV):
            if (d / name).is_file():
                return d / name
    raise FileNotFoundError(f"no checkpoint at {path} (looked for {LAST} / {PREV} in it and in its checkpoints/)")


def load_checkpoint(path: str | os.PathLike[str], map_location: str | torch.device = "cpu",
                    mmap: bool = False) -> tuple[dict[str, Any], Path]:
    """Load the checkpoint at ``path`` (file or run dir). A damaged ``last.pt`` falls back to
    ``prev.pt``. Returns ``(state, file)``. ``mmap``: map the tensors from the file instead of
    reading them (``torch.load(mmap=True)``), for a reader that needs only part of it: an
    evaluation reads the actor, not the replay buffer that makes a checkpoint gigabytes."""
    p = resolve_checkpoint(path)
    candidates = [p]
    if p.name == LAST and (p.parent / PREV).is_file():
        candidates.append(p.parent / PREV)
    err: Exception | None = None
    for c in candidates:
        try:
            return torch.load(c, map_location=map_location, weights_only=False, mmap=mmap), c
        except Exception as e:  # a torn or truncated file: try the previous one
            err = e
    raise RuntimeError(f"could not read any checkpoint at {path}: {err}") from err


def run_dir_of(checkpoint_file: str | os.PathLike[str]) -> Path:
    p = Path(checkpoint_file).resolve()
    return p.parent.parent if p.parent.name == "checkpoints" else p.parent
