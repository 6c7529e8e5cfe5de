"""The LLM alone (docs/model.md §8, paper §6.1 "LLM"): the LLM decides every step of every episode.

``python -m uavlae.train +exp=llm`` flies the fixed evaluation set with an
:class:`~uavlae.policies.override.OverridePolicy` in ``mode="always"``. A full evaluation is
tens of thousands of LLM calls, so it runs in *chunks* of scenarios (``trainer.eval_chunk``;
default: the whole set at once) under a *call budget* (``trainer.llm_call_budget``) and
resumes where it left off:

- Each step sends every still-flying row of the chunk to the advisor at once (one call per
  row). A row whose episode has ended is stepped on as
  :func:`uavlae.envs.metrics.rollout_metrics` does (its output ignored) but is never asked
  again (``OverridePolicy.row_mask``), so the episodes and their metrics are that evaluator's,
  without paying for the rows already done.
- After every step the progress (finished chunks' records and trajectories; the chunk in
  flight: its tensordict, the env's generator, the episode tracker, the per-row counters;
  the policy's counters; the accumulated wall clock) is written atomically to
  ``progress.pt`` in the evaluation folder. A killed run, or one whose budget ran out,
  continues from there when the same command is run again; finished episodes are never
  flown again. Ctrl-C (SIGINT) pauses at the last saved slot and still writes the results. The
  file remembers the config it belongs to: another config is an error.
- The budget counts LLM decisions (rows asked) in one invocation; a step is never split,
  so the run pauses before the first step that would go past it.
- Only the episodes of finished chunks are scored (a chunk is a fixed part of the set, so the
  score is that of a subset of scenarios, not biased toward short episodes); ``complete`` says
  whether every chunk is done, ``episodes_scored`` how many episodes the metrics cover.
- Shards (``trainer.eval_shards=S trainer.eval_shard=s``): S processes fly one evaluation
  side by side, each with its own LLM server, into the same folder. Shard ``s`` takes the chunks
  ``k`` with ``k % S == s`` and keeps its progress in ``progress.shard<s>of<S>.pt``; every
  process skips a chunk that another progress file of the folder has finished or holds in
  flight, and scores the union of the finished chunks of every file. So a sweep over
  ``trainer.eval_shard=0,1`` runs on both cores of a small machine or as an array of cluster
  jobs, and whichever process writes last writes every episode finished by then. A chunk left in
  flight by a shard count no longer run is finished by that count's command, not taken over.
- ``trainer.llm_call_budget=0`` asks nothing: it writes the metrics of what the progress files
  hold (after the shards have stopped, the union of all of them).

Chunk ``k`` seeds its env with ``seed + k``, whoever flies it: with one chunk the evaluation is
exactly the :class:`~uavlae.evaluate.Evaluator`'s. The cost of the LLM (calls, HTTP requests,
tokens, failures, wall clock, calls/s) comes back beside the metrics, summed over every
invocation and every shard (the wall clock too: the time one process would have taken).
"""

from __future__ import annotations

import io
import json
import logging
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import torch
from tensordict import TensorDict
from torchrl.envs.utils import ExplorationType, set_exploration_type, step_mdp

from uavlae.envs import UAVEnv, make_env_config
from uavlae.envs.metrics import EpisodeTracker, aggregate, concat_records, save_aggregates, save_records
from uavlae.envs.scenario import Scenario
from uavlae.errors import InputError
from uavlae.files import atomic_write
from uavlae.lifecycle import config_differences
from uavlae.policies.override import FALLBACK

log = logging.getLogger(__name__)

PROGRESS = "progress.pt"
FORMAT_VERSION = 2  # 2: chunks kept by index (shards finish them out of order); 1 is read and upgraded
# the per-episode LLM columns added to episodes.csv
LLM_COLUMNS = ("llm_calls", "llm_fallbacks")


def _own_extra_state(policy: Any) -> bool:
    """Whether ``policy`` keeps state through ``get_extra_state`` (``OverridePolicy`` does; a
    plain ``nn.Module``'s default refuses to be called)."""
    get = getattr(type(policy), "get_extra_state", None)
    return get is not None and get is not getattr(torch.nn.Module, "get_extra_state", None)


class LLMAloneEvaluation:
    """The evaluation set flown chunk by chunk under a call budget, resumable (module docstring).

    Args:
        env_cfg: the world.
        scenarios: the evaluation set.
        policy: the acting module (an ``OverridePolicy`` in ``mode="always"``; anything that
            writes ``"action"`` works, e.g. the heuristic: then nothing is counted as a fallback).
        out_dir: where ``episodes.csv``, ``metrics.json``, the trajectory PNGs and
            ``progress.pt`` go.
        seed: chunk ``k``'s env is seeded with ``seed + k``.
        chunk: scenarios flown together (``None``: all of them).
        max_steps: step budget per episode (``None``: ``env_cfg.t_max``).
        budget: LLM decisions this invocation may ask (``None``: no limit; 0: none, only score
            what the progress files hold).
        fingerprint: what identifies the run (its config); a progress file of another one is
            an error.
        n_plots: trajectories drawn at the end.
        device: where the env runs.
        shard, shards: this process flies the chunks ``k`` with ``k % shards == shard``.
        stop: called before every step; True pauses the flight there as a spent budget does
            (SIGTERM, SIGINT: the same command continues).
    """

    def __init__(
        self,
        env_cfg: Any,
        scenarios: list[Scenario],
        policy: Any,
        out_dir: str | Path,
        *,
        seed: int,
        chunk: int | None = None,
        max_steps: int | None = None,
        budget: int | None = None,
        fingerprint: Mapping[str, Any] | None = None,
        n_plots: int = 3,
        device: str | torch.device = "cpu",
        shard: int = 0,
        shards: int = 1,
        stop: Any = None,
    ):
        self.env_cfg = make_env_config(env_cfg)
        self.scenarios = list(scenarios)
        if not self.scenarios:
            raise ValueError("the LLM-alone evaluation needs at least one scenario")
        self.policy = policy
        self.out = Path(out_dir)
        self.seed = int(seed)
        self.chunk = len(self.scenarios) if chunk is None else min(int(chunk), len(self.scenarios))
        if self.chunk < 1:
            raise ValueError(f"trainer.eval_chunk must be >= 1, got {chunk!r}")
        self.max_steps = int(max_steps if max_steps is not None else self.env_cfg.t_max)
        if budget is not None and 0 < int(budget) < self.chunk:
            raise ValueError(
                f"trainer.llm_call_budget={budget} is below the {self.chunk} rows a step of a chunk asks "
                "(trainer.eval_chunk): no step would fit; raise the budget or lower the chunk"
            )
        self.budget = None if budget is None else int(budget)
        self.fingerprint = json.loads(json.dumps(dict(fingerprint or {}), default=str))
        self.n_plots = int(n_plots)
        self.device = torch.device(device)
        self.n_chunks = -(-len(self.scenarios) // self.chunk)
        self.shard, self.shards = int(shard), int(shards)
        self.stop = stop
        if self.shards < 1 or not 0 <= self.shard < self.shards:
            raise ValueError(f"trainer.eval_shard={shard} must be in [0, trainer.eval_shards={shards})")
        self.own_chunks = [k for k in range(self.n_chunks) if k % self.shards == self.shard]
        self.asked = 0  # LLM decisions asked in this invocation (the budget's counter)

    # ------------------------------------------------------------------ progress files
    @property
    def progress_file(self) -> Path:
        return self.out / (PROGRESS if self.shards == 1 else f"progress.shard{self.shard}of{self.shards}.pt")

    def _read(self, path: Path) -> dict[str, Any]:
        """A progress file, checked against this run's config and upgraded to the current format."""
        state = torch.load(path, map_location="cpu", weights_only=False)
        if state.get("version") not in (1, FORMAT_VERSION):
            raise InputError(f"{path}: progress format {state.get('version')}, expected {FORMAT_VERSION}")
        if state["fingerprint"] != self.fingerprint or state["chunk"] != self.chunk:
            # settings the file lacks were added to the code after it was written: no difference
            changed, _ = config_differences({**self.fingerprint, "eval_chunk": self.chunk},
                                            {**state["fingerprint"], "eval_chunk": state["chunk"]})
            if changed:
                raise InputError(
                    f"{path} holds the progress of another config (differs in {changed[:8]}); "
                    "remove it or pick another run_dir"
                )
        if state["version"] == 1:  # chunks 0 .. next_chunk - 1 in order, their episodes' paths in one list
            sizes = [len(r["row"]) for r in state["records"]]
            flat, trajs = list(state.pop("trajectories")), []
            for n in sizes:
                trajs.append(flat[:n])
                flat = flat[n:]
            k = state.pop("next_chunk")
            state.update(version=FORMAT_VERSION, done=list(range(k)), trajectories=trajs, totals=None)
            if state["in_flight"] is not None:
                state["in_flight"]["chunk"] = k
        return state

    def _load(self) -> dict[str, Any]:
        if not self.progress_file.is_file():
            return {"version": FORMAT_VERSION, "fingerprint": self.fingerprint, "chunk": self.chunk,
                    "done": [], "records": [], "trajectories": [], "in_flight": None, "policy": None,
                    "totals": None, "wall_s": 0.0, "invocations": 0}
        return self._read(self.progress_file)

    def _others(self) -> list[dict[str, Any]]:
        """The progress of the other shards (and shard counts) in the folder."""
        own = self.progress_file.name
        return [self._read(p) for p in sorted(self.out.glob("progress*.pt")) if p.name != own]

    def _next_chunk(self, state: dict[str, Any]) -> int | None:
        """This process's chunk in flight, else its first chunk no progress file has finished or
        holds in flight; None when it has none left."""
        if state["in_flight"] is not None:
            return int(state["in_flight"]["chunk"])
        taken = set(state["done"])
        for other in self._others():
            taken.update(other["done"])
            if other["in_flight"] is not None:
                taken.add(int(other["in_flight"]["chunk"]))
        return next((k for k in self.own_chunks if k not in taken), None)

    def _save(self, state: dict[str, Any]) -> None:
        state["totals"] = self._totals()  # what the other shards read of this one's cost
        buf = io.BytesIO()
        torch.save(state, buf)
        atomic_write(self.progress_file, lambda fh: fh.write(buf.getvalue()))

    def _policy_state(self) -> Any:
        snapshot = getattr(self.policy, "snapshot", None)
        if snapshot is not None:
            snapshot(reset=True)  # the advisor's window into the run's totals, which travel below
        if _own_extra_state(self.policy):
            return self.policy.get_extra_state()
        cache = getattr(self.policy, "cache_state", None)  # a bare heuristic: its per-row memory
        return {"cache": cache()} if cache is not None else None

    def _totals(self) -> dict[str, float]:
        totals = self.policy.run_totals() if hasattr(self.policy, "run_totals") else {}
        return {k: float(v) for k, v in totals.items() if isinstance(v, (int, float))}

    def _load_policy_state(self, state: Any) -> None:
        if state is None:
            return
        if _own_extra_state(self.policy):
            self.policy.set_extra_state(state)
        elif "cache" in state and hasattr(self.policy, "load_cache_state"):
            self.policy.load_cache_state(state["cache"])

    # ------------------------------------------------------------------ the run
    def run(self) -> dict[str, Any]:
        """Fly until every chunk is done or the budget is spent; returns :meth:`result`."""
        state = self._load()
        self._load_policy_state(state["policy"])
        state["invocations"] += 1
        t0, wall0 = time.perf_counter(), float(state["wall_s"])
        paused = False
        try:
            with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
                while not paused and (k := self._next_chunk(state)) is not None:
                    paused = not self._fly_chunk(state, k, lambda: wall0 + time.perf_counter() - t0)
        except KeyboardInterrupt:  # Ctrl-C / SIGINT: a pause at the last saved slot
            if not self.progress_file.is_file():
                raise
            log.warning("interrupted: the progress of the last finished slot is kept; the same command continues")
            state = self._read(self.progress_file)
            self._load_policy_state(state["policy"])
            return self.result(state)
        state["wall_s"] = wall0 + time.perf_counter() - t0
        state["policy"] = self._policy_state()
        self._save(state)
        return self.result(state)

    def _fly_chunk(self, state: dict[str, Any], k: int, wall: Any) -> bool:
        """Fly chunk ``k`` on from where it stands; False if the budget ran out."""
        scen = self.scenarios[k * self.chunk:(k + 1) * self.chunk]
        b = len(scen)
        env = UAVEnv(self.env_cfg, batch_size=b, device=self.device, seed=self.seed + k, scenarios=scen)
        tracker = EpisodeTracker(b, self.env_cfg, max_episodes_per_row=1, device=self.device)
        fl = state["in_flight"]
        if fl is None:
            env.set_seed(self.seed + k)
            td = env.reset()
            zeros = torch.zeros(b, dtype=torch.int64, device=self.device)
            fl = {"chunk": k, "step": 0, "finished": torch.zeros(b, dtype=torch.bool, device=self.device), "length": zeros.clone(),
                  "llm_calls": zeros.clone(), "llm_fallbacks": zeros.clone(),
                  "positions": [td.get(("state", "position")).reshape(b, 2).clone()]}
        else:
            env.load_sampler_state(fl["env"])
            tracker.load_state_dict(fl["tracker"])
            td = TensorDict(fl["td"], batch_size=[b], device=self.device)
            log.info("chunk %d/%d: resuming at step %d", k + 1, self.n_chunks, fl["step"])
        nxt = fl.get("last_next")
        while fl["step"] < self.max_steps and not bool(fl["finished"].all()):
            active = (~fl["finished"]).nonzero().squeeze(-1)
            if self.budget is not None and self.asked + active.numel() > self.budget:
                log.info("call budget of %d spent: chunk %d/%d paused at step %d", self.budget, k + 1, self.n_chunks,
                         fl["step"])
                return False
            if self.stop is not None and self.stop():  # a stop pauses as the budget does: at this saved step
                log.info("stopped: chunk %d/%d paused at step %d", k + 1, self.n_chunks, fl["step"])
                return False
            if hasattr(self.policy, "row_mask"):  # the rows whose episode ended are not asked
                self.policy.row_mask = ~fl["finished"]
            td = self.policy(td)  # the whole chunk: the actor's per-row memory stays aligned
            self.asked += int(active.numel())
            fl["llm_calls"][active] += 1
            if "action_source" in td.keys():
                fl["llm_fallbacks"] += ((td.get("action_source").reshape(-1) == FALLBACK) & ~fl["finished"]).long()
            td = env.step(td)
            nxt = td.get("next")
            fl["positions"].append(nxt.get(("state", "position")).reshape(b, 2).clone())
            fl["length"] += (~fl["finished"]).long()
            going = ~fl["finished"]  # the data each GE holds as a row's episode ends: its picture's
            fl.setdefault("ge_left", nxt.get(("state", "ge_remaining")).clone())[going] = \
                nxt.get(("state", "ge_remaining"))[going]
            fl["finished"] = fl["finished"] | tracker.update(nxt)
            fl["step"] += 1
            td = step_mdp(td, keep_other=True)  # finished rows go on without a reset: first episodes only
            fl.update(td=td.to_dict(), env=env.sampler_state(), tracker=tracker.state_dict(), last_next=nxt.clone())
            state["in_flight"] = fl
            state["wall_s"] = wall()
            state["policy"] = self._policy_state()
            self._save(state)
        if nxt is not None and not bool(fl["finished"].all()):
            tracker.flush_unfinished(nxt)
        records = tracker.records()
        records = {key: v[torch.argsort(records["row"])] for key, v in records.items()}
        records["row"] = records["row"] + k * self.chunk  # the scenario's index in the whole set
        for c in LLM_COLUMNS:
            records[c] = fl[c].clone()
        traj = torch.stack(fl["positions"], 0).cpu()
        state["records"].append({key: v.cpu() for key, v in records.items()})
        state["trajectories"].append([traj[: int(n) + 1, i] for i, n in enumerate(fl["length"].tolist())])
        state["done"].append(k)
        state.setdefault("ge_left", {})[k] = fl.get("ge_left")  # by chunk: files of the first formats lack it
        state["in_flight"] = None
        state["wall_s"] = wall()
        state["policy"] = self._policy_state()
        self._save(state)
        log.info("chunk %d/%d done: %d episodes", k + 1, self.n_chunks, b)
        return True

    # ------------------------------------------------------------------ what it gives
    def result(self, state: dict[str, Any]) -> dict[str, Any]:
        """``metrics`` over the episodes of the chunks finished in any progress file of the
        folder (NaN with none), ``complete``, ``episodes_scored`` / ``episodes_total``,
        ``cost`` (every file's) and ``records``; ``in_flight_step`` is this process's."""
        states = [state, *self._others()]
        chunks: dict[int, tuple[dict, list]] = {}
        for st in states:
            for k, rec, traj in zip(st["done"], st["records"], st["trajectories"]):
                chunks.setdefault(int(k), (rec, traj))  # a chunk two processes raced for counts once
        order = sorted(chunks)
        parts = [chunks[k][0] for k in order]
        records = concat_records(parts) if parts else {}
        if parts:
            for c in LLM_COLUMNS:
                records[c] = torch.cat([r[c] for r in parts])
        agg = aggregate(records) if parts else aggregate([])
        calls_scored = int(records["llm_calls"].sum()) if parts else 0
        in_flight = state["in_flight"]
        calls_in_flight = sum(int(st["in_flight"]["llm_calls"].sum()) for st in states if st["in_flight"] is not None)
        trajectories = [(k * self.chunk + i, t) for k in order for i, t in enumerate(chunks[k][1])]
        ge_left = {k: v for st in states for k, v in (st.get("ge_left") or {}).items() if v is not None}
        return {"metrics": agg, "complete": len(order) >= self.n_chunks,
                "episodes_scored": int(agg["n_episodes"]), "episodes_total": len(self.scenarios),
                "chunks_done": len(order), "chunks": self.n_chunks,
                "in_flight_step": None if in_flight is None else int(in_flight["step"]),
                "cost": self.cost(states, calls_scored, calls_in_flight), "records": records,
                "trajectories": trajectories, "ge_left": ge_left, "invocations": int(state["invocations"]),
                "shard": self.shard, "shards": self.shards, "progress_files": len(states)}

    def cost(self, states: list[dict[str, Any]], calls_scored: int, calls_in_flight: int) -> dict[str, float]:
        """What the LLM cost over every invocation of every progress file (``states[0]`` is this
        process's, whose policy counts it live): ``calls`` (decisions asked, one per flying row
        and step: ``calls_scored`` in the scored episodes plus ``calls_in_flight`` in the chunks
        in flight), the advisor's HTTP requests, cache hits, ask-again attempts, failures
        (answered by the fallback), prompt and completion tokens, the latency quantiles (the
        largest over the files), the wall clock (summed over the files: one process's time) and
        calls per second of it."""
        every = [self._totals(), *(st.get("totals") or {} for st in states[1:])]
        wall = sum(float(st["wall_s"]) for st in states)
        calls = calls_scored + calls_in_flight
        out = {"calls": calls, "calls_scored": calls_scored, "calls_in_flight": calls_in_flight,
               "wall_s": wall, "calls_per_s": calls / wall if wall > 0 else float("nan"),
               "fallbacks": int(sum(t.get("source/fallback", 0) for t in every)),
               "invocations": int(sum(st["invocations"] for st in states))}
        for k in ("calls", "requests", "cache_hits", "ask_again", "failures", "retries", "prompt_tokens",
                  "completion_tokens", "latency_p50_s", "latency_p95_s"):
            vs = [t[f"advisor/{k}"] for t in every if f"advisor/{k}" in t]
            if vs:
                out["http_calls" if k == "calls" else k] = float(max(vs) if k.startswith("latency") else sum(vs))
        return out

    def write(self, result: Mapping[str, Any], title: str = "") -> None:
        """``episodes.csv`` and ``metrics.json`` of the scored episodes, and the first PNGs."""
        if result["records"]:
            save_records(result["records"], self.out / "episodes.csv")
        save_aggregates(dict(result["metrics"]), self.out / "metrics.json")
        from uavlae.envs.render import draw_scenario, episode_outcome

        records = result["records"]
        at = {int(r): j for j, r in enumerate(records["row"].tolist())} if records else {}
        for i, traj in result["trajectories"][: self.n_plots]:
            outcome = f": {episode_outcome({k: v[at[i]] for k, v in records.items()})}" if i in at else ""
            left = result.get("ge_left", {}).get(i // self.chunk)
            draw_scenario(self.scenarios[i], [traj], path=self.out / f"trajectory_{i}.png",
                          title=f"{title} scenario {i}{outcome}".strip(), cfg=self.env_cfg,
                          ge_left=None if left is None else left[i % self.chunk])
