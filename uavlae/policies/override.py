"""The override policy (SPEC.md §8, SAC+LLM / SAC+Heuristic / fixed-probability LLM).

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
========  =====  ===========================================================

Triggers (``mode``): ``"proximity"`` (paper: any BZ, NFZ, RZ or OU within ``d_th`` of the
DCU, read from the env's ``("state", "d_bz" | "d_nfz" | "d_rz" | "d_ou")``; an OU counts only
within the perception radius, as the DCU sees it, which matters once ``d_th`` exceeds it), ``"fixed_prob"``
(each row with probability ``fp`` from the module's own seeded generator, whatever the
surroundings), ``"always"`` (the ``llm`` baseline) and ``"never"``.

Failed advice (``ok`` False) follows ``fallback``: ``"policy"`` keeps the actor's action,
``"heuristic"`` executes the heuristic's action (both recorded as FALLBACK), and
``"end_episode"`` (paper §5.3) keeps the actor's action and sets ``"override_abort"`` for that
row so :class:`uavlae.collect.UAVCollector` ends the episode there.

Advisors share one small protocol (duck-typed, see :class:`Advisor`)::

    advise(td_rows, rows) -> (actions [n, 2] in [-1, 1], ok [n] bool)

where ``td_rows`` is the tensordict of the triggered rows only (with its ``("state", ...)``
entries) and ``rows`` their indices in the batch. An advisor may expose ``source`` (the
``action_source`` value of its successful actions, default LLM), ``fallback`` (its own
configured fallback, used when the policy's ``fallback`` is None), ``snapshot()`` (counters)
and ``close()``.

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
import math
from collections.abc import Iterator, Mapping
from typing import Any, Protocol

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torch import Tensor
from torchrl.envs.utils import ExplorationType, set_exploration_type

POLICY, LLM, HEURISTIC, FALLBACK = 0, 1, 2, 3
SOURCE_NAMES = {POLICY: "policy", LLM: "llm", HEURISTIC: "heuristic", FALLBACK: "fallback"}
MODES = ("proximity", "fixed_prob", "always", "never")
FALLBACKS = ("policy", "heuristic", "end_episode")
# the env's distances to the nearest obstacle of each kind (docs/env_contract.md)
PROXIMITY_KEYS = (("state", "d_bz"), ("state", "d_nfz"), ("state", "d_rz"), ("state", "d_ou"))

__all__ = [
    "Advisor", "FALLBACK", "HEURISTIC", "HeuristicAdvisor", "LLM", "LLMAdvisorAdapter", "OverridePolicy",
    "POLICY", "SOURCE_NAMES",
]


class Advisor(Protocol):
    """What :class:`OverridePolicy` needs from an advisor."""

    def advise(self, td_rows: TensorDictBase, rows: Tensor) -> tuple[Tensor, Tensor]: ...


# ---------------------------------------------------------------------------- advisors


class HeuristicAdvisor:
    """The greedy controller as an advisor (SAC+Heuristic); it never fails.

    Args:
        heuristic: a :class:`uavlae.policies.heuristic.HeuristicPolicy`.

    [decision] The heuristic sees only the triggered rows, like the LLM. Its per-row plan and
    graph caches assume a fixed batch, so with changing row sets it replans those rows each
    call: correct, a little slower than acting on the whole batch.
    """

    source = HEURISTIC

    def __init__(self, heuristic: Any):
        self.heuristic = heuristic
        self.calls = 0
        self.rows_advised = 0

    def advise(self, td_rows: TensorDictBase, rows: Tensor) -> tuple[Tensor, Tensor]:
        self.calls += 1
        self.rows_advised += int(rows.numel())
        action = self.heuristic.act(td_rows.get("state"))
        return action, torch.ones(action.shape[0], dtype=torch.bool, device=action.device)

    def snapshot(self, reset: bool = False) -> dict[str, float]:
        out = {"calls": self.calls, "rows_advised": self.rows_advised}
        if reset:
            self.calls = self.rows_advised = 0
        return out

    def state_dict(self) -> dict[str, Any]:
        """The heuristic's plan and graph caches and the counters (checkpoints: exact resume)."""
        return {"cache": self.heuristic.cache_state(), "calls": self.calls, "rows_advised": self.rows_advised}

    def load_state_dict(self, state: Mapping[str, Any]) -> None:
        self.heuristic.load_cache_state(state["cache"])
        self.calls, self.rows_advised = int(state["calls"]), int(state["rows_advised"])


class LLMAdvisorAdapter:
    """An :class:`uavlae.llm.LLMAdvisor` behind the advisor protocol.

    The triggered rows become :class:`~uavlae.llm.AdvisorState` objects (the env's raw state
    and the world limits of ``env_cfg``), all go to ``advise_sync`` in one call so the
    advisor sends them concurrently (up to its ``max_concurrency``), and each validated
    velocity becomes the action ``v / v_max`` (SPEC §2). An ``AdviceFailure`` gives ``ok``
    False; the override policy applies the fallback.

    Args:
        llm: the advisor (owns its client, cache and possibly a local server).
        env_cfg: the env's config (``EnvConfig`` or anything with its attributes).
        timeout: seconds to wait for one step's answers (None: the advisor's own limits).
    """

    source = LLM

    def __init__(self, llm: Any, env_cfg: Any, timeout: float | None = None):
        from uavlae.envs.config import make_env_config
        from uavlae.llm import WorldLimits

        self.llm = llm
        self.env_cfg = make_env_config(env_cfg)
        self.limits = WorldLimits.from_env_config(self.env_cfg)
        self.timeout = timeout

    @property
    def fallback(self) -> str:
        return self.llm.cfg.fallback

    def advise(self, td_rows: TensorDictBase, rows: Tensor) -> tuple[Tensor, Tensor]:
        from uavlae.llm import Advice, advisor_states_from_tensordict

        n = td_rows.batch_size[0]
        states = advisor_states_from_tensordict(td_rows, list(range(n)), self.limits)
        results = self.llm.advise_sync(states, timeout=self.timeout)
        v_max = self.limits.v_max
        actions = torch.zeros(n, 2)
        ok = torch.zeros(n, dtype=torch.bool)
        for i, r in enumerate(results):
            if isinstance(r, Advice):
                actions[i] = torch.tensor(r.action(v_max))
                ok[i] = True
        return actions.clamp(-1.0, 1.0), ok

    def snapshot(self, reset: bool = False) -> dict[str, float]:
        return self.llm.stats.snapshot(reset=reset)

    def close(self) -> None:
        self.llm.close()


# ---------------------------------------------------------------------------- the module


class OverridePolicy(TensorDictModuleBase):
    """The actor, with its action overridden by an advisor on triggered rows.

    Args:
        actor: any module reading ``td`` and writing ``"action"`` ``[B, 2]`` (its other
            outputs, e.g. ``"action_log_prob"``, are left as the actor wrote them).
        advisor: see the module docstring; ``None`` means the actor alone (mode ignored).
        mode: ``"proximity"`` | ``"fixed_prob"`` | ``"always"`` | ``"never"``.
        d_th: proximity threshold, metres (SPEC §8: 15 m).
        fp: trigger probability of ``"fixed_prob"`` (paper: 0.3, 0.4, 0.5, 1.0).
        fallback: ``"policy"`` | ``"heuristic"`` | ``"end_episode"``; ``None`` takes the
            advisor's ``fallback`` (the LLM config's) or ``"policy"``.
        heuristic: a ``HeuristicPolicy`` for ``fallback="heuristic"`` (a
            :class:`HeuristicAdvisor`'s own heuristic is used when this is None).
        seed: seeds the trigger generator of ``"fixed_prob"``.
        perception_radius: OUs farther than this (m) do not trigger (the env's ``d_ou``
            counts every OU; the DCU sees only those within its perception radius).
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
        perception_radius: float = math.inf,
    ):
        super().__init__()
        if mode not in MODES:
            raise ValueError(f"override.mode must be one of {list(MODES)}, got {mode!r}")
        if not (math.isfinite(d_th) and d_th >= 0):
            raise ValueError(f"override.d_th must be a finite distance >= 0 m, got {d_th!r}")
        if not 0.0 <= fp <= 1.0:
            raise ValueError(f"override.fp must be in [0, 1], got {fp!r}")
        if fallback is None:
            fallback = getattr(advisor, "fallback", None) or "policy"
        if fallback not in FALLBACKS:
            raise ValueError(f"override.fallback must be one of {list(FALLBACKS)}, got {fallback!r}")
        if heuristic is None and isinstance(advisor, HeuristicAdvisor):
            heuristic = advisor.heuristic
        if fallback == "heuristic" and heuristic is None:
            raise ValueError("override.fallback='heuristic' needs a heuristic policy")
        self.actor = actor
        # plain attributes, not submodules: never in state_dict, never moved by .to()
        self.__dict__["advisor"] = advisor
        self.__dict__["heuristic"] = heuristic
        self.mode = mode
        self.d_th = float(d_th)
        self.fp = float(fp)
        self.fallback = fallback
        self.seed = int(seed)
        self.perception_radius = float(perception_radius)
        self.deterministic = False  # evaluation / deployment: actor alone, deterministic
        self._active_actor: Any = None  # set by using_actor() (random warm-up frames)
        self.generator = torch.Generator()
        self.generator.manual_seed(self.seed)
        in_keys = list(getattr(actor, "in_keys", ["observation"]))
        if advisor is not None and mode == "proximity":
            in_keys += [k for k in PROXIMITY_KEYS if k not in in_keys]
        self.in_keys = in_keys
        self.reset_counters()

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
        if not self.override_active:
            return torch.zeros(B, dtype=torch.bool, device=device)
        if self.mode == "always":
            return torch.ones(B, dtype=torch.bool, device=device)
        if self.mode == "fixed_prob":
            u = torch.rand(B, generator=self.generator)
            return (u < self.fp).to(device)
        # "proximity": SPEC §8, any BZ, NFZ, RZ or OU within d_th (inf when none is present)
        d = torch.stack([td.get(k).reshape(B) for k in PROXIMITY_KEYS], dim=-1)
        d_ou = d[:, -1]  # PROXIMITY_KEYS ends with d_ou
        d = torch.cat([d[:, :-1], d_ou.masked_fill(d_ou > self.perception_radius, math.inf)[:, None]], -1).amin(-1)
        return (d <= self.d_th).to(device)

    # ------------------------------------------------------------------ acting
    def _act(self, td: TensorDictBase) -> TensorDictBase:
        actor = self._active_actor if self._active_actor is not None else self.actor
        if self.deterministic:
            with set_exploration_type(ExplorationType.DETERMINISTIC):
                out = actor(td)
        else:
            out = actor(td)
        return td if out is None else out

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        td = self._act(tensordict)
        action = td.get("action")
        B = td.batch_size[0]
        source = torch.zeros(B, dtype=torch.int64, device=action.device)
        abort = torch.zeros(B, dtype=torch.bool, device=action.device)
        trig = self.trigger(td)
        rows = trig.nonzero().squeeze(-1)
        if rows.numel():
            with torch.no_grad():
                adv_action, ok = self.advisor.advise(td[rows], rows)
            adv_action = adv_action.to(device=action.device, dtype=action.dtype).clamp(-1.0, 1.0)
            ok = ok.to(device=action.device, dtype=torch.bool).reshape(-1)
            if adv_action.shape != (rows.numel(), action.shape[-1]) or ok.shape[0] != rows.numel():
                raise ValueError(
                    f"advisor returned actions {tuple(adv_action.shape)} and ok {tuple(ok.shape)} "
                    f"for {rows.numel()} rows"
                )
            action = action.clone()
            good, bad = rows[ok], rows[~ok]
            action[good] = adv_action[ok]
            source[good] = int(getattr(self.advisor, "source", LLM))
            if bad.numel():
                source[bad] = FALLBACK
                if self.fallback == "heuristic":
                    h = self.heuristic.act(td[bad].get("state"))
                    action[bad] = h.to(device=action.device, dtype=action.dtype)
                elif self.fallback == "end_episode":
                    abort[bad] = True
                # "policy": the actor's action stays
            td.set("action", action)
        td.set("action_source", source)
        td.set("override_abort", abort)
        if self.override_active:
            self._count(source, trig, abort)
        return td

    # ------------------------------------------------------------------ counters
    def reset_counters(self) -> None:
        self.counts = {"frames": 0, "triggered": 0, "aborts": 0, **{f"source/{n}": 0 for n in SOURCE_NAMES.values()}}

    def _count(self, source: Tensor, trig: Tensor, abort: Tensor) -> None:
        c = self.counts
        c["frames"] += int(source.numel())
        c["triggered"] += int(trig.sum())
        c["aborts"] += int(abort.sum())
        per = torch.bincount(source.reshape(-1).cpu(), minlength=len(SOURCE_NAMES))
        for k, name in SOURCE_NAMES.items():
            c[f"source/{name}"] += int(per[k])

    def snapshot(self, reset: bool = False) -> dict[str, float]:
        """Counters since the last reset: frames acted with the override on, ``triggered``,
        ``source/<name>``, ``aborts``, ``trigger_rate`` (triggered / frames), ``override_rate``
        (advisor actions executed / frames), ``advice_fail_rate`` (fallbacks / triggered), and
        the advisor's own counters under ``advisor/`` (the LLM's: requests, calls, cache hits,
        retries, failures by kind, tokens, latency quantiles)."""
        c = dict(self.counts)
        frames, trig = c["frames"], c["triggered"]
        nan = float("nan")
        c["trigger_rate"] = trig / frames if frames else nan
        c["override_rate"] = (c["source/llm"] + c["source/heuristic"]) / frames if frames else nan
        c["advice_fail_rate"] = c["source/fallback"] / trig if trig else nan
        snap = getattr(self.advisor, "snapshot", None)
        if snap is not None:
            c.update({f"advisor/{k}": v for k, v in snap(reset=reset).items()})
        if reset:
            self.reset_counters()
        return c

    # ------------------------------------------------------------------ state
    def get_extra_state(self) -> dict[str, Any]:
        # an advisor with state that shapes its answers (the heuristic's plan cache) saves it too
        adv = getattr(self.advisor, "state_dict", None)
        return {"generator": self.generator.get_state(), "counts": dict(self.counts),
                "advisor": adv() if adv is not None else None}

    def set_extra_state(self, state: Mapping[str, Any]) -> None:
        self.generator.set_state(state["generator"])
        self.counts = dict(state["counts"])
        if state.get("advisor") is not None and hasattr(self.advisor, "load_state_dict"):
            self.advisor.load_state_dict(state["advisor"])

    def __deepcopy__(self, memo: dict) -> "OverridePolicy":
        # A target network is a copy of the actor, never of this wrapper (whose advisor owns an
        # HTTP client, a cache and maybe a server): refuse loudly rather than duplicate them.
        raise TypeError(
            "OverridePolicy must not be deep-copied; copy policy.actor instead (the advisor "
            "owns a client, a cache and possibly a local server)"
        )

    def close(self) -> None:
        close = getattr(self.advisor, "close", None)
        if close is not None:
            close()

    def extra_repr(self) -> str:
        return (f"mode={self.mode!r}, d_th={self.d_th}, fp={self.fp}, fallback={self.fallback!r}, "
                f"advisor={type(self.advisor).__name__ if self.advisor is not None else None}")
