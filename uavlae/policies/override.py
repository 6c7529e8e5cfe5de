"""The override policy (docs/model.md §8, SAC+LLM / SAC+Heuristic / fixed-probability LLM).

:class:`OverridePolicy` wraps any acting module (the SAC actor, a random policy) with an
*advisor*. Per step and per batch row it decides whether the advisor acts (the *trigger*),
sends only the triggered rows to the advisor, merges the advisor's actions into the actor's
and records who acted in ``"action_source"``:

========  =====  ===========================================================
constant  value  meaning
========  =====  ===========================================================
POLICY    0      the wrapped actor acted (not triggered, or override off)
LLM       1      the LLM advisor's validated velocity was executed
HEURISTIC 2      the heuristic advisor's action was executed
FALLBACK  3      triggered, the advisor failed, the fallback setting acted
STUDENT   4      a network trained on the LLM's answers answered in its place
SCRIPTED  5      a scripted advisor of known quality (hover, uniform random)
========  =====  ===========================================================

:data:`ADVICE_SOURCES` (LLM, HEURISTIC, STUDENT, SCRIPTED) are the rows where an advisor's own
answer was executed: what the advised fraction counts and what a cloning term learns from.
FALLBACK rows are not advice (the advisor failed), POLICY rows are the actor's.

Triggers (``mode``): ``"proximity"`` (paper: any BZ, NFZ, RZ or OU within ``d_th`` of the
DCU, read from the env's ``("state", "d_bz" | "d_nfz" | "d_rz" | "d_ou")``; an OU counts only
within the perception radius, as the DCU sees it, which matters once ``d_th`` exceeds it), ``"fixed_prob"``
(each row with probability ``fp`` from the module's own seeded generator, whatever the
surroundings), ``"always"`` (the ``llm`` baseline) and ``"never"``.

Failed advice (``ok`` False) follows ``fallback``, the one fallback setting
(``advisor.fallback``): ``"policy"`` keeps the actor's action, ``"heuristic"`` executes the
heuristic's action (both recorded as FALLBACK), and ``"end_episode"`` (paper §5.3) keeps the
actor's action and sets ``"override_abort"`` for that row so
:class:`uavlae.collect.UAVCollector` ends the episode there. A step with failed rows logs one
warning naming that setting. An LLM endpoint that is down is not a failed row but the end of
the run: the advisor raises its ``EndpointError`` through ``result()``.

Advisors implement one contract, :class:`uavlae.policies.advisor.Advisor` (re-exported here):
``advise(td_rows, rows) -> (actions [n, 2] in [-1, 1], ok [n] bool)`` on the triggered rows only,
and the hooks this module calls, each named there once with its default: ``source`` (the
``action_source`` of its answered rows), ``start`` (the request sent without waiting: its
handle's ``result()`` gives ``advise``'s answer while the LLM's requests are in flight on the
server), ``observe`` (the whole batch at every step the override is on, for an advisor that
remembers earlier slots), ``fallback`` (its own, for a policy given none), ``snapshot`` and
``latencies`` (its counters), ``asks_llm`` and ``price`` (what :meth:`OverridePolicy.cost`
counts), ``state_dict`` (checkpointed with this module) and ``close``. An advisor that answers through several hands (the student advisor,
:mod:`uavlae.policies.student`) returns a third tensor, each row's ``action_source``.

A step in two halves: :meth:`OverridePolicy.begin` decides the triggered rows from the state
alone and starts their advice; :meth:`OverridePolicy.finish` runs the actor, waits for the
answers and merges them. ``forward`` is ``finish(begin(td))``; the collector runs the learner's
scheduled gradient steps between the two, while the requests are in flight. Neither half reads
the actor's parameters before ``finish``, so what runs in between cannot change the answers.

Advisor phase-out, beyond the paper (off by default): ``phase_out_frames = F`` anneals the
trigger linearly to nothing over the first ``F`` frames the override acts on (``d_th`` in
proximity mode, ``fp`` in fixed-probability mode, scaled by ``1 - frames / F``; from ``F`` on
no row is triggered), so the actor flies alone before training ends.

Teacher labels, beyond the paper (off by default): with ``label_all`` the advisor's answer for
every row of the step, asked or not, is written to ``"advice"`` ``[B, 2]`` (``"advice_ok"``
``[B]`` bool: the rows it labelled), taken from :meth:`Advisor.label` (an advisor that computes
every row's answer anyway, as the heuristic does in ``observe``; others refuse it). The rows the
actor flies itself are labelled too, so a cloning term (``algo.clone_weight``) pulls the actor
toward the teacher on the states the actor visits, not only on the teacher's own (DAgger, Ross
et al. 2011); the trigger still decides who acts. Nothing is labelled in evaluation.

Dependence, counted every step the override is on: the advised fraction (advice executed /
frames), the trigger rate and, on the rows where advice was executed, the gap between the
advice and the actor's own deterministic action there (``tanh`` of its ``"loc"`` when the actor
writes one, else its action): ``actor_gap`` (mean L2 distance, action units) and
``actor_agree`` (the fraction within ``agree_tol`` of it); with teacher labels, ``label_gap``: the
same distance to the label on the rows the actor flew itself.

Fewer calls, beyond the paper (both off by default, both counted in :meth:`snapshot`):

- ``hold_steps = k > 1``: a valid answer is executed again on its row for up to ``k`` slots in
  a row while that row stays triggered, in the same episode; a row that leaves the trigger,
  starts a new episode or gets a failed answer asks again.
- ``max_calls = n``: at most ``n`` rows are sent to the advisor in the whole run (the module's
  counter is checkpointed); triggered rows beyond it act with the actor (``source/policy``,
  counted in ``budget_skipped``); held answers still run out their ``k`` slots.

Only ``"action"`` is overridden: an actor's other outputs (``"loc"``, ``"scale"``,
``"action_log_prob"``) stay the actor's, so an on-policy learner must not be fed overridden
rows as its own samples (the paper overrides SAC, an off-policy learner; filter on
``action_source`` otherwise).

Evaluation and deployment use the actor alone (SPEC §8): set ``policy.deterministic = True``
(or use ``with policy.actor_only():``); the override is then off and the actor runs under
``ExplorationType.DETERMINISTIC``. The advisor is a plain attribute, never a submodule, so
``state_dict()`` holds only the actor's parameters plus this module's small extra state
(trigger generator and counters); the LLM advisor's HTTP client never travels with a copy
or a pickle (``LLMAdvisor.__getstate__`` drops it).
"""

from __future__ import annotations

import contextlib
import logging
import math
import time
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from typing import Any

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torch import Tensor
from torchrl.envs.utils import ExplorationType, set_exploration_type

from uavlae.policies.advisor import (  # re-exported: the advisors and their sources are imported from here
    ADVICE_SOURCES,
    FALLBACK,
    HEURISTIC,
    LLM,
    POLICY,
    SCRIPTED,
    SOURCE_NAMES,
    STUDENT,
    Advisor,
    Handle,
    HeuristicAdvisor,
    LLMAdvisorAdapter,
    ScriptedAdvisor,
)

MODES = ("proximity", "fixed_prob", "always", "never")
FALLBACKS = ("policy", "heuristic", "end_episode")
# the env's distances to the nearest obstacle of each kind (docs/env_contract.md)
PROXIMITY_KEYS = (("state", "d_bz"), ("state", "d_nfz"), ("state", "d_rz"), ("state", "d_ou"))
STEP_KEY = ("state", "step")  # the slot within the episode: a held answer never crosses a reset
# what an advisor's snapshot counts (summed over the run by OverridePolicy.run_totals)
ADVISOR_COUNTS = ("requests", "calls", "cache_hits", "retries", "ask_again", "advice_ok", "failures",
                  "prompt_tokens", "cached_prompt_tokens", "completion_tokens", "call_s", "rows_advised",
                  # the student advisor's (uavlae.policies.student): who answered, why the LLM was asked,
                  # and how far the student's answer lay from the LLM's where both answered
                  "student/rows", "student/llm_rows", "student/student_rows", "student/asked_warmup",
                  "student/asked_unsure", "student/asked_novel", "student/asked_audit", "student/audit_err_rows",
                  "student/audit_err_sum", "student/llm_err_rows", "student/llm_err_sum", "student/updates",
                  "student/train_s")
# the seconds between failure warnings: a weak model's rare bad rows are counted, not each logged
WARN_EVERY_S = 60.0

log = logging.getLogger(__name__)

__all__ = [
    "ADVICE_SOURCES", "Advisor", "FALLBACK", "HEURISTIC", "Handle", "HeuristicAdvisor", "LLM", "LLMAdvisorAdapter",
    "OverridePolicy", "POLICY", "Pending", "SCRIPTED", "SOURCE_NAMES", "STUDENT", "ScriptedAdvisor",
]


@dataclass
class Pending:
    """What :meth:`OverridePolicy.begin` started for one step (rows are batch indices)."""

    trig: Tensor  # [B] bool: triggered rows
    held: Tensor  # [B] bool: triggered rows executing a held answer (no request)
    skipped: Tensor  # [B] bool: triggered rows the call budget left to the actor
    rows: Tensor  # [n] int64: the rows sent to the advisor
    handle: Handle | None  # the advisor's handle (result()), None when no row was sent
    started_at: float  # time.perf_counter() when the requests were sent
    labels: Tensor | None = None  # [B, 2]: the advisor's answer for every row (label_all), else None

    @property
    def done_at(self) -> float | None:
        """When the answers arrived (None: still in flight, or nothing was asked)."""
        return None if self.handle is None else self.handle.done_at


# ---------------------------------------------------------------------------- the module


def _checked_args(advisor: Advisor | None, mode: str, d_th: float, fp: float, fallback: str | None, heuristic: Any,
                  hold_steps: int, max_calls: int | None, phase_out_frames: int | None, agree_tol: float,
                  label_all: bool) -> tuple[str, Any]:
    """:class:`OverridePolicy`'s arguments checked, each bad one named; returns the fallback and the
    heuristic it resolves to (the advisor's own where none is given)."""
    if mode not in MODES:
        raise ValueError(f"override.mode must be one of {list(MODES)}, got {mode!r}")
    if not (math.isfinite(d_th) and d_th >= 0):
        raise ValueError(f"override.d_th must be a finite distance >= 0 m, got {d_th!r}")
    if not 0.0 <= fp <= 1.0:
        raise ValueError(f"override.fp must be in [0, 1], got {fp!r}")
    if advisor is not None and not isinstance(advisor, Advisor):
        raise TypeError(f"an advisor implements uavlae.policies.advisor.Advisor (the hooks this policy calls, "
                        f"each with its default); got {type(advisor).__name__}")
    if fallback is None:
        fallback = (None if advisor is None else advisor.fallback) or "policy"
    if fallback not in FALLBACKS:
        raise ValueError(f"override.fallback must be one of {list(FALLBACKS)}, got {fallback!r}")
    if heuristic is None and isinstance(advisor, HeuristicAdvisor):
        heuristic = advisor.heuristic
    if fallback == "heuristic" and heuristic is None:
        raise ValueError("override.fallback='heuristic' needs a heuristic policy")
    if isinstance(hold_steps, bool) or int(hold_steps) != hold_steps or hold_steps < 1:
        raise ValueError(f"advisor.hold_steps must be an integer >= 1 (1: ask every slot), got {hold_steps!r}")
    if max_calls is not None and (isinstance(max_calls, bool) or int(max_calls) != max_calls or max_calls < 0):
        raise ValueError(f"advisor.max_calls must be null (no budget) or an integer >= 0, got {max_calls!r}")
    if phase_out_frames is not None:
        if isinstance(phase_out_frames, bool) or int(phase_out_frames) != phase_out_frames or phase_out_frames < 1:
            raise ValueError(f"advisor.phase_out_frames must be null (never) or an integer >= 1, got {phase_out_frames!r}")
        if mode not in ("proximity", "fixed_prob"):
            raise ValueError(f"advisor.phase_out_frames anneals d_th (proximity) or fp (fixed_prob); mode {mode!r} has neither")
    if not agree_tol > 0:
        raise ValueError(f"advisor.agree_tol must be > 0 (action units), got {agree_tol!r}")
    if label_all and (advisor is None or type(advisor).label is Advisor.label):
        raise ValueError(f"advisor.label_all labels every row with the advisor's answer, which needs an advisor that "
                         f"answers every row anyway (advisor.kind=heuristic); "
                         f"{'there is no advisor' if advisor is None else type(advisor).__name__ + ' gives none'}")
    return fallback, heuristic


class OverridePolicy(TensorDictModuleBase):
    """The actor, with its action overridden by an advisor on triggered rows.

    Args:
        actor: any module reading ``td`` and writing ``"action"`` ``[B, 2]`` (its other
            outputs, e.g. ``"action_log_prob"``, are left as the actor wrote them).
        advisor: an :class:`uavlae.policies.advisor.Advisor`; ``None`` means the actor alone
            (mode ignored).
        mode: ``"proximity"`` | ``"fixed_prob"`` | ``"always"`` | ``"never"``.
        d_th: proximity threshold, metres (SPEC §8: 15 m).
        fp: trigger probability of ``"fixed_prob"`` (paper: 0.3, 0.4, 0.5, 1.0).
        fallback: ``"policy"`` | ``"heuristic"`` | ``"end_episode"``; ``None`` takes the
            advisor's ``fallback`` or ``"policy"``.
        heuristic: a ``HeuristicPolicy`` for ``fallback="heuristic"`` (a
            :class:`HeuristicAdvisor`'s own heuristic is used when this is None).
        seed: seeds the trigger generator of ``"fixed_prob"``.
        hold_steps: slots a valid answer is executed on its row while the row stays triggered
            (1: the paper, ask every slot).
        max_calls: rows the advisor may be asked in the run (None: no budget).
        perception_radius: OUs farther than this (m) do not trigger (the env's ``d_ou``
            counts every OU; the DCU sees only those within its perception radius).
        phase_out_frames: anneal the trigger to nothing over this many frames (None: never).
        agree_tol: the distance (action units) within which the actor counts as agreeing
            with the executed advice.
        label_all: write the advisor's answer for every row to ``"advice"`` / ``"advice_ok"``
            (teacher labels, module doc); the advisor must give :meth:`Advisor.label`.
    """

    out_keys = ["action", "action_source", "override_abort"]

    def __init__(
        self,
        actor: Any,
        advisor: Advisor | None = None,
        mode: str = "proximity",
        d_th: float = 15.0,
        fp: float = 0.3,
        fallback: str | None = "policy",
        heuristic: Any = None,
        seed: int = 0,
        hold_steps: int = 1,
        max_calls: int | None = None,
        perception_radius: float = math.inf,
        phase_out_frames: int | None = None,
        agree_tol: float = 0.1,
        label_all: bool = False,
    ):
        super().__init__()
        fallback, heuristic = _checked_args(advisor, mode, d_th, fp, fallback, heuristic, hold_steps, max_calls,
                                            phase_out_frames, agree_tol, label_all)
        self.actor = actor
        # plain attributes, not submodules: never in state_dict, never moved by .to()
        self.__dict__["advisor"] = advisor
        self.__dict__["heuristic"] = heuristic
        self.mode = mode
        self.d_th = float(d_th)
        self.fp = float(fp)
        self.fallback = fallback
        self.seed = int(seed)
        self.hold_steps = int(hold_steps)
        self.max_calls = None if max_calls is None else int(max_calls)
        self.calls_used = 0  # rows sent to the advisor in the run (max_calls)
        self.hold: dict[str, Tensor] | None = None  # per row: action, source, slots left, last step
        self.perception_radius = float(perception_radius)
        self.phase_out_frames = None if phase_out_frames is None else int(phase_out_frames)
        self.agree_tol = float(agree_tol)
        self.label_all = bool(label_all)
        if self.label_all:
            self.out_keys = [*self.out_keys, "advice", "advice_ok"]
        self.deterministic = False  # evaluation / deployment: actor alone, deterministic
        # bool [B]: the rows that may be triggered at all (None: every row); the LLM-alone
        # evaluation clears a row once its episode has ended, so it is never asked again
        self.row_mask: Tensor | None = None
        self._active_actor: Any = None  # set by using_actor() (random warm-up frames)
        self._eval_actor: Any = None  # set by advised(actor=...): how the evaluated actor acts
        self._full_trigger = False  # set by advised(): the paper's trigger, no phase-out
        self.generator = torch.Generator()
        self.generator.manual_seed(self.seed)
        in_keys = list(getattr(actor, "in_keys", ["observation"]))
        if advisor is not None and mode == "proximity":
            in_keys += [k for k in PROXIMITY_KEYS if k not in in_keys]
        if advisor is not None and self.hold_steps > 1 and STEP_KEY not in in_keys:
            in_keys.append(STEP_KEY)
        self.in_keys = in_keys
        self.reset_counters()
        self.totals = dict(self.counts)  # never reset: the run's counters (run_totals)
        self.advisor_totals = {k: 0.0 for k in ADVISOR_COUNTS}  # the advisor's, summed over resets
        self._warned_at, self._failed_quiet = -math.inf, 0  # failure warnings (_warn_failed)

    # ------------------------------------------------------------------ switches
    @property
    def override_active(self) -> bool:
        return self.advisor is not None and self.mode != "never" and not self.deterministic

    @contextlib.contextmanager
    def actor_only(self) -> Iterator["OverridePolicy"]:
        """Evaluation: no override, the actor's deterministic action (SPEC §8)."""
        prev, self.deterministic = self.deterministic, True
        try:
            yield self
        finally:
            self.deterministic = prev

    @contextlib.contextmanager
    def advised(self, max_calls: int | None = None, actor: Any = None) -> Iterator["OverridePolicy"]:
        """Evaluation of the actor *with* its advisor: the override on at its full trigger (no
        phase-out), at most ``max_calls`` rows asked (None: no budget), the actor acting
        deterministically under the evaluator's exploration type, or as ``actor`` acts (the
        evaluation's own, e.g. a :class:`~uavlae.policies.sampling.SampledActor`, so the rows
        with and without the advisor fly the actor alike). What it counts is :meth:`snapshot`'s
        inside the block; on leaving, the training state (counters, budget, held answers, the
        advisor's memory and generators) is put back as it was, so training continues exactly."""
        saved = self.get_extra_state()
        saved_max, prev_det = self.max_calls, self.deterministic
        self.deterministic, self._full_trigger = False, True
        self.max_calls, self.calls_used, self.hold = max_calls, 0, None
        # a plain attribute, not a submodule: it is the evaluation's, not part of this policy's state
        object.__setattr__(self, "_eval_actor", actor)
        self.reset_counters()
        try:
            yield self
        finally:
            self.max_calls, self.deterministic, self._full_trigger = saved_max, prev_det, False
            object.__setattr__(self, "_eval_actor", None)
            self.set_extra_state(saved)

    @contextlib.contextmanager
    def using_actor(self, actor: Any) -> Iterator["OverridePolicy"]:
        """Act with ``actor`` in place of the wrapped one (e.g. random warm-up), override kept."""
        prev, self._active_actor = self._active_actor, actor
        try:
            yield self
        finally:
            self._active_actor = prev

    # ------------------------------------------------------------------ trigger
    def trigger(self, td: TensorDictBase) -> Tensor:
        """Bool ``[B]``: the rows whose action the advisor gives this step."""
        B = td.batch_size[0]
        device = td.get("action").device if "action" in td.keys() else td.device
        scale = self.phase()
        if not self.override_active or scale <= 0.0:
            if self.mode == "fixed_prob" and self.override_active:
                torch.rand(B, generator=self.generator)  # the same draws whatever the schedule
            return torch.zeros(B, dtype=torch.bool, device=device)
        if self.mode == "always":
            trig = torch.ones(B, dtype=torch.bool, device=device)
        elif self.mode == "fixed_prob":
            u = torch.rand(B, generator=self.generator)
            trig = (u < self.fp * scale).to(device)
        else:  # "proximity": SPEC §8, any BZ, NFZ, RZ or OU within d_th (inf when none is present)
            d = torch.stack([td.get(k).reshape(B) for k in PROXIMITY_KEYS], dim=-1)
            d_ou = d[:, -1]  # PROXIMITY_KEYS ends with d_ou
            d = torch.cat([d[:, :-1], d_ou.masked_fill(d_ou > self.perception_radius, math.inf)[:, None]], -1).amin(-1)
            trig = (d <= self.d_th * scale).to(device)
        return trig if self.row_mask is None else trig & self.row_mask.to(device)

    def phase(self) -> float:
        """The phase-out's scale on ``d_th`` / ``fp`` now: ``1 - frames / phase_out_frames``
        over the frames the override has acted on, floored at 0 (1 without a phase-out)."""
        if self.phase_out_frames is None or self._full_trigger:
            return 1.0
        return max(0.0, 1.0 - self.totals["frames"] / self.phase_out_frames)

    # ------------------------------------------------------------------ acting
    def _act(self, td: TensorDictBase) -> TensorDictBase:
        actor = self._active_actor if self._active_actor is not None else (
            self._eval_actor if self._eval_actor is not None else self.actor)
        if self.deterministic:
            with set_exploration_type(ExplorationType.DETERMINISTIC):
                out = actor(td)
        else:
            out = actor(td)
        return td if out is None else out

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        return self.finish(tensordict, self.begin(tensordict))

    def begin(self, td: TensorDictBase) -> Pending:
        """The first half of a step: the triggered rows (from the state alone) and their advice,
        sent; held answers and the call budget decide which rows are asked."""
        labels = None
        if self.override_active:
            with torch.no_grad():
                self.advisor.observe(td)  # a stateful advisor follows every row, every slot
                if self.label_all:
                    labels = self.advisor.label()
                    if labels is None:
                        raise RuntimeError(f"advisor.label_all: {type(self.advisor).__name__} gave no labels "
                                           "after observing the batch")
        trig = self.trigger(td)
        B = trig.shape[0]
        none = torch.zeros(B, dtype=torch.bool, device=trig.device)
        held, skipped = none, none
        ask = trig
        if trig.any() and self.hold_steps > 1:
            h = self._hold_state(B, trig.device)
            step = td.get(STEP_KEY).reshape(B).to(trig.device)
            held = trig & (h["left"] > 0) & (step == h["step"] + 1)
            ask = trig & ~held
        if self.max_calls is not None and ask.any():
            left = max(self.max_calls - self.calls_used, 0)
            within = torch.cumsum(ask.long(), 0) <= left  # the first rows in batch order
            skipped, ask = ask & ~within, ask & within
        rows = ask.nonzero().squeeze(-1)
        handle = None
        started = time.perf_counter()
        if rows.numel():
            self.calls_used += int(rows.numel())
            with torch.no_grad():
                handle = self.advisor.start(td[rows], rows)
        return Pending(trig=trig, held=held, skipped=skipped, rows=rows, handle=handle, started_at=started,
                       labels=labels)

    def finish(self, td: TensorDictBase, pending: Pending) -> TensorDictBase:
        """The second half: the actor acts, the answers are awaited and merged."""
        td = self._act(td)
        action = td.get("action")
        own = action  # the actor's own action, before any advice replaces it
        B = td.batch_size[0]
        source = torch.zeros(B, dtype=torch.int64, device=action.device)
        abort = torch.zeros(B, dtype=torch.bool, device=action.device)
        trig, held, rows = pending.trig.to(action.device), pending.held.to(action.device), pending.rows
        if held.any() or rows.numel():
            action = action.clone()
        if held.any():
            h = self.hold
            action[held] = h["action"][held].to(dtype=action.dtype)
            source[held] = h["source"][held]
        good = rows[:0]
        wait = 0.0
        if rows.numel():
            t0 = time.perf_counter()
            answer = pending.handle.result()
            wait = time.perf_counter() - t0
            adv_action, ok = answer[0], answer[1]
            adv_action = adv_action.to(device=action.device, dtype=action.dtype).clamp(-1.0, 1.0)
            ok = ok.to(device=action.device, dtype=torch.bool).reshape(-1)
            if adv_action.shape != (rows.numel(), action.shape[-1]) or ok.shape[0] != rows.numel():
                raise ValueError(
                    f"advisor returned actions {tuple(adv_action.shape)} and ok {tuple(ok.shape)} "
                    f"for {rows.numel()} rows"
                )
            good, bad = rows[ok], rows[~ok]
            action[good] = adv_action[ok]
            if len(answer) > 2:  # an advisor that answers through several hands names each row's
                source[good] = answer[2].to(device=source.device, dtype=source.dtype).reshape(-1)[ok]
            else:
                source[good] = int(self.advisor.source)
            if bad.numel():
                self._warn_failed(pending, int(bad.numel()), int(rows.numel()))
                source[bad] = FALLBACK
                if self.fallback == "heuristic":
                    hact = self.heuristic.act(td[bad].get("state"))
                    action[bad] = hact.to(device=action.device, dtype=action.dtype)
                elif self.fallback == "end_episode":
                    abort[bad] = True
                # "policy": the actor's action stays
        if held.any() or rows.numel():
            td.set("action", action)
        if self.hold_steps > 1 and trig.any():
            self._update_hold(td, trig, held, good, action, source)
        td.set("action_source", source)
        td.set("override_abort", abort)
        if pending.labels is not None:
            labels = pending.labels.to(device=action.device, dtype=action.dtype).clamp(-1.0, 1.0)
            td.set("advice", labels)
            td.set("advice_ok", torch.ones(B, dtype=torch.bool, device=action.device))
            self._count_label_gap(td, own, labels, source)
        if self.override_active:
            self._count(source, trig, abort, held, pending.skipped, int(rows.numel()), wait)
            self._count_agreement(td, own, action, source)
        return td

    def _warn_failed(self, pending: Pending, n_bad: int, n_asked: int) -> None:
        """One warning for a step's failed rows, naming the setting that acts on them (at most
        one every WARN_EVERY_S; every failed row is counted in ``source/fallback``)."""
        self._failed_quiet += 1
        now = time.monotonic()
        if now - self._warned_at < WARN_EVERY_S:
            return
        why = sorted(set(pending.handle.failures))
        since = self._failed_quiet - 1
        quiet = f"; {since} step(s) with failures since the last warning" if self._warned_at > -math.inf else ""
        log.warning("advice failed on %d of %d asked row(s)%s; advisor.fallback=%s acts there%s", n_bad, n_asked,
                    f" ({'; '.join(w[:160] for w in why[:3])})" if why else "", self.fallback, quiet)
        self._warned_at, self._failed_quiet = now, 0

    def _count_agreement(self, td: TensorDictBase, own: Tensor, action: Tensor, source: Tensor) -> None:
        """How far the actor's own deterministic action lies from the advice executed in its
        place (skipped during the random warm-up, when the actor does not act)."""
        if self._active_actor is not None:
            return
        advised = torch.isin(source, torch.tensor(ADVICE_SOURCES, device=source.device))
        n = int(advised.sum())
        if not n:
            return
        loc = td.get("loc", None)
        mine = loc.tanh() if loc is not None and loc.shape == own.shape else own
        gap = torch.linalg.vector_norm(mine[advised].float() - action[advised].float(), dim=-1)
        add = {"gap_rows": n, "gap_sum": float(gap.sum()), "agree_rows": int((gap <= self.agree_tol).sum())}
        for c in (self.counts, self.totals):
            for k, v in add.items():
                c[k] = c.get(k, 0) + v

    def _count_label_gap(self, td: TensorDictBase, own: Tensor, labels: Tensor, source: Tensor) -> None:
        """How far the actor's own deterministic action lies from the teacher's label on the rows
        the actor flew itself (``label_gap``): whether the labels teach it on its own states."""
        if self._active_actor is not None:
            return
        mine_rows = source == POLICY
        n = int(mine_rows.sum())
        if not n:
            return
        loc = td.get("loc", None)
        mine = loc.tanh() if loc is not None and loc.shape == own.shape else own
        gap = torch.linalg.vector_norm(mine[mine_rows].float() - labels[mine_rows].float(), dim=-1)
        for c in (self.counts, self.totals):
            c["label_rows"] = c.get("label_rows", 0) + n
            c["label_gap_sum"] = c.get("label_gap_sum", 0.0) + float(gap.sum())

    # ------------------------------------------------------------------ held answers
    def _hold_state(self, B: int, device: torch.device) -> dict[str, Tensor]:
        if self.hold is None or self.hold["left"].shape[0] != B:
            self.hold = {
                "action": torch.zeros(B, 2, device=device),
                "source": torch.zeros(B, dtype=torch.int64, device=device),
                "left": torch.zeros(B, dtype=torch.int64, device=device),  # executions still allowed
                "step": torch.full((B,), -2, dtype=torch.int64, device=device),  # slot last executed
            }
        return self.hold

    def _update_hold(self, td: TensorDictBase, trig: Tensor, held: Tensor, good: Tensor, action: Tensor,
                     source: Tensor) -> None:
        B = trig.shape[0]
        h = self._hold_state(B, trig.device)
        h["left"] = torch.where(held, h["left"] - 1, torch.zeros_like(h["left"]))  # anything else asks again
        if good.numel():
            h["action"][good] = action[good].to(h["action"].dtype)
            h["source"][good] = source[good]
            h["left"][good] = self.hold_steps - 1
        h["step"] = td.get(STEP_KEY).reshape(B).to(trig.device).clone()

    # ------------------------------------------------------------------ counters
    def reset_counters(self) -> None:
        self.counts = {"frames": 0, "triggered": 0, "aborts": 0, "held": 0, "budget_skipped": 0,
                       "advised": 0, "advice_wait_s": 0.0, "gap_rows": 0, "gap_sum": 0.0, "agree_rows": 0,
                       **{f"source/{n}": 0 for n in SOURCE_NAMES.values()}}

    def _count(self, source: Tensor, trig: Tensor, abort: Tensor, held: Tensor, skipped: Tensor, advised: int,
               wait: float) -> None:
        per = torch.bincount(source.reshape(-1).cpu(), minlength=len(SOURCE_NAMES))
        add = {"frames": int(source.numel()), "triggered": int(trig.sum()), "aborts": int(abort.sum()),
               "held": int(held.sum()), "budget_skipped": int(skipped.sum()), "advised": advised,
               "advice_wait_s": wait, **{f"source/{name}": int(per[k]) for k, name in SOURCE_NAMES.items()}}
        for c in (self.counts, self.totals):
            for k, v in add.items():
                c[k] = c.get(k, 0) + v

    @staticmethod
    def _rates(c: dict[str, Any]) -> dict[str, Any]:
        frames, trig = c["frames"], c["triggered"]
        nan = float("nan")
        c["trigger_rate"] = trig / frames if frames else nan
        advice = sum(c.get(f"source/{SOURCE_NAMES[k]}", 0) for k in ADVICE_SOURCES)
        c["override_rate"] = advice / frames if frames else nan  # the advised fraction of these frames
        c["advised_fraction"] = c["override_rate"]
        c["advice_fail_rate"] = c["source/fallback"] / trig if trig else nan
        gap_rows = c.get("gap_rows", 0)
        c["actor_gap"] = c.get("gap_sum", 0.0) / gap_rows if gap_rows else nan
        c["actor_agree"] = c.get("agree_rows", 0) / gap_rows if gap_rows else nan
        if c.get("label_rows"):  # teacher labels (label_all): the actor's distance to them on its own rows
            c["label_gap"] = c["label_gap_sum"] / c["label_rows"]
        return c

    def _with_settings(self, counts: dict[str, Any]) -> dict[str, Any]:
        """``counts`` with their rates, and the settings that shaped them: the call budget, the
        held slots, the phase-out and the agreement tolerance."""
        c = self._rates(dict(counts))
        c["calls_used"] = self.calls_used
        c["max_calls"] = -1 if self.max_calls is None else self.max_calls
        c["hold_steps"] = self.hold_steps
        c["phase"] = self.phase()
        c["agree_tol"] = self.agree_tol
        return c

    def snapshot(self, reset: bool = False) -> dict[str, float]:
        """Counters since the last reset: frames acted with the override on, ``triggered``,
        ``source/<name>``, ``aborts``, ``held`` (triggered rows that executed a held answer),
        ``budget_skipped`` (triggered rows left to the actor by ``max_calls``), ``advised`` (rows
        sent to the advisor), ``advice_wait_s`` (time spent waiting for answers after the
        work done while they were in flight), ``trigger_rate`` (triggered / frames),
        ``override_rate`` (advisor actions executed / frames), ``advice_fail_rate``
        (fallbacks / triggered), ``calls_used`` / ``max_calls`` (the run's budget; -1: none),
        and the advisor's own counters under ``advisor/`` (the LLM's: requests, calls, cache
        hits, retries, failures by kind, tokens, latency quantiles)."""
        c = self._with_settings(self.counts)
        if self.advisor is not None:
            adv = self.advisor.snapshot(reset=reset)
            c.update({f"advisor/{k}": v for k, v in adv.items()})
            if reset:
                for k in ADVISOR_COUNTS:
                    self.advisor_totals[k] += float(adv.get(k, 0) or 0)
        if reset:
            self.reset_counters()
        return c

    def counters(self) -> dict[str, Any]:
        """The override's own counters since the last reset, with their rates (no advisor
        transport counters): what an evaluation inside :meth:`advised` reads."""
        return self._rates(dict(self.counts))

    def run_totals(self) -> dict[str, Any]:
        """The run's counters (never reset, checkpointed): :meth:`snapshot`'s names, the
        advisor's counts summed over the whole run and, for an LLM advisor, its per-call
        latency quantiles over every answered call (``advisor/latency_p50_s``, ``_p95_s``)."""
        c = self._with_settings(self.totals)
        if self.advisor is not None:
            window = self.advisor.snapshot(reset=False)
            for k in ADVISOR_COUNTS:
                if k in window or self.advisor_totals[k]:
                    c[f"advisor/{k}"] = self.advisor_totals[k] + float(window.get(k, 0) or 0)
        lat = None if self.advisor is None else self.advisor.latencies()
        if lat is not None:
            xs = sorted(lat)
            for name, p in (("latency_p50_s", 0.5), ("latency_p95_s", 0.95)):
                c[f"advisor/{name}"] = xs[min(len(xs) - 1, int(p * len(xs)))] if xs else float("nan")
        for what in ("audit", "llm"):  # the student's mean velocity error (m/s) against the LLM
            rows = c.get(f"advisor/student/{what}_err_rows", 0)
            if rows:
                c[f"advisor/student/{what}_err_mps"] = c[f"advisor/student/{what}_err_sum"] / rows
        return c

    def cost(self) -> dict[str, float]:
        """What the run's advice cost, for an advisor that asks an LLM (else empty): triggered
        rows; rows executed from the LLM's answer, from the student's, from a held answer, by
        the fallback, and left to the actor by the call budget; the rows sent to the LLM, its
        HTTP calls (retries included) and cache hits; tokens in (of them served from the
        server's prompt cache) and out; seconds the LLM spent answering (the answered calls'
        latencies summed) and seconds the loop waited for answers after the work it did
        meanwhile; and, for an endpoint with a price (``llm.price_*_per_mtok``), the money
        (``money``, in ``llm.price_currency``; NaN without a price)."""
        if self.advisor is None or not self.advisor.asks_llm:
            return {}
        t = self.run_totals()
        tin, tcached, tout = (float(t.get(f"advisor/{k}", 0.0)) for k in
                              ("prompt_tokens", "cached_prompt_tokens", "completion_tokens"))
        out = {"triggered": t["triggered"], "rows_llm": t["source/llm"], "rows_student": t["source/student"],
               "rows_held": t["held"], "rows_fallback": t["source/fallback"], "rows_actor": t["budget_skipped"],
               "llm_requests": float(t.get("advisor/requests", 0.0)), "llm_calls": float(t.get("advisor/calls", 0.0)),
               "llm_cache_hits": float(t.get("advisor/cache_hits", 0.0)),
               "tokens_in": tin, "tokens_in_cached": tcached, "tokens_out": tout,
               "llm_s": float(t.get("advisor/call_s", 0.0)), "wait_s": float(t.get("advice_wait_s", 0.0)),
               "money": math.nan}
        p = self.advisor.price()
        if p is not None:  # Eq.: (uncached in * p_in + cached in * p_cached + out * p_out) / 1e6
            p_in, p_cached, p_out, _ = p
            out["money"] = ((tin - tcached) * p_in + tcached * p_cached + tout * p_out) / 1e6
        return out

    def currency(self) -> str | None:
        p = None if self.advisor is None else self.advisor.price()
        return None if p is None else p[3]

    # ------------------------------------------------------------------ state
    def get_extra_state(self) -> dict[str, Any]:
        # an advisor with state that shapes its answers (the heuristic's plan cache) saves it too;
        # the held answers and the budget's counter shape the next steps, so they travel as well
        return {"generator": self.generator.get_state(), "counts": dict(self.counts),
                "totals": dict(self.totals), "advisor_totals": dict(self.advisor_totals),
                "calls_used": self.calls_used,
                "hold": None if self.hold is None else {k: v.clone() for k, v in self.hold.items()},
                "advisor": None if self.advisor is None else self.advisor.state_dict()}

    def set_extra_state(self, state: Mapping[str, Any]) -> None:
        self.generator.set_state(state["generator"])
        self.counts = dict(state["counts"])
        self.totals = dict(state.get("totals", self.counts))
        self.advisor_totals.update(state.get("advisor_totals", {}))
        self.calls_used = int(state.get("calls_used", 0))
        hold = state.get("hold")
        self.hold = None if hold is None else {k: v.clone() for k, v in hold.items()}
        if state.get("advisor") is not None and self.advisor is not None:
            self.advisor.load_state_dict(state["advisor"])

    def __deepcopy__(self, memo: dict) -> "OverridePolicy":
        # A target network is a copy of the actor, never of this wrapper (whose advisor owns an
        # HTTP client, a cache and maybe a server): refuse loudly rather than duplicate them.
        raise TypeError(
            "OverridePolicy must not be deep-copied; copy policy.actor instead (the advisor "
            "owns a client, a cache and possibly a local server)"
        )

    def close(self) -> None:
        if self.advisor is not None:
            self.advisor.close()

    def extra_repr(self) -> str:
        return (f"mode={self.mode!r}, d_th={self.d_th}, fp={self.fp}, fallback={self.fallback!r}, "
                f"hold_steps={self.hold_steps}, max_calls={self.max_calls}, "
                f"advisor={type(self.advisor).__name__ if self.advisor is not None else None}")
