"""A run's lifecycle: the folder one process owns, what a command does with what that folder
holds, and a stop on a signal that leaves a checkpoint.

- :class:`RunFolder`: a run folder is owned by one process while it runs. A second process
  pointed at it refuses at once, naming the folder and the owner's pid (an advisory
  ``fcntl`` lock on ``<run_dir>/.lock``, released by the system when the owner exits, however it
  exits). The LLM alone's shards, which fly one evaluation side by side by design, each own a
  lock of their own (``.lock.shard<s>of<S>``).
- :func:`plan`: new, resume or done, decided in one place from the run's recorded config:
  ``resume=RUN`` continues a run (a command-line setting that conflicts with the recorded run
  is an error naming each key; :data:`RESUMABLE_KEYS` may change, and extending
  ``trainer.total_frames`` is then honoured); ``experiment.reuse=true`` (the sweeps) keeps a
  finished run, resumes one with a checkpoint, and starts clean a run killed before its first
  checkpoint; a new run into a folder that holds a run is an error.
- :class:`GracefulStop`: SIGTERM (what Slurm sends before a time limit or a preemption) and
  SIGINT end the current batch; the loop then writes a checkpoint and raises :class:`RunStopped`,
  whose message says how to resume. It covers every phase of a command, not only training: an
  evaluation (the baselines and the actor with its advisor among them) checks it at every episode
  step (:meth:`GracefulStop.check` raises :class:`StopRequested`), and a wait that has no steps,
  such as a local LLM server starting, is cut short at once (:meth:`GracefulStop.interruptible`).
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import os
import shutil
import signal
import time
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf

from uavlae.checkpoint import LAST, PREV, checkpoint_dir, load_checkpoint, run_dir_of
from uavlae.errors import ConfigError

__all__ = [
    "GracefulStop", "Plan", "RESUMABLE_KEYS", "RunFolder", "RunFolderBusy", "RunStopped", "StopRequested",
    "config_differences", "flatten_keys", "plan",
]

# May differ between a run's recorded config and the command that continues it. Runtime settings
# (how it runs, not what it computes) are always taken from the new command; the budgets only
# when the command sets them (extending total_frames continues training to the new budget);
# the LLM alone's call budget and shards are how one evaluation is split into invocations, and the
# with-advisor evaluation's call budget is what a finished training may spend on that one evaluation.
RUNTIME_KEYS = ("threads", "device", "trainer.progress_bar", "trainer.progress_every_s", "trainer.progress_first_s",
                "logger.wandb.mode", "logger.library_output")
BUDGET_KEYS = ("trainer.total_frames", "trainer.total_episodes", "trainer.llm_call_budget", "trainer.eval_shard",
               "trainer.eval_shards", "trainer.eval_advisor_max_calls")
RESUMABLE_KEYS = RUNTIME_KEYS + BUDGET_KEYS
# settings removed from the code, which a run saved before holds: they had no effect (llm.fallback
# was logged, never applied: advisor.fallback acted), so a recorded config is read without them
REMOVED_KEYS = ("llm.fallback",)
# what says how to find a run, not what it is
BOOKKEEPING_KEYS = ("resume", "experiment.reuse", "run_dir", "checkpoint", "out")
# what a rerun after a kill before the first checkpoint removes: everything the run wrote
RUN_OUTPUTS = ("config.json", "config.yaml", "meta.json", "summary.json", "final_metrics.json", "eval_set.json",
               "logs", "eval", "checkpoints", "wandb", ".hydra", "train.log", "error.txt")


class RunFolderBusy(RuntimeError):
    """Another live process owns the run folder."""


class StopRequested(Exception):
    """A stop (SIGTERM, SIGINT) reached a phase between training batches (an evaluation, a server
    start); the command turns it into :class:`RunStopped` once what must be saved is."""

    def __init__(self, signum: int):
        super().__init__(f"stopped by signal {signum}")
        self.signum = signum


class RunStopped(RuntimeError):
    """SIGTERM or SIGINT ended the run after a checkpoint; ``str()`` says how to resume."""

    def __init__(self, message: str, signum: int):
        super().__init__(message)
        self.signum = signum


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
    w = flatten_keys(want)
    h = {k: v for k, v in flatten_keys(have).items() if k not in REMOVED_KEYS}
    added = sorted(set(w) - set(h))
    changed = sorted(k for k in set(w) | set(h) if k not in added and w.get(k) != h.get(k))
    return changed, added


def _under(key: str, prefixes: Sequence[str]) -> bool:
    return any(key == p or key.startswith(p + ".") for p in prefixes)


# ---------------------------------------------------------------------------- the folder


class RunFolder:
    """A run folder, owned by this process between ``acquire()`` and ``release()`` (or a ``with``)."""

    def __init__(self, path: str | os.PathLike[str], lock_name: str = ".lock"):
        self.path = Path(path)
        self.lock_file = self.path / lock_name
        self._fh: Any = None

    def acquire(self) -> RunFolder:
        self.path.mkdir(parents=True, exist_ok=True)
        fh = open(self.lock_file, "a+")
        try:
            fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            fh.seek(0)
            owner = fh.read().strip() or "unknown"
            fh.close()
            raise RunFolderBusy(
                f"run folder {self.path} is in use by process {owner}; wait for it to end, or choose another run_dir"
            ) from None
        fh.seek(0)
        fh.truncate()
        fh.write(str(os.getpid()))
        fh.flush()
        self._fh = fh
        return self

    def release(self) -> None:
        if self._fh is not None:
            fcntl.flock(self._fh, fcntl.LOCK_UN)
            self._fh.close()
            self._fh = None

    def __enter__(self) -> RunFolder:
        return self.acquire()

    def __exit__(self, *exc: Any) -> None:
        self.release()

    def clean(self) -> None:
        """Remove what an earlier, unfinished attempt wrote (it never reached a checkpoint)."""
        for name in RUN_OUTPUTS:
            p = self.path / name
            if p.is_dir():
                shutil.rmtree(p)
            elif p.exists():
                p.unlink()


def lock_name(cfg: DictConfig) -> str:
    """The LLM alone's shards each own their share of one evaluation folder."""
    shards = int(OmegaConf.select(cfg, "trainer.eval_shards", default=1) or 1)
    if cfg.controller == "llm" and shards > 1:
        return f".lock.shard{int(cfg.trainer.eval_shard)}of{shards}"
    return ".lock"


# ---------------------------------------------------------------------------- new, resume or done


@dataclass
class Plan:
    """What a command does with its run folder: ``kind`` is ``new``, ``resume`` or ``done``;
    ``cfg`` the config the run goes on with; ``ckpt`` the checkpoint to continue from; ``final``
    a finished run's final metrics; ``clean``: remove what an earlier attempt that never
    reached a checkpoint wrote before starting."""

    kind: str
    cfg: DictConfig
    ckpt: dict[str, Any] | None = None
    final: dict[str, Any] | None = None
    clean: bool = False


def _container(cfg: Any) -> dict[str, Any]:
    if isinstance(cfg, DictConfig):
        return OmegaConf.to_container(cfg, resolve=True)  # type: ignore[return-value]
    return dict(cfg)


def _conflicts(want: Mapping[str, Any], have: Mapping[str, Any], keys: Sequence[str] | None) -> list[str]:
    """``key: recorded -> asked`` for each key of ``keys`` (None: every key) where the two
    configs differ, leaving out what may differ on resume and the bookkeeping."""
    w = flatten_keys(dict(want))
    h = {k: v for k, v in flatten_keys(dict(have)).items() if k not in REMOVED_KEYS}
    candidates = sorted(set(w) | set(h)) if keys is None else sorted(keys)
    out = []
    for k in candidates:
        if _under(k, RESUMABLE_KEYS + BOOKKEEPING_KEYS + ("hydra",)) or k not in h:
            continue  # a key the record lacks was added to the code since, at a default that keeps its behaviour
        if w.get(k) != h.get(k):
            out.append(f"{k}: recorded {h.get(k)!r}, asked {w.get(k)!r}")
    return out


def _without_removed(cfg: dict[str, Any]) -> dict[str, Any]:
    out = OmegaConf.create(cfg)
    for key in REMOVED_KEYS:
        parent, _, leaf = key.rpartition(".")
        node = OmegaConf.select(out, parent) if parent else out
        if isinstance(node, DictConfig) and leaf in node:
            node.pop(leaf)
    return OmegaConf.to_container(out)  # type: ignore[return-value]


def _carry_over(recorded: dict[str, Any], want: dict[str, Any], budget_keys: Sequence[str]) -> dict[str, Any]:
    """The recorded config (less :data:`REMOVED_KEYS`) with the runtime settings of ``want`` and
    the budgets it asks for."""
    out = OmegaConf.create(_without_removed(recorded))
    flat = flatten_keys(want)
    for k in (*RUNTIME_KEYS, *budget_keys):
        if k in flat:
            OmegaConf.update(out, k, flat[k], merge=False)
    return OmegaConf.to_container(out)  # type: ignore[return-value]


def _finished(run_dir: Path, cfg: Mapping[str, Any]) -> dict[str, Any] | None:
    """A finished run's final metrics: written, complete (the LLM alone paused by its call
    budget is not) and, for a learner, at the budget the config asks for (an extension is not)."""
    final_file = run_dir / "final_metrics.json"
    if not final_file.is_file():
        return None
    final = json.loads(final_file.read_text())
    if final.get("eval/complete", 1) == 0:
        return None
    if cfg.get("controller", "learner") == "learner":
        tr = cfg["trainer"]
        frames_done = int(final.get("frames", 0)) >= int(tr["total_frames"])
        episodes_done = tr.get("total_episodes") is not None and int(final.get("episodes", 0)) >= int(tr["total_episodes"])
        if not (frames_done or episodes_done):
            return None
    return final


def _has_checkpoint(run_dir: Path) -> bool:
    d = checkpoint_dir(run_dir)
    return (d / LAST).is_file() or (d / PREV).is_file()


def plan(cfg: DictConfig, changed_keys: Sequence[str] | None = None) -> Plan:
    """Decide what ``cfg`` does with its run folder (module doc). ``changed_keys``: the keys the
    command line set, checked against the recorded run on ``resume=`` (None: every key)."""
    if cfg.resume:
        return _plan_resume(cfg, changed_keys)
    run_dir = Path(cfg.run_dir)
    want = _container(cfg)
    saved = run_dir / "config.json"
    if not saved.is_file():
        return Plan("new", cfg)
    if not cfg.experiment.reuse:
        raise ConfigError(
            f"{run_dir} holds a run already: continue it with resume={run_dir}, keep it as it is with "
            "experiment.reuse=true, or choose another run_dir"
        )
    recorded = json.loads(saved.read_text())
    conflicts = _conflicts(want, recorded, None)
    if conflicts:
        raise ConfigError(f"{run_dir} holds a run of another config; remove it or set experiment.root elsewhere. "
                         "Differences: " + "; ".join(conflicts))
    merged = _carry_over(recorded, want, BUDGET_KEYS)
    final = _finished(run_dir, merged)
    if final is not None:
        return Plan("done", OmegaConf.create(merged), final=final)
    if cfg.controller != "learner":
        return Plan("new", cfg)  # the LLM alone continues from its own progress files; the others fly again
    if _has_checkpoint(run_dir):
        return _continue(run_dir, merged)
    return Plan("new", cfg, clean=True)  # killed before its first checkpoint: start clean


def _plan_resume(cfg: DictConfig, changed_keys: Sequence[str] | None) -> Plan:
    ckpt, file = load_checkpoint(cfg.resume)
    recorded = dict(ckpt["config"])
    want = _container(cfg)
    keys = None if changed_keys is None else [k for k in changed_keys if not _under(k, BOOKKEEPING_KEYS)]
    conflicts = _conflicts(want, recorded, keys)
    if conflicts:
        raise ConfigError(f"resume={cfg.resume}: the command line conflicts with the recorded run (only "
                         f"{', '.join(RESUMABLE_KEYS)} may change on resume): " + "; ".join(conflicts))
    asked = [k for k in BUDGET_KEYS if keys is None or k in keys]
    merged = _carry_over(recorded, want, asked)
    run_dir = run_dir_of(file)
    merged["run_dir"] = str(run_dir)
    final = _finished(run_dir, merged)
    if final is not None and int(final.get("frames", 0)) <= int(ckpt["counters"]["frames"]):
        return Plan("done", OmegaConf.create(merged), final=final)
    merged["resume"] = str(file)
    return Plan("resume", OmegaConf.create(merged), ckpt=ckpt)


def _continue(run_dir: Path, merged: dict[str, Any]) -> Plan:
    ckpt, file = load_checkpoint(run_dir)
    merged = {**merged, "resume": str(file), "run_dir": str(run_dir)}
    return Plan("resume", OmegaConf.create(merged), ckpt=ckpt)


# ---------------------------------------------------------------------------- signals


class GracefulStop:
    """While active, SIGTERM and SIGINT set :attr:`signum` instead of ending the process; the
    loop ends its current batch, writes a checkpoint and raises :class:`RunStopped`. A second
    signal of the same kind ends the process at once (the previous handler runs), unless it
    comes within :attr:`SAME_STOP_S` of the first: one stop often arrives twice, to the whole
    process group and again from a parent that passes it on (GNU make forwards SIGTERM to its
    recipe, ``timeout`` to its command), and that must not cost the checkpoint. Only the main
    thread can install handlers; elsewhere this does nothing."""

    SIGNALS = (signal.SIGTERM, signal.SIGINT)
    SAME_STOP_S = 2.0

    def __init__(self, clock: Any = time.monotonic) -> None:
        self.signum: int | None = None
        self._previous: dict[int, Any] = {}
        self._clock = clock
        self._first_at = 0.0
        self._raise_at_once = False  # inside interruptible(): the handler raises StopRequested

    def _handle(self, signum: int, frame: Any) -> None:
        if self.signum is None:
            self.signum, self._first_at = signum, self._clock()
            if self._raise_at_once:
                raise StopRequested(signum)
            return
        if signum == self.signum and self._clock() - self._first_at < self.SAME_STOP_S:
            return  # the same stop, delivered again
        previous = self._previous.get(signum)  # asked again: stop now
        signal.signal(signum, previous if previous is not None else signal.SIG_DFL)
        os.kill(os.getpid(), signum)

    def __enter__(self) -> GracefulStop:
        try:
            for s in self.SIGNALS:
                self._previous[s] = signal.signal(s, self._handle)
        except ValueError:  # not the main thread
            self._previous.clear()
        return self

    def __exit__(self, *exc: Any) -> None:
        for s, h in self._previous.items():
            signal.signal(s, h)
        self._previous.clear()

    @property
    def requested(self) -> bool:
        return self.signum is not None

    def check(self) -> None:
        """Raise :class:`StopRequested` if a stop was asked (a step boundary of an evaluation)."""
        if self.signum is not None:
            raise StopRequested(self.signum)

    @contextlib.contextmanager
    def interruptible(self) -> Iterator[GracefulStop]:
        """A wait with no step to end at (a local LLM server starting): a stop asked before or
        during the block raises :class:`StopRequested` at once, out of the wait itself. Only for
        work that is thrown away when cut short (the server is stopped on the way out)."""
        self.check()
        self._raise_at_once = True
        try:
            yield self
        finally:
            self._raise_at_once = False
