"""The advisor contract: everything :class:`uavlae.policies.override.OverridePolicy` may ask of an
advisor, each hook named once with its default (the way gymnax's ``Environment`` and TorchRL's
``EnvBase`` write theirs), and the advisors that implement it.

An advisor answers the *triggered rows* of a step: ``advise(td_rows, rows)`` gets the tensordict
of those rows only (with their ``("state", ...)`` entries) and ``rows``, their indices in the
batch, and returns ``(actions [n, 2] in [-1, 1], ok [n] bool)``; an advisor that answers through
several hands (the student advisor, :mod:`uavlae.policies.student`) returns a third tensor, each
row's ``action_source``. Rows with ``ok`` False are failed advice: the override applies its one
fallback setting there (``advisor.fallback``). The override calls, and an advisor may override:

==================  ==============================================================================
hook                default
==================  ==============================================================================
``source``          LLM: the ``action_source`` of its answered rows (without a third tensor)
``asks_llm``        False: True makes :meth:`OverridePolicy.cost` count its calls, tokens, money
``fallback``        None: its own fallback setting, for an override given none (then ``policy``)
``advise``          abstract
``start``           ``advise`` answered at once, wrapped in an :class:`Answered` handle
``observe``         nothing: an advisor that remembers earlier slots follows every row here
``label``           None: its answer for every row of the step just observed, had it been asked
``snapshot``        no counters
``latencies``       None: it times no calls (no latency quantiles in the run's totals)
``price``           None: no price per token (the money is NaN where ``asks_llm``)
``state_dict``      None: nothing that shapes its next answers (the checkpoint holds None)
``load_state_dict`` nothing
``close``           nothing: an advisor that holds a client, a cache or a server lets them go
==================  ==============================================================================

A :class:`Handle` is one step's answers in flight: ``result()`` waits for them, ``done_at`` says
when they arrived (None while in flight) and ``failures`` what failed, one line per failed row.

:class:`InProcessAdvisor` is the advisors that answer in this process, at once, and never fail
(the heuristics, the scripted advisors): what they share (their call and row counters, in their
snapshot and their state) is written there once.
"""

from __future__ import annotations

import abc
import time
from collections.abc import Mapping, Sequence
from typing import Any, ClassVar, Protocol

import torch
from tensordict import TensorDictBase
from torch import Tensor

from uavlae.envs.config import make_env_config
from uavlae.llm import WorldLimits, advisor_states_from_tensordict

POLICY, LLM, HEURISTIC, FALLBACK, STUDENT, SCRIPTED = 0, 1, 2, 3, 4, 5
SOURCE_NAMES = {POLICY: "policy", LLM: "llm", HEURISTIC: "heuristic", FALLBACK: "fallback", STUDENT: "student",
                SCRIPTED: "scripted"}
ADVICE_SOURCES = (LLM, HEURISTIC, STUDENT, SCRIPTED)  # an advisor's own answer was executed

# (actions [n, 2], ok [n]) or, answered through several hands, (actions, ok, action_source [n])
Answer = tuple[Tensor, ...]
# (input, cached input, output) price per million tokens, and the currency
Price = tuple[float, float, float, str]

__all__ = [
    "ADVICE_SOURCES", "Advisor", "Answer", "Answered", "FALLBACK", "HEURISTIC", "Handle", "HeuristicAdvisor",
    "InProcessAdvisor", "LLM", "LLMAdvisorAdapter", "LLMEndpoint", "POLICY", "Price", "SCRIPTED", "SOURCE_NAMES",
    "STUDENT", "ScriptedAdvisor",
]


# ---------------------------------------------------------------------------- the contract


class Handle(abc.ABC):
    """One step's answers, asked for and perhaps still in flight."""

    done_at: float | None = None  # time.perf_counter() when the answers arrived; None while in flight
    failures: Sequence[str] = ()  # what failed, one line per failed row, once answered

    @abc.abstractmethod
    def result(self) -> Answer:
        """Wait for the answers and return them as :meth:`Advisor.advise` does."""


class Answered(Handle):
    """The handle of an answer given when asked: arrived at once."""

    def __init__(self, answer: Answer):
        self.answer = answer
        self.done_at = time.perf_counter()

    def result(self) -> Answer:
        return self.answer


class Advisor(abc.ABC):
    """What :class:`OverridePolicy` may call on an advisor (module docstring: the table of hooks)."""

    source: ClassVar[int] = LLM  # the action_source of its answered rows, without a third tensor
    asks_llm: ClassVar[bool] = False  # its rows cost LLM calls, tokens and money (OverridePolicy.cost)
    fallback: ClassVar[str | None] = None  # its own fallback, for an override given none (None: "policy")

    @abc.abstractmethod
    def advise(self, td_rows: TensorDictBase, rows: Tensor) -> Answer:
        """The actions of the triggered rows ``rows`` (``td_rows``: those rows only), and which
        of them are valid advice."""

    def start(self, td_rows: TensorDictBase, rows: Tensor) -> Handle:
        """The same request, sent without waiting: the caller works while it is in flight and
        reads ``result()`` after. By default the answer is given here, at once."""
        return Answered(self.advise(td_rows, rows))

    def observe(self, td: TensorDictBase) -> None:
        """The whole batch, at every step the override is on, before any row is asked: an
        advisor whose answers depend on earlier slots keeps that memory per env row here,
        however the set of triggered rows changes from slot to slot. By default: nothing."""

    def label(self) -> Tensor | None:
        """Its answer ``[B, 2]`` for every row of the batch :meth:`observe` was just given, had
        each been asked, where it has one at no extra cost (a teacher's label for the rows the
        actor flies, :class:`uavlae.policies.override.OverridePolicy`'s ``label_all``); None: it
        has none. Nothing is counted as advice and nothing it remembers changes."""
        return None

    def snapshot(self, reset: bool = False) -> dict[str, float]:
        """Its counters since the last reset (``reset``: start a new window); the override logs
        them under ``advisor/`` and sums :data:`uavlae.policies.override.ADVISOR_COUNTS` of them
        over the run. By default: none."""
        return {}

    def latencies(self) -> list[float] | None:
        """Every answered call's latency in the run, seconds; None: it times no calls."""
        return None

    def price(self) -> Price | None:
        """What its tokens cost, per million (input, cached input, output) and the currency;
        None: no price."""
        return None

    def state_dict(self) -> dict[str, Any] | None:
        """What shapes its next answers (memory, generators, counters), for an exact resume;
        None: nothing."""
        return None

    def load_state_dict(self, state: Mapping[str, Any]) -> None:
        """Back to a :meth:`state_dict`. By default: nothing to restore."""

    def close(self) -> None:
        """Let go of what it holds (a client, a cache, a server). By default: nothing."""


# ---------------------------------------------------------------------------- in-process advisors


class InProcessAdvisor(Advisor):
    """An advisor that answers in this process, at once, and never fails: a subclass gives
    :meth:`act` (the asked rows' actions) and, when it has any, the rest of its state
    (:meth:`own_state`, :meth:`load_own_state`); the counters are kept here."""

    def __init__(self) -> None:
        self.calls = 0
        self.rows_advised = 0

    @abc.abstractmethod
    def act(self, td_rows: TensorDictBase, rows: Tensor) -> Tensor:
        """The actions ``[n, 2]`` of the asked rows."""

    def advise(self, td_rows: TensorDictBase, rows: Tensor) -> Answer:
        self.calls += 1
        self.rows_advised += int(rows.numel())
        action = self.act(td_rows, rows)
        return action, torch.ones(action.shape[0], dtype=torch.bool, device=action.device)

    def snapshot(self, reset: bool = False) -> dict[str, float]:
        out = {"calls": self.calls, "rows_advised": self.rows_advised}
        if reset:
            self.calls = self.rows_advised = 0
        return out

    def own_state(self) -> dict[str, Any]:
        """What else shapes its answers (memory, a generator); none by default."""
        return {}

    def load_own_state(self, state: Mapping[str, Any]) -> None:
        """Back to an :meth:`own_state`."""

    def state_dict(self) -> dict[str, Any]:
        return {**self.own_state(), "calls": self.calls, "rows_advised": self.rows_advised}

    def load_state_dict(self, state: Mapping[str, Any]) -> None:
        self.load_own_state(state)
        self.calls, self.rows_advised = int(state["calls"]), int(state["rows_advised"])


class HeuristicAdvisor(InProcessAdvisor):
    """The greedy controller (or the planner) as an advisor (SAC+Heuristic); it never fails.

    Args:
        heuristic: a :class:`uavlae.policies.greedy.GreedyPolicy` or
            :class:`uavlae.policies.heuristic.HeuristicPolicy`.

    The heuristics remember earlier slots (target, detour side, stall counter, homing latch; the
    planner's plans). Under the override the triggered rows change from slot to slot, so the
    advisor follows every row: :meth:`observe` steps the heuristic on the whole batch at every
    step the override is on, and :meth:`advise` answers the asked rows from that step. Each
    row's answer is then the one the heuristic would give flying that env row every slot, as it
    does when flown alone: the advisor is the baseline it is compared with. Called without
    :meth:`observe` (a direct call), it acts on the given rows alone.
    """

    source = HEURISTIC

    def __init__(self, heuristic: Any):
        super().__init__()
        self.heuristic = heuristic
        self._step: Tensor | None = None  # this step's action of every row, from observe()

    def observe(self, td: TensorDictBase) -> None:
        self._step = self.heuristic.act(td.get("state"))

    def act(self, td_rows: TensorDictBase, rows: Tensor) -> Tensor:
        step, self._step = self._step, None
        return step[rows.to(step.device)] if step is not None else self.heuristic.act(td_rows.get("state"))

    def label(self) -> Tensor | None:
        """Every row's answer of the step :meth:`observe` computed (it steps the heuristic on the
        whole batch anyway): the rows the actor flies get the label at no cost."""
        return None if self._step is None else self._step.clone()

    def own_state(self) -> dict[str, Any]:
        """The heuristic's memory (checkpoints: exact resume)."""
        return {"cache": self.heuristic.cache_state()}

    def load_own_state(self, state: Mapping[str, Any]) -> None:
        self.heuristic.load_cache_state(state["cache"])


class ScriptedAdvisor(InProcessAdvisor):
    """Advisors of known, poor quality, for measuring what advice is worth (beyond the paper):
    ``"hover"`` answers a zero velocity (the DCU stays where it is), ``"random"`` a uniform
    action in [-1, 1]^2 from its own seeded generator (checkpointed). Neither ever fails.

    Args:
        kind: ``"hover"`` | ``"random"``.
        seed: seeds ``"random"``'s generator.
    """

    source = SCRIPTED
    KINDS = ("hover", "random")

    def __init__(self, kind: str, seed: int = 0):
        if kind not in self.KINDS:
            raise ValueError(f"a scripted advisor is one of {list(self.KINDS)}, got {kind!r}")
        super().__init__()
        self.kind = kind
        self.generator = torch.Generator().manual_seed(int(seed))

    def act(self, td_rows: TensorDictBase, rows: Tensor) -> Tensor:
        n = int(rows.numel())
        if self.kind == "hover":
            return torch.zeros(n, 2)
        return torch.rand(n, 2, generator=self.generator) * 2.0 - 1.0

    def own_state(self) -> dict[str, Any]:
        return {"generator": self.generator.get_state()}

    def load_own_state(self, state: Mapping[str, Any]) -> None:
        self.generator.set_state(state["generator"])


# ---------------------------------------------------------------------------- the LLM


class LLMEndpoint(Protocol):
    """What :class:`LLMAdvisorAdapter` asks of its LLM (:class:`uavlae.llm.LLMAdvisor`)."""

    cfg: Any  # its uavlae.llm.LLMConfig: the view the prompt shows, the price
    stats: Any  # its uavlae.llm.AdvisorStats: snapshot(reset) and the answered calls' latencies

    def submit(self, states: list[Any]) -> Any:
        """The answers to ``states`` (Advice or AdviceFailure each), as a future: sent at once."""

    def close(self) -> None: ...


class LLMAdvisorAdapter(Advisor):
    """An :class:`uavlae.llm.LLMAdvisor` behind the advisor contract.

    The triggered rows become :class:`~uavlae.llm.AdvisorState` objects (the env's raw state
    and the world limits of ``env_cfg``), all go to the LLM in one request so that it sends them
    concurrently (up to its ``max_concurrency``), and each validated velocity becomes the action
    ``v / v_max`` (SPEC §2). An ``AdviceFailure`` gives ``ok`` False; the override policy applies
    its fallback.

    Args:
        llm: the LLM (owns its client, cache and possibly a local server).
        env_cfg: the env's config (``EnvConfig`` or anything with its attributes).
        timeout: seconds to wait for one step's answers (None: the LLM's own limits).
    """

    source = LLM
    asks_llm = True

    def __init__(self, llm: LLMEndpoint, env_cfg: Any, timeout: float | None = None):
        self.llm = llm
        self.env_cfg = make_env_config(env_cfg)
        self.limits = WorldLimits.from_env_config(self.env_cfg)
        self.timeout = timeout
        self.run_latencies: list[float] = []  # the windows already reset, for the run's quantiles

    @property
    def observation(self) -> str:
        """How the prompt writes the state (``compact`` | ``verbose``): what the LLM is shown."""
        return self.llm.cfg.observation

    def advise(self, td_rows: TensorDictBase, rows: Tensor) -> Answer:
        return self.start(td_rows, rows).result()

    def start(self, td_rows: TensorDictBase, rows: Tensor) -> "_LLMHandle":
        """Send the rows' requests and return at once; ``result()`` waits for the answers."""
        return self.ask(self.states(td_rows))

    def states(self, td_rows: TensorDictBase) -> list[Any]:
        """The rows as the LLM sees them (:class:`~uavlae.llm.AdvisorState`, of its view)."""
        n = td_rows.batch_size[0]
        cfg = self.llm.cfg
        local = cfg.view == "local"  # the LLM alone: what lies within view_radius
        return advisor_states_from_tensordict(td_rows, list(range(n)), self.limits,
                                              view_radius=cfg.view_radius if local else None)

    def ask(self, states: list[Any]) -> "_LLMHandle":
        """The LLM's answers to ``states``, in flight."""
        return _LLMHandle(self, self.llm.submit(states))

    def price(self) -> Price | None:
        cfg = self.llm.cfg
        price = cfg.price()
        return None if price is None else (*price, cfg.price_currency)

    def _actions(self, results: list[Any]) -> Answer:
        v_max = self.limits.v_max
        actions = torch.zeros(len(results), 2)
        ok = torch.zeros(len(results), dtype=torch.bool)
        for i, r in enumerate(results):
            if r.ok:
                actions[i] = torch.tensor(r.action(v_max))
                ok[i] = True
        return actions.clamp(-1.0, 1.0), ok

    def snapshot(self, reset: bool = False) -> dict[str, float]:
        if reset:  # the run's per-call latencies outlive the logging window
            self.run_latencies.extend(self.llm.stats.latencies)
        return self.llm.stats.snapshot(reset=reset)

    def latencies(self) -> list[float]:
        """Every answered HTTP call's latency in this run, seconds (the current window too)."""
        return [*self.run_latencies, *self.llm.stats.latencies]

    def state_dict(self) -> dict[str, Any]:
        return {"run_latencies": torch.tensor(self.run_latencies, dtype=torch.float64)}

    def load_state_dict(self, state: Mapping[str, Any]) -> None:
        self.run_latencies[:] = [float(x) for x in state["run_latencies"].tolist()]

    def close(self) -> None:
        self.llm.close()


class _LLMHandle(Handle):
    """The LLM's answers for one step, in flight; ``done_at`` is set when they arrive."""

    def __init__(self, adapter: LLMAdvisorAdapter, future: Any):
        self.adapter = adapter
        self.future = future
        self.done_at: float | None = None
        self.failures: list[str] = []
        future.add_done_callback(self._arrived)

    def _arrived(self, _future: Any) -> None:
        self.done_at = time.perf_counter()

    def answers(self) -> list[Any]:
        """The LLM's results (Advice or AdviceFailure), in order; raises its EndpointError."""
        results = self.future.result(self.adapter.timeout)
        self.failures = [f"{r.kind.value}: {r.detail}" for r in results if not r.ok]
        return results

    def result(self) -> Answer:
        return self.adapter._actions(self.answers())
