"""``UAVEnv``: the batched data-collection world as a TorchRL ``EnvBase``.

The physics is :func:`uavlae.envs.world.world_step`; this class only declares the specs and
moves the raw state between the tensordict and that function. The state lives in the
tensordict under ``("state", NAME)`` (docs/env_contract.md), so a rollout carries it step to
step and a partial reset only touches the rows it names.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Bounded, Categorical, Composite, Unbounded
from torchrl.envs import EnvBase

from uavlae.envs.config import EnvConfig, make_env_config
from uavlae.envs.scenario import Scenario, sample_scenarios, stack_scenarios
from uavlae.envs.world import (
    EVENT_KEYS,
    REWARD_KEYS,
    ObservationLayout,
    draw_noise,
    initial_state,
    state_keys,
    state_shapes,
    world_step_core,
)


class UAVEnv(EnvBase):
    """Many independent scenarios of the paper's world, stepped at once.

    Args:
        cfg: an :class:`EnvConfig`, a mapping or an OmegaConf node (validated); ``None`` gives
            docs/model.md's defaults.
        batch_size: ``[B]``, the number of scenarios stepped together.
        device: where the tensors live.
        seed: seeds the env's own ``torch.Generator`` (scenario sampling, OU motion, ties).
        scenarios: optional fixed scenarios (a list of :class:`Scenario`, or a batched scenario
            TensorDict); batch row ``i`` is always reset to scenario ``i % len(scenarios)``.
        compile_step: run the step (``world_step_core``, reward sum and observation) through
            ``torch.compile`` (Inductor, static shapes), chosen once here. The first step pays a
            one-off compile, once per process, batch size and device (Inductor's on-disk cache
            shortens later ones); worth it for long collection runs, not for tests or short
            evaluations (docs/performance.md). Events, flags and integer state equal the eager
            ones exactly; floats may differ in the last bit (Inductor's fused float32 math).
            Not TorchRL's own ``compile=`` keyword: EnvBase's metaclass takes that one and
            compiles the whole ``step_and_maybe_reset``, resets included, which recompiles on
            every partial reset (the scenario pool's counters are Python ints).
    """

    batch_locked = True

    def __init__(
        self,
        cfg: EnvConfig | dict | Any = None,
        *,
        batch_size: Sequence[int] | torch.Size | int = (1,),
        device: torch.device | str = "cpu",
        seed: int | None = None,
        scenarios: Sequence[Scenario] | TensorDictBase | None = None,
        compile_step: bool = False,
    ):
        self.cfg = make_env_config(cfg)
        if isinstance(batch_size, int):
            batch_size = (batch_size,)
        batch_size = torch.Size(batch_size)
        if len(batch_size) != 1 or batch_size[0] < 1:
            raise ValueError(f"UAVEnv needs a one-dimensional batch_size [B] with B >= 1, got {list(batch_size)}")
        super().__init__(device=device, batch_size=batch_size)
        self.layout = ObservationLayout(self.cfg)
        self.raw_state_keys = state_keys(self.cfg)
        self.compiled = bool(compile_step)
        self._core = self._make_core(self.compiled)
        self._fixed: TensorDictBase | None = None
        self._pool: TensorDictBase | None = None
        self._pool_pos = 0
        if scenarios is not None:
            self.set_scenarios(scenarios)
        self._make_specs()
        if seed is None:
            seed = int(torch.empty((), dtype=torch.int64).random_().item())
        self.set_seed(seed)

    # ------------------------------------------------------------------ set-up
    def set_scenarios(self, scenarios: Sequence[Scenario] | TensorDictBase | None) -> None:
        """Reset to these scenarios from now on (``None``: sample again)."""
        if scenarios is None:
            self._fixed = None
            return
        if isinstance(scenarios, TensorDictBase):
            td = scenarios
        else:
            scenarios = list(scenarios)
            if not scenarios:
                raise ValueError("scenarios must contain at least one Scenario")
            td = stack_scenarios(scenarios, self.cfg)
        self._fixed = td.to(self.device)

    def _make_specs(self) -> None:
        b = self.batch_size
        B = b[0]
        f = torch.float32

        def u(*shape, dtype=f):
            return Unbounded(shape=(B, *shape), dtype=dtype, device=self.device)

        def flag(*shape):
            return Categorical(2, shape=(B, *shape), dtype=torch.bool, device=self.device)

        state = {}
        for key, (shape, dtype) in state_shapes(self.cfg).items():
            state[key] = flag(*shape) if dtype == torch.bool else u(*shape, dtype=dtype)
        self.observation_spec = Composite(
            observation=u(self.layout.size),
            state=Composite(state, shape=b, device=self.device),
            reward_terms=Composite({n: u(1) for n in REWARD_KEYS}, shape=b, device=self.device),
            events=Composite({n: flag(1) for n in EVENT_KEYS}, shape=b, device=self.device),
            cost=u(1),
            shape=b,
            device=self.device,
        )
        self.action_spec = Bounded(-1.0, 1.0, shape=(B, 2), dtype=f, device=self.device)
        self.reward_spec = u(1)
        self.done_spec = Composite(
            done=flag(1), terminated=flag(1), truncated=flag(1), shape=b, device=self.device
        )

    def _make_core(self, compile: bool = False):
        cfg, layout = self.cfg, self.layout

        def core(state, action, noise):
            nxt, events, terms, cost, terminated, truncated = world_step_core(state, action, noise, cfg)
            reward = torch.stack(list(terms.values()), dim=0).sum(0)
            # the [B, 1] entries of the output, made here (inside the compiled graph, when compiled)
            col = {k: e.unsqueeze(-1) for k, e in events.items()}
            col_terms = {k: r.unsqueeze(-1) for k, r in terms.items()}
            flags = tuple(f.unsqueeze(-1) for f in (terminated | truncated, terminated, truncated))
            return nxt, col, col_terms, cost.unsqueeze(-1), reward.unsqueeze(-1), flags, layout.build(nxt)

        if not compile:
            return core
        # Only tensors (dicts of them) go in; cfg and layout are closed over, so the guards are
        # on constants and the same compiled graph serves every step (no recompiles).
        return torch.compile(core, dynamic=False, fullgraph=True)

    def _set_seed(self, seed: int | None) -> None:
        rng = torch.Generator(device=self.device)
        rng.manual_seed(int(seed) if seed is not None else 0)
        self.rng = rng
        self._pool, self._pool_pos = None, 0  # a new seed starts a new scenario stream

    def sampler_state(self) -> dict[str, Any]:
        """The env's random state for an exact resume: its generator and scenario pool (plain
        tensors and dicts, loadable with ``torch.load(weights_only=True)``)."""
        pool = self._pool
        return {
            "rng": self.rng.get_state(),
            "pool": None if pool is None else pool.to_dict(),
            "pool_batch": None if pool is None else list(pool.batch_size),
            "pool_pos": self._pool_pos,
        }

    def load_sampler_state(self, state: dict[str, Any]) -> None:
        self.rng.set_state(state["rng"])
        pool = state["pool"]
        self._pool = None if pool is None else TensorDict(pool, batch_size=state["pool_batch"], device=self.device)
        self._pool_pos = int(state["pool_pos"])

    # ------------------------------------------------------------------ data in / out
    def _scenarios_for(self, rows: torch.Tensor | None) -> tuple[TensorDictBase, torch.Tensor | None]:
        """The scenarios to reset to, and for each of the B rows the index of its scenario
        (``None``: one scenario per row, in order). Only the fresh ones are built, so a partial
        reset of a few rows costs a few rows, plus one gather."""
        B = self.batch_size[0]
        if self._fixed is not None:
            return self._fixed, torch.arange(B, device=self.device) % self._fixed.batch_size[0]
        n = int(rows.sum().item()) if rows is not None else B
        fresh = self._draw(max(n, 1))
        if n == B:
            return fresh, None
        return fresh, (torch.cumsum(rows.long(), 0) - 1).clamp(min=0)

    def _draw(self, n: int) -> TensorDictBase:
        """``n`` fresh scenarios, taken in order from a pool refilled ``pool_size`` at a time."""
        if self.cfg.sampling.pool_size == 0:
            return sample_scenarios(self.cfg, n, self.rng, device=self.device)
        start = self._take(n)
        return self._pool[start : start + n]

    def _take(self, n: int) -> int:
        """Hands out the next ``n`` pool entries (refilling the pool first if it holds fewer):
        returns the index of the first one in ``self._pool``."""
        size = self.cfg.sampling.pool_size
        have = 0 if self._pool is None else self._pool.batch_size[0] - self._pool_pos
        if have < n:
            fresh = sample_scenarios(self.cfg, max(size, n - have), self.rng, device=self.device)
            rest = self._pool[self._pool_pos:] if have else None
            self._pool = fresh if rest is None else torch.cat([rest, fresh], 0)
            self._pool_pos = 0
        start = self._pool_pos
        self._pool_pos += n
        return start

    def _output(
        self,
        state: dict[str, torch.Tensor],
        events: dict[str, torch.Tensor],
        terms: dict[str, torch.Tensor],
        cost: torch.Tensor,
        reward: torch.Tensor,
        flags: tuple[torch.Tensor, torch.Tensor, torch.Tensor],
        obs: torch.Tensor | None = None,
    ) -> TensorDict:
        """The output tensordict; events, terms, cost, reward and the (done, terminated,
        truncated) flags come already shaped ``[B, 1]``."""
        b = state["position"].shape[:1]
        done, terminated, truncated = flags
        return TensorDict(
            {
                "observation": self.layout.build(state) if obs is None else obs,
                "state": TensorDict(state, batch_size=b),
                "reward_terms": TensorDict(terms, batch_size=b),
                "events": TensorDict(events, batch_size=b),
                "cost": cost,
                "reward": reward,
                "done": done,
                "terminated": terminated,
                "truncated": truncated,
            },
            batch_size=b,
            device=self.device,
        )

    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs: Any) -> TensorDictBase:
        rows = None
        if tensordict is not None and "_reset" in tensordict.keys():
            rows = tensordict.get("_reset").reshape(self.batch_size)
            if bool(rows.all()):
                rows = None
        scen, pos = self._scenarios_for(rows)
        state = initial_state(scen.to_dict(), self.cfg)
        n = scen.batch_size[0]
        zf = torch.zeros(n, 1, device=self.device)
        zb = torch.zeros(n, 1, device=self.device, dtype=torch.bool)
        out = self._output(
            state, {k: zb for k in EVENT_KEYS}, {k: zf for k in REWARD_KEYS}, zf, zf, (zb, zb, zb)
        )
        del out["reward"]
        return out if pos is None else out[pos]

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        nxt, events, terms, cost, reward, flags, obs = self._core(*self._core_inputs(tensordict))
        return self._output(nxt, events, terms, cost, reward, flags, obs)

    def _core_inputs(self, tensordict: TensorDictBase) -> tuple[dict, torch.Tensor, dict]:
        """What the step's core takes for this root: its raw state, its action and the slot's
        random draws (which advance the env's generator)."""
        st = dict(tensordict.get("state").items())
        missing = [k for k in self.raw_state_keys if k not in st]
        if missing:
            raise KeyError(f"UAVEnv.step: the input has no ('state', key) for {missing}: "
                           "step a root that reset() or step() made")
        state = {k: st[k] for k in self.raw_state_keys}
        action = tensordict.get("action")
        return state, action, draw_noise(state, self.cfg, self.rng)
