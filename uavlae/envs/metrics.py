"""Episode metrics of the paper (docs/model.md §5): per-episode records and their aggregates.

Three layers, each usable alone:

* :class:`EpisodeTracker` — a pure batched accumulator. Feed it every step's ``"next"``
  tensordict of :class:`~uavlae.envs.uav_env.UAVEnv` (events, reward terms, state, done);
  whenever a row is done it emits one record for that row's episode and starts afresh.
* :class:`EpisodeMetrics` — the same tracker as a TorchRL ``Transform`` (docs/style.md rule 4), so any
  rollout or collector over ``TransformedEnv(UAVEnv(...), EpisodeMetrics(cfg))`` is measured,
  partial resets included. It changes no data.
* :func:`aggregate` — DCR, CR, SLR, RVR, ECR and the means over a set of records;
  :func:`rollout_metrics` — run a batched evaluation until every row has finished one episode.

Records are column-wise: ``dict[str, Tensor]`` with one entry per episode in every column
(:data:`RECORD_COLUMNS`). :func:`records_to_rows`, :func:`save_records` and
:func:`load_records` turn them into plain rows and CSV / JSON files.
"""

from __future__ import annotations

import csv
import json
import math
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import torch
from tensordict import TensorDictBase
from torch import Tensor
from torchrl.envs import EnvBase, Transform
from torchrl.envs.utils import step_mdp

from uavlae.envs.config import EnvConfig, make_env_config
from uavlae.envs.world import REWARD_KEYS

# Collision events (SPEC §5): any of them in any slot makes the episode "collided".
COLLISION_EVENTS = ("bz_collision", "nfz_entry", "ou_collision")
# Per-episode "did it ever happen" flags, OR-ed over the episode's slots.
ANY_FLAGS = COLLISION_EVENTS + ("collided", "boundary_exit", "rz_speeding")
# Flags read from the episode's last slot.
FINAL_FLAGS = ("landed", "energy_exhausted", "terminated", "truncated")
TERM_COLUMNS = tuple(f"term_{k}" for k in REWARD_KEYS)
RECORD_COLUMNS = (
    "row", "length", "return", "cost", "data_collected", "data_total", "energy_used", "energy_total",
    *ANY_FLAGS, *FINAL_FLAGS, *TERM_COLUMNS,
)
_INT_COLUMNS = {"row", "length"}
_BOOL_COLUMNS = set(ANY_FLAGS) | set(FINAL_FLAGS)


def _flat(t: Tensor, b: int) -> Tensor:
    return t.reshape(b)


class EpisodeTracker:
    """Accumulates per-row episode statistics of a ``[B]``-batched env and emits records.

    Args:
        batch_size: B, the number of rows stepped together.
        cfg: the env config (for ``energy_total`` = ``cfg.energy.e_total`` of each record).
        max_episodes_per_row: keep at most this many records per row (``None``: all). An
            evaluation uses 1: short episodes would otherwise be over-represented.
        device: where the accumulators live (that of the env's tensors).
    """

    def __init__(
        self,
        batch_size: int,
        cfg: EnvConfig | Mapping | None = None,
        *,
        max_episodes_per_row: int | None = None,
        device: torch.device | str = "cpu",
    ):
        self.batch_size = int(batch_size)
        self.cfg = make_env_config(cfg)
        self.max_episodes_per_row = max_episodes_per_row
        self.device = torch.device(device)
        self._chunks: list[dict[str, Tensor]] = []
        self.episodes_per_row = torch.zeros(self.batch_size, dtype=torch.int64, device=self.device)
        self._acc: dict[str, Tensor] = {}
        self.reset()

    # ------------------------------------------------------------------ accumulators
    def reset(self, rows: Tensor | None = None) -> None:
        """Forget the running episode of ``rows`` (bool ``[B]``; ``None``: every row)."""
        b, dev = self.batch_size, self.device
        if not self._acc:
            self._acc = {
                "length": torch.zeros(b, dtype=torch.int64, device=dev),
                "return": torch.zeros(b, device=dev),
                "cost": torch.zeros(b, device=dev),
                **{k: torch.zeros(b, device=dev) for k in TERM_COLUMNS},
                **{k: torch.zeros(b, dtype=torch.bool, device=dev) for k in ANY_FLAGS},
            }
            return
        if rows is None:
            for v in self._acc.values():
                v.zero_()
            return
        rows = rows.reshape(b).to(dev)
        for k, v in self._acc.items():
            self._acc[k] = torch.where(rows, torch.zeros_like(v), v)

    def update(self, next_td: TensorDictBase) -> Tensor:
        """Add one step (the env's ``"next"`` tensordict); returns the bool ``[B]`` done mask.

        Rows that are done emit a record and restart their accumulators, so the tracker
        follows auto-resetting rollouts without being told about the resets.
        """
        b = self.batch_size
        acc = self._acc
        ev = next_td.get("events")
        terms = next_td.get("reward_terms")
        acc["length"] = acc["length"] + 1
        acc["return"] = acc["return"] + _flat(next_td.get("reward"), b).to(acc["return"].dtype)
        acc["cost"] = acc["cost"] + _flat(next_td.get("cost"), b).to(acc["cost"].dtype)
        for name in REWARD_KEYS:
            key = f"term_{name}"
            acc[key] = acc[key] + _flat(terms.get(name), b).to(acc[key].dtype)
        collided = torch.zeros(b, dtype=torch.bool, device=self.device)
        for name in COLLISION_EVENTS:
            e = _flat(ev.get(name), b)
            acc[name] = acc[name] | e
            collided = collided | e
        acc["collided"] = acc["collided"] | collided
        acc["boundary_exit"] = acc["boundary_exit"] | _flat(ev.get("boundary_exit"), b)
        acc["rz_speeding"] = acc["rz_speeding"] | _flat(ev.get("rz_speeding"), b)

        done = _flat(next_td.get("done"), b)
        if bool(done.any()):
            self._emit(done, next_td)
            self.reset(done)
        return done

    def _emit(self, done: Tensor, next_td: TensorDictBase) -> None:
        b = self.batch_size
        keep = done
        if self.max_episodes_per_row is not None:
            keep = done & (self.episodes_per_row < self.max_episodes_per_row)
        self.episodes_per_row = self.episodes_per_row + done.long()
        if not bool(keep.any()):
            return
        st, ev = next_td.get("state"), next_td.get("events")
        rec = {k: v[keep] for k, v in self._acc.items()}
        rec["row"] = torch.arange(b, device=self.device)[keep]
        rec["data_collected"] = _flat(st.get("data_collected"), b)[keep].float()
        rec["data_total"] = _flat(st.get("data_total"), b)[keep].float()
        rec["energy_used"] = _flat(st.get("energy_used"), b)[keep].float()
        rec["energy_total"] = torch.full_like(rec["energy_used"], self.cfg.energy.e_total)
        rec["landed"] = _flat(ev.get("landed"), b)[keep]
        rec["energy_exhausted"] = _flat(ev.get("energy_exhausted"), b)[keep]
        rec["terminated"] = _flat(next_td.get("terminated"), b)[keep]
        rec["truncated"] = _flat(next_td.get("truncated"), b)[keep]
        self._chunks.append(rec)

    def flush_unfinished(self, next_td: TensorDictBase) -> None:
        """Close every running episode now (as truncated), e.g. when a step budget runs out."""
        b = self.batch_size
        running = self._acc["length"] > 0
        if not bool(running.any()):
            return
        td = next_td.clone(recurse=False)
        td.set("truncated", (running | _flat(next_td.get("truncated"), b)).reshape(b, 1))
        td.set("terminated", _flat(next_td.get("terminated"), b).reshape(b, 1) & ~running.reshape(b, 1))
        self._emit(running, td)
        self.reset(running)

    # ------------------------------------------------------------------ output
    def records(self) -> dict[str, Tensor]:
        """Every record emitted so far, column-wise, in order of completion."""
        return concat_records(self._chunks, device=self.device)

    def state_dict(self) -> dict[str, Any]:
        """The running episodes' accumulators, the episode counts and the records emitted so far
        (plain tensors: ``torch.load(weights_only=True)`` reads them back)."""
        return {"acc": {k: v.clone() for k, v in self._acc.items()},
                "episodes_per_row": self.episodes_per_row.clone(), "records": self.records()}

    def load_state_dict(self, state: Mapping[str, Any]) -> None:
        self._acc = {k: v.clone().to(self.device) for k, v in state["acc"].items()}
        self.episodes_per_row = state["episodes_per_row"].clone().to(self.device)
        recs = state["records"]
        n = int(next(iter(recs.values())).numel()) if recs else 0
        self._chunks = [dict(recs)] if n else []

    def clear(self) -> None:
        """Drop the emitted records (the running episodes are kept)."""
        self._chunks = []
        self.episodes_per_row = torch.zeros_like(self.episodes_per_row)


def empty_records(device: torch.device | str = "cpu") -> dict[str, Tensor]:
    out = {}
    for k in RECORD_COLUMNS:
        dtype = torch.int64 if k in _INT_COLUMNS else torch.bool if k in _BOOL_COLUMNS else torch.float32
        out[k] = torch.zeros(0, dtype=dtype, device=device)
    return out


def concat_records(chunks: Sequence[Mapping[str, Tensor]], device: torch.device | str = "cpu") -> dict[str, Tensor]:
    """Concatenate column-wise record chunks into one column-wise record set."""
    if not chunks:
        return empty_records(device)
    return {k: torch.cat([c[k] for c in chunks]) for k in RECORD_COLUMNS}


class EpisodeMetrics(Transform):
    """Episode bookkeeping as a TorchRL transform: measures, never changes, the data.

    ``TransformedEnv(UAVEnv(cfg, batch_size=[B]), EpisodeMetrics(cfg))``; read
    :meth:`records` / :meth:`aggregate` after any rollout. Lives in the process of the env it
    is attached to (a collector's worker keeps its own copy).
    """

    def __init__(self, cfg: EnvConfig | Mapping | None = None, *, max_episodes_per_row: int | None = None):
        super().__init__(in_keys=[], out_keys=[])
        self.cfg = make_env_config(cfg)
        self.max_episodes_per_row = max_episodes_per_row
        self.tracker: EpisodeTracker | None = None

    def _tracker(self, td: TensorDictBase) -> EpisodeTracker:
        b = int(td.batch_size.numel()) if td.batch_dims else 1
        if self.tracker is None or self.tracker.batch_size != b:
            self.tracker = EpisodeTracker(
                b, self.cfg, max_episodes_per_row=self.max_episodes_per_row, device=td.device or "cpu"
            )
        return self.tracker

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase) -> TensorDictBase:
        tracker = self._tracker(tensordict_reset)
        rows = tensordict.get("_reset", None) if tensordict is not None else None
        tracker.reset(None if rows is None else rows.reshape(-1))
        return tensordict_reset

    def _step(self, tensordict: TensorDictBase, next_tensordict: TensorDictBase) -> TensorDictBase:
        self._tracker(next_tensordict).update(next_tensordict)
        return next_tensordict

    def _call(self, next_tensordict: TensorDictBase) -> TensorDictBase:
        return next_tensordict

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        return tensordict

    def records(self) -> dict[str, Tensor]:
        return self.tracker.records() if self.tracker is not None else empty_records()

    def aggregate(self) -> dict[str, float]:
        return aggregate(self.records())

    def clear(self) -> None:
        if self.tracker is not None:
            self.tracker.clear()


# ---------------------------------------------------------------------------- aggregates


def _as_columns(records: Mapping[str, Any] | Sequence[Mapping[str, Any]]) -> dict[str, Tensor]:
    if isinstance(records, Mapping):
        return {k: torch.as_tensor(v) for k, v in records.items()}
    rows = list(records)
    if not rows:
        return empty_records()
    return {k: torch.as_tensor([r[k] for r in rows]) for k in rows[0]}


def aggregate(records: Mapping[str, Any] | Sequence[Mapping[str, Any]]) -> dict[str, float]:
    """The paper's metrics over N episodes (SPEC §5, paper §6.2) plus means.

    DCR = Σ collected / Σ total; CR = episodes with a collision / N; SLR = landed / N;
    RVR = episodes with RZ speeding / N; ECR = Σ energy used / Σ E_total. Also
    ``boundary_exit_rate``, ``mean_return``, ``mean_length``, ``mean_cost`` and
    ``mean_term_<name>`` for every reward term. ``n_episodes`` = N; NaN everywhere when N = 0.
    Accepts column-wise records or a list of row dicts.
    """
    c = _as_columns(records)
    n = int(c["length"].numel()) if "length" in c else 0
    nan = float("nan")

    def total(k: str) -> float:
        return float(c[k].double().sum())

    def rate(k: str) -> float:
        return total(k) / n if n else nan

    def mean(k: str) -> float:
        return float(c[k].double().mean()) if n else nan

    def ratio(num: str, den: str) -> float:
        d = total(den) if n else 0.0
        return total(num) / d if d > 0 else nan

    out: dict[str, float] = {
        "n_episodes": n,
        "DCR": ratio("data_collected", "data_total"),  # Σ collected / Σ total
        "CR": rate("collided"),
        "SLR": rate("landed"),
        "RVR": rate("rz_speeding"),
        "ECR": ratio("energy_used", "energy_total"),  # Σ energy used / Σ E_total
        "boundary_exit_rate": rate("boundary_exit"),
        "mean_return": mean("return"),
        "mean_length": mean("length"),
        "mean_cost": mean("cost"),
    }
    for k in TERM_COLUMNS:
        if k in c:
            out[f"mean_{k}"] = mean(k)
    return out


PAPER_METRICS = ("DCR", "CR", "SLR", "RVR", "ECR")


def format_metrics(agg: Mapping[str, float], keys: Sequence[str] = PAPER_METRICS) -> str:
    """A small two-line table of the chosen aggregates."""
    head = " | ".join(f"{k:>7}" for k in keys)
    vals = " | ".join(f"{agg[k]:7.3f}" for k in keys)
    return f"{head}\n{vals}"


# ---------------------------------------------------------------------------- files


def records_to_rows(records: Mapping[str, Tensor]) -> list[dict[str, Any]]:
    """Column-wise records to a list of plain-python row dicts."""
    cols = {k: torch.as_tensor(v).detach().cpu().tolist() for k, v in records.items()}
    n = len(next(iter(cols.values()))) if cols else 0
    return [{k: cols[k][i] for k in cols} for i in range(n)]


def save_records(records: Mapping[str, Tensor] | Sequence[Mapping[str, Any]], path: str | Path) -> Path:
    """Write records to ``path``: CSV when it ends in ``.csv``, else JSON (a list of rows)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    rows = records_to_rows(records) if isinstance(records, Mapping) else [dict(r) for r in records]
    if path.suffix.lower() == ".csv":
        fields = list(rows[0]) if rows else list(RECORD_COLUMNS)
        with path.open("w", newline="") as f:
            w = csv.DictWriter(f, fieldnames=fields)
            w.writeheader()
            w.writerows(rows)
    else:
        path.write_text(json.dumps(rows, indent=1))
    return path


def load_records(path: str | Path) -> dict[str, Tensor]:
    """Read records written by :func:`save_records` back into column-wise tensors."""
    path = Path(path)
    if path.suffix.lower() == ".csv":
        with path.open(newline="") as f:
            rows = list(csv.DictReader(f))
    else:
        rows = json.loads(path.read_text())
    if not rows:
        return empty_records()
    out = {}
    for k in rows[0]:
        vals = [r[k] for r in rows]
        if k in _BOOL_COLUMNS:
            out[k] = torch.tensor([v in (True, "True", "true", "1", 1) for v in vals])
        elif k in _INT_COLUMNS:
            out[k] = torch.tensor([int(v) for v in vals], dtype=torch.int64)
        else:
            out[k] = torch.tensor([float(v) for v in vals], dtype=torch.float32)
    return out


def save_aggregates(agg: Mapping[str, float], path: str | Path) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    clean = {k: (None if isinstance(v, float) and math.isnan(v) else v) for k, v in agg.items()}
    path.write_text(json.dumps(clean, indent=1))
    return path


# ---------------------------------------------------------------------------- evaluation


Policy = Callable[[TensorDictBase], TensorDictBase]


def rollout_metrics(
    env: EnvBase,
    policy: Policy | None = None,
    *,
    max_steps: int | None = None,
    generator: torch.Generator | None = None,
    cfg: EnvConfig | Mapping | None = None,
    tensordict: TensorDictBase | None = None,
    on_step: Callable[[int, Tensor, TensorDictBase], None] | None = None,
) -> tuple[dict[str, Tensor], dict[str, float], list[Tensor]]:
    """Run ``env`` until each batch row has finished one episode (or ``max_steps`` ran out).

    Args:
        env: a ``[B]``-batched :class:`UAVEnv` (or a ``TransformedEnv`` over one).
        policy: reads the tensordict, writes ``"action"`` (a ``TensorDictModule`` or any
            callable); ``None``: uniform random actions in [-1, 1]² drawn from ``generator``.
        max_steps: step budget (default ``cfg.t_max``, after which every episode is over);
            rows still running then are recorded as truncated.
        generator: the random policy's generator (``None``: a fresh one seeded 0).
        cfg: the env config (default ``env.cfg`` / ``env.base_env.cfg``).
        tensordict: a reset tensordict to start from (default ``env.reset()``).
        on_step: called after every step with the steps done, the rows whose first episode has
            ended (``[B]`` bool) and the step's ``"next"`` tensordict: the caller's progress line,
            what it keeps of each episode's end, and its way to stop (it raises).

    Rows whose episode ended keep being stepped without a reset (their output is ignored),
    so each row contributes exactly its first episode: ``records`` has B entries, one per row
    (column ``row``), and ``trajectories[i]`` is row i's positions ``[length_i + 1, 2]``,
    start included.
    """
    if cfg is None:
        cfg = getattr(env, "cfg", None) or getattr(getattr(env, "base_env", None), "cfg", None)
    cfg = make_env_config(cfg)
    b = int(env.batch_size.numel())
    max_steps = int(max_steps if max_steps is not None else cfg.t_max)
    if policy is None:
        if generator is None:
            generator = torch.Generator(device=env.device).manual_seed(0)
        gen = generator

        def policy(td: TensorDictBase) -> TensorDictBase:
            a = torch.rand((b, 2), generator=gen, device=env.device) * 2.0 - 1.0
            td.set("action", a)
            return td

    tracker = EpisodeTracker(b, cfg, max_episodes_per_row=1, device=env.device)
    td = env.reset() if tensordict is None else tensordict
    positions = [td.get(("state", "position")).reshape(b, 2).clone()]
    finished = torch.zeros(b, dtype=torch.bool, device=env.device)
    length = torch.zeros(b, dtype=torch.int64, device=env.device)
    nxt = None
    with torch.no_grad():
        for step in range(max_steps):
            td = policy(td)
            td = env.step(td)
            nxt = td.get("next")
            positions.append(nxt.get(("state", "position")).reshape(b, 2).clone())
            length = length + (~finished).long()
            done = tracker.update(nxt)
            finished = finished | done
            if on_step is not None:
                on_step(step + 1, finished, nxt)
            if bool(finished.all()):
                break
            # keep stepping finished rows without a reset: only first episodes count
            td = step_mdp(td, keep_other=True)
    if nxt is not None and not bool(finished.all()):
        tracker.flush_unfinished(nxt)
    records = tracker.records()
    order = torch.argsort(records["row"])
    records = {k: v[order] for k, v in records.items()}
    traj = torch.stack(positions, 0).cpu()  # [T+1, B, 2]
    lengths = length.cpu().tolist()
    trajectories = [traj[: lengths[i] + 1, i] for i in range(b)]
    return records, aggregate(records), trajectories
