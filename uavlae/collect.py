"""The collector and the replay buffer (docs/style.md: scenario → env → override policy → collector →
replay buffer).

:class:`UAVCollector` steps one batched :class:`~uavlae.envs.UAVEnv` with a policy (usually an
:class:`~uavlae.policies.override.OverridePolicy`) in the calling process and yields batches of
shape ``[B, T]`` (time last, as torchrl's collectors) holding what was executed: ``"action"``,
``"action_source"`` and ``"next"`` with reward, done flags, cost, events and state. It is
deliberately single-process: the LLM advisor's client, cache and local server stay in this
process, and nothing of the policy is copied or pickled (see ``OverridePolicy.__deepcopy__``).

A step comes in two halves, so that the caller's work can run while the advice is in flight:
:meth:`UAVCollector.begin_step` decides the triggered rows from the state alone and sends their
advice requests; :meth:`UAVCollector.finish_step` lets the actor act (the updated actor, when the
caller ran gradient steps in between), waits for the answers, merges them and steps the env,
returning the executed transition ``[B]``. :meth:`UAVCollector.step` is both halves with nothing
between them; :meth:`UAVCollector.rollout_batch` stacks ``T`` steps.

``override_abort`` rows (failed advice with ``fallback="end_episode"``, paper §5.3) get
``("next", "truncated")`` and ``("next", "done")`` set before the partial reset, so exactly
those episodes end there. Finished episodes are measured with
:class:`~uavlae.envs.metrics.EpisodeTracker`; :meth:`UAVCollector.episode_metrics` gives the
records and the paper's aggregates since the last call.

:func:`make_replay_buffer` builds the torchrl ``TensorDictReplayBuffer`` (``LazyTensorStorage``,
uniform ``RandomSampler``) that takes the collector's batches flattened to ``[B * T]``
transitions; its ``state_dict()`` / ``load_state_dict()`` hold the stored data for checkpoints.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torchrl.data import LazyMemmapStorage, LazyTensorStorage, RandomSampler, TensorDictReplayBuffer
from torchrl.envs.utils import ExplorationType, set_exploration_type, step_mdp

from uavlae.envs.metrics import EpisodeTracker, aggregate
from uavlae.policies.override import POLICY, OverridePolicy, Pending
from uavlae.policies.safety import SafetyFilter, SafetyStats, apply_filter

NestedKey = str | tuple[str, ...]

# What a learner needs of a transition; the bulky static ("state", ...) entries are left out.
# Missing keys are skipped, so this serves SAC/DDPG (replay) and PPO/CPO (log-probs) alike.
TRANSITION_KEYS: tuple[NestedKey, ...] = (
    "observation", "action", "action_source", "action_log_prob", "advice", "advice_ok",
    "done", "terminated", "truncated",
    ("next", "observation"), ("next", "reward"), ("next", "cost"), ("next", "done"),
    ("next", "terminated"), ("next", "truncated"), ("next", "events"), ("next", "reward_terms"),
    ("safety", "changed"), ("safety", "delta"), ("next", "safety_penalty"),
)

__all__ = ["TRANSITION_KEYS", "UAVCollector", "UniformReplayBuffer", "make_replay_buffer"]


@dataclass
class StepHandle:
    """A step between its two halves: the root it acts on, the override's pending advice
    (None for a plain policy), whether the random warm-up acts, and what finish_step closes."""

    td: TensorDictBase
    pending: Pending | None
    random: bool
    stack: contextlib.ExitStack


def _has_extra_state(module: Any) -> bool:
    """Every nn.Module has ``get_extra_state``; only overriding it means there is state to keep."""
    return type(module).get_extra_state is not torch.nn.Module.get_extra_state


class _UniformRandom(TensorDictModuleBase):
    """Uniform actions in the env's action box, from the collector's own generator."""

    in_keys: list = []
    out_keys = ["action"]

    def __init__(self, action_spec: Any, generator: torch.Generator):
        super().__init__()
        self.low = action_spec.space.low
        self.high = action_spec.space.high
        self.shape = action_spec.shape
        self.generator = generator

    def forward(self, td: TensorDictBase) -> TensorDictBase:
        u = torch.rand(self.shape, generator=self.generator).to(self.low.device)
        td.set("action", self.low + (self.high - self.low) * u)
        return td


class UAVCollector:
    """Batched on-process collector for :class:`~uavlae.envs.UAVEnv` (batch ``[B]``).

    Args:
        env: the env (``batch_size=[B]``); it is reset on the first batch.
        policy: reads the root tensordict, writes ``"action"`` (an ``OverridePolicy`` also
            writes ``"action_source"`` and ``"override_abort"``; other policies get
            ``action_source = POLICY``).
        frames_per_batch: env frames per yielded batch; ``T = frames_per_batch // B`` steps.
        total_frames: stop after this many frames (``None`` or ``-1``: never stop).
        init_random_frames: the first frames act with ``random_policy`` (the override, if
            any, still applies on top: its advisor helps from the first step).
        random_policy: default: uniform in the action box, seeded by ``seed``.
        keep_keys: keys of the yielded batches (``None``: everything the env and policy
            wrote; :data:`TRANSITION_KEYS`: what a learner needs, without the raw state).
        exploration_type: the policy acts under it (``RANDOM``: sampled actions).
        seed: seeds the random warm-up policy.
        max_episodes_per_row: passed to the episode tracker.
        safety: a :class:`~uavlae.policies.safety.SafetyFilter` that every executed action goes
            through (the actor's, an advisor's, the warm-up's); the transition records
            ``("safety", "changed")`` and ``("safety", "delta")`` (|Δv|, m/s), and with
            ``penalty > 0`` the reward loses ``penalty * delta / v_max``
            (``("next", "safety_penalty")``); ``learn_from="proposed"`` stores the wish instead
            of the executed action, and ``cost > 0`` adds ``cost * delta / v_max`` to
            ``("next", "cost")`` after the episode tracker has counted the env's cost.
    """

    def __init__(
        self,
        env: Any,
        policy: Any,
        frames_per_batch: int,
        total_frames: int | None = None,
        init_random_frames: int = 0,
        random_policy: Any = None,
        *,
        keep_keys: Sequence[NestedKey] | None = None,
        exploration_type: ExplorationType = ExplorationType.RANDOM,
        seed: int = 0,
        max_episodes_per_row: int | None = None,
        safety: SafetyFilter | None = None,
    ):
        if len(env.batch_size) != 1:
            raise ValueError(f"UAVCollector needs an env with batch_size [B], got {list(env.batch_size)}")
        self.env = env
        self.policy = policy
        self.B = int(env.batch_size[0])
        if frames_per_batch < self.B:
            raise ValueError(f"frames_per_batch={frames_per_batch} must be >= the env batch size {self.B}")
        self.T = int(frames_per_batch) // self.B
        self.frames_per_batch = self.T * self.B
        self.total_frames = -1 if total_frames is None else int(total_frames)
        self.init_random_frames = int(init_random_frames)
        self.generator = torch.Generator()
        self.generator.manual_seed(int(seed))
        self.random_policy = random_policy if random_policy is not None else _UniformRandom(env.action_spec, self.generator)
        self.keep_keys = None if keep_keys is None else list(keep_keys)
        self.exploration_type = exploration_type
        self.tracker = EpisodeTracker(self.B, env.cfg, max_episodes_per_row=max_episodes_per_row, device=env.device)
        self.frames = 0
        self.batches = 0
        self._td: TensorDictBase | None = None
        self.safety = safety
        self.safety_stats = SafetyStats()  # since the last logged batch
        self.safety_totals = SafetyStats()  # over the run

    # ------------------------------------------------------------------ stepping
    def _reset(self) -> None:
        self._td = self.env.reset()
        self.tracker.reset()

    def begin_step(self) -> StepHandle:
        """The first half of a step: the triggered rows' advice requests go out (the random
        warm-up's actor acts for the first ``init_random_frames`` frames, the override on top)."""
        if self._td is None:
            self._reset()
        stack = contextlib.ExitStack()
        random = self.frames < self.init_random_frames
        if not isinstance(self.policy, OverridePolicy):  # a plain policy acts alone, in finish_step
            return StepHandle(self._td, None, random, stack)
        if random:
            stack.enter_context(self.policy.using_actor(self.random_policy))
        with torch.no_grad(), set_exploration_type(self.exploration_type):
            pending = self.policy.begin(self._td)
        return StepHandle(self._td, pending, random, stack)

    @torch.no_grad()
    def finish_step(self, handle: StepHandle) -> TensorDictBase:
        """The second half: the actor acts, the answers are merged, the env steps; returns the
        executed transition ``[B]`` (with ``"next"``)."""
        with handle.stack, set_exploration_type(self.exploration_type):
            td = handle.td
            if handle.pending is None:
                td = self.random_policy(td) if handle.random else self.policy(td)
                td.set("action_source", torch.full((self.B,), POLICY, dtype=torch.int64, device=td.device))
                td.set("override_abort", torch.zeros(self.B, dtype=torch.bool, device=td.device))
            else:
                td = self.policy.finish(td, handle.pending)
        wish = None
        if self.safety is not None:
            if self.safety.cfg.learn_from == "proposed":
                wish = td.get("action").clone()
            self._filter(td)
        td = self.env.step(td)
        nxt = td.get("next")
        if self.safety is not None and self.safety.cfg.penalty > 0:
            # the filter's change is priced in the reward, so the actor learns not to lean on it
            pen = self.safety.cfg.penalty * td.get(("safety", "delta")) / self.env.cfg.motion.v_max
            nxt.set("safety_penalty", pen.reshape(nxt.get("reward").shape))
            nxt.set("reward", nxt.get("reward") - nxt.get("safety_penalty"))
        abort = td.get("override_abort").reshape(self.B, 1)
        if bool(abort.any()):
            # paper §5.3: no valid LLM action after the attempts ends the episode; it is cut
            # short (truncated), not terminal, so the value of the next state is still bootstrapped
            nxt.set("truncated", nxt.get("truncated") | abort)
            nxt.set("done", nxt.get("done") | abort)
        self.tracker.update(nxt)
        # after the tracker: an episode's reported cost stays docs/model.md §7's, while a
        # constrained learner's cost also counts the filter's correction
        if self.safety is not None and self.safety.cfg.cost > 0:
            extra = self.safety.cfg.cost * td.get(("safety", "delta")) / self.env.cfg.motion.v_max
            nxt.set("cost", nxt.get("cost") + extra.reshape(nxt.get("cost").shape).to(nxt.get("cost").dtype))
        if wish is not None:
            # the filter becomes part of the learner's dynamics: the wish is stored with the
            # outcome of its corrected execution
            td.set("action", wish)
        out = td if self.keep_keys is None else td.select(*self.keep_keys, strict=False)
        # clone: the partial reset below writes in place (TensorDict.where(out=...)) into the
        # tensors that the next root shares with this transition's "next"
        out = out.clone()
        self._td = self.env.maybe_reset(step_mdp(td, keep_other=False, exclude_action=True))
        self.frames += self.B
        return out

    def _filter(self, td: TensorDictBase) -> None:
        apply_filter(self.safety, td)
        for stats in (self.safety_stats, self.safety_totals):
            stats.add(td.get(("safety", "changed")), td.get(("safety", "delta")))

    def step(self) -> TensorDictBase:
        """One env step of every row: returns the transition ``[B]`` (with ``"next"``)."""
        return self.finish_step(self.begin_step())

    def rollout_batch(self) -> TensorDictBase:
        """``T`` steps of every row stacked to ``[B, T]`` (time last)."""
        return self.batch_of([self.step() for _ in range(self.T)])

    def batch_of(self, steps: Sequence[TensorDictBase]) -> TensorDictBase:
        """The ``T`` transitions of one batch, stacked to ``[B, T]`` and counted as a batch (a
        caller that steps the collector itself, to work between the steps, ends a batch so)."""
        self.batches += 1
        return torch.stack(list(steps), dim=1)

    def __iter__(self) -> Iterator[TensorDictBase]:
        while self.total_frames < 0 or self.frames < self.total_frames:
            yield self.rollout_batch()

    def __len__(self) -> int:
        if self.total_frames < 0:
            raise TypeError("an endless collector (total_frames=None) has no length")
        return -(-self.total_frames // self.frames_per_batch)

    # ------------------------------------------------------------------ reporting
    def episode_metrics(self, clear: bool = True) -> tuple[dict[str, torch.Tensor], dict[str, float]]:
        """``(records, aggregates)`` of the episodes finished since the last call (``clear``):
        column-wise per-episode records (``uavlae.envs.metrics.RECORD_COLUMNS``) and DCR, CR,
        SLR, RVR, ECR, means of return, length, cost and of every reward term, ``n_episodes``."""
        records = self.tracker.records()
        if clear:
            self.tracker.clear()
        return records, aggregate(records)

    def override_stats(self, reset: bool = False) -> dict[str, float]:
        """The override policy's counters (trigger and override rates, sources, LLM counters)."""
        return dict(self.policy.snapshot(reset=reset)) if isinstance(self.policy, OverridePolicy) else {}

    # ------------------------------------------------------------------ resume
    def state_dict(self) -> dict[str, Any]:
        """Everything needed to continue collecting exactly where this one is (plain tensors and
        dicts, loadable with ``torch.load(weights_only=True)``): frame counters, the env's RNG
        and scenario pool, the current tensordict, the warm-up generator, the episode tracker
        and the override policy's trigger generator and counters."""
        env = getattr(self.env, "base_env", self.env)  # a TransformedEnv keeps its RNG in the base
        tr = self.tracker
        out: dict[str, Any] = {
            "frames": self.frames,
            "batches": self.batches,
            "generator": self.generator.get_state(),
            "env": env.sampler_state() if hasattr(env, "sampler_state") else None,
            "td": None if self._td is None else self._td.to_dict(),
            "tracker": {
                "acc": {k: v.clone() for k, v in tr._acc.items()},
                "episodes_per_row": tr.episodes_per_row.clone(),
                "records": tr.records(),
            },
        }
        if _has_extra_state(self.policy):
            out["policy_extra"] = self.policy.get_extra_state()
        if self.safety is not None:
            out["safety"] = {"since_log": self.safety_stats.state_dict(), "run": self.safety_totals.state_dict()}
        return out

    def load_state_dict(self, state: Mapping[str, Any]) -> None:
        env = getattr(self.env, "base_env", self.env)
        self.frames = int(state["frames"])
        self.batches = int(state.get("batches", 0))
        self.generator.set_state(state["generator"])
        if state.get("env") is not None:
            env.load_sampler_state(state["env"])
        td = state.get("td")
        self._td = None if td is None else TensorDict(td, batch_size=self.env.batch_size, device=self.env.device)
        tr = state["tracker"]
        self.tracker._acc = {k: v.clone().to(self.tracker.device) for k, v in tr["acc"].items()}
        self.tracker.episodes_per_row = tr["episodes_per_row"].clone().to(self.tracker.device)
        recs = tr["records"]
        n = int(next(iter(recs.values())).numel()) if recs else 0
        self.tracker._chunks = [dict(recs)] if n else []
        if "policy_extra" in state and _has_extra_state(self.policy):
            self.policy.set_extra_state(state["policy_extra"])
        if state.get("safety") is not None:
            self.safety_stats.load_state_dict(state["safety"]["since_log"])
            self.safety_totals.load_state_dict(state["safety"]["run"])

    def shutdown(self) -> None:
        """Close the policy's advisor (its client and any local server it started)."""
        if isinstance(self.policy, OverridePolicy):
            self.policy.close()


def _gather(td: TensorDictBase, index: torch.Tensor, batch_size: torch.Size) -> TensorDict:
    """``td[index]`` for a 1-D integer ``index``: every leaf gathered with ``index_select``."""
    return TensorDict(
        {k: _gather(v, index, batch_size) if isinstance(v, TensorDictBase) else torch.index_select(v, 0, index)
         for k, v in td.items()},
        batch_size=batch_size, device=td.device,
    )


class UniformReplayBuffer(TensorDictReplayBuffer):
    """torchrl's ``TensorDictReplayBuffer`` whose plain ``sample()`` draws the indices with its
    own sampler and gathers the stored leaves directly, through the buffer's public ``sampler``
    and ``storage``. The result, ``"index"`` included, equals the stock sample exactly
    (``tests/test_collect.py``) at less than its cost per batch (docs/performance.md). With
    ``return_info``, another batch size, a transform, or storage other than a
    ``LazyTensorStorage`` holding one TensorDict, the stock ``sample()`` answers.

    Its ``state_dict()`` holds the stored rows only, not the storage's whole capacity: a
    buffer of 1M transitions filled to 1024 saves megabytes, not the 1.4 GB of its empty rows.
    ``load_state_dict()`` writes them back through ``extend`` and restores the sampling
    generator, so sampling continues exactly. A buffer that has wrapped around (full) saves
    torchrl's own state."""

    generator: torch.Generator | None = None  # the sampling generator (make_replay_buffer sets it)

    def _filled_only(self) -> bool:
        n = len(self)
        return 0 < n < self.storage.max_size and self._gather_ok() and self.generator is not None

    def state_dict(self) -> dict[str, Any]:
        if not self._filled_only():
            return super().state_dict()
        rows = self.storage.get(slice(0, len(self))).clone()  # a copy: a view would save the whole storage
        return {"filled_rows": rows.to_dict(), "n": len(rows), "generator": self.generator.get_state(),
                "batch_size": self.batch_size}

    def load_state_dict(self, state_dict: dict[str, Any]) -> None:
        if "filled_rows" not in state_dict:
            super().load_state_dict(state_dict)
            return
        if len(self) or self.generator is None:
            raise ValueError("a buffer's stored rows load into an empty buffer made by make_replay_buffer")
        rows = TensorDict(state_dict["filled_rows"], batch_size=[int(state_dict["n"])])
        self.extend(rows.exclude("index"))
        self.generator.set_state(state_dict["generator"])

    def _gather_ok(self) -> bool:
        storage = self.storage
        return (
            type(self.sampler) is RandomSampler
            and type(storage) is LazyTensorStorage
            and storage.ndim == 1
            and len(storage) > 0
            and (self.transform is None or len(self.transform) == 0)
        )

    def sample(self, batch_size: int | None = None, return_info: bool = False, include_info: bool | None = None) -> Any:
        if (return_info or include_info is not None or self.batch_size is None
                or batch_size not in (None, self.batch_size) or not self._gather_ok()):
            return super().sample(batch_size, return_info=return_info, include_info=include_info)
        index, _ = self.sampler.sample(self.storage, self.batch_size)
        stored = self.storage.get(slice(None))  # a view of the filled rows
        if not isinstance(stored, TensorDict):
            return super().sample(batch_size)
        data = _gather(stored, index.to(stored.device) if stored.device is not None else index,
                       torch.Size([self.batch_size]))
        data.set("index", index)
        return data


def make_replay_buffer(
    capacity: int,
    batch_size: int,
    device: torch.device | str = "cpu",
    storage: str = "lazy_tensor",
    *,
    seed: int | None = 0,
    scratch_dir: str | None = None,
) -> TensorDictReplayBuffer:
    """Uniform replay of single transitions.

    Extend it with ``batch.reshape(-1)`` (a collector batch ``[B, T]`` flattened to ``[B * T]``);
    ``sample()`` returns ``[batch_size]`` on ``device``. ``storage``: ``"lazy_tensor"`` (RAM or
    ``device`` memory) or ``"lazy_memmap"`` (memory-mapped files under ``scratch_dir``).
    ``seed`` seeds the buffer's own sampling generator (None: torch's global RNG), which its
    ``state_dict()`` saves with the data, the write cursor and the batch size.
    """
    if capacity < 1 or batch_size < 1:
        raise ValueError(f"replay capacity ({capacity}) and batch_size ({batch_size}) must be >= 1")
    if storage == "lazy_tensor":
        store = LazyTensorStorage(int(capacity), device=device)
    elif storage == "lazy_memmap":
        store = LazyMemmapStorage(int(capacity), device=device, scratch_dir=scratch_dir)
    else:
        raise ValueError(f"replay storage must be 'lazy_tensor' or 'lazy_memmap', got {storage!r}")
    generator = None
    if seed is not None:
        generator = torch.Generator()
        generator.manual_seed(int(seed))
    buffer = UniformReplayBuffer(storage=store, sampler=RandomSampler(), batch_size=int(batch_size), generator=generator)
    buffer.generator = generator
    return buffer


def flatten_batch(batch: TensorDictBase) -> TensorDictBase:
    """A collector batch ``[B, T]`` as ``[B * T]`` transitions for the replay buffer."""
    return batch.reshape(-1)


__all__ += ["flatten_batch"]
