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
from tensordict import NestedKey, TensorDict, TensorDictBase
from torchrl.data import Bounded, Categorical, Composite, Unbounded
from torchrl.envs import EnvBase

from uavlae.envs import ckernels
from uavlae.envs.config import EnvConfig, make_env_config
from uavlae.envs.geodesic import grid_shape
from uavlae.envs.scenario import Scenario, sample_scenarios, stack_scenarios
from uavlae.envs.world import (
    EVENT_KEYS,
    REWARD_KEYS,
    GEO_KEY,
    ObservationLayout,
    draw_noise,
    initial_state,
    state_keys,
    world_step_core,
)

_BOOL_STATE = {"nfz_mask", "rz_mask", "bz_mask", "ge_mask", "ou_mask"}
_INT_STATE = {"step", "served_ge"}


def _inductor_options(device: torch.device) -> dict[str, Any]:
    """Inductor settings for the compiled step. On an x86 CPU with AVX2, ``cpp.simdlen: 8`` and
    capping fusion at 8 nodes per kernel made the compiled step about 25% faster than Inductor's
    defaults (benchmarks/env_throughput.py, B = 4096, one thread). Inductor reads ``simdlen`` as
    a bit width (256 or 512), so 8 matches no instruction set and it emits scalar C++ loops:
    with the step's tiny entity dimensions (2, 4, 7, 15) innermost, those beat its vectorised
    loops (with ``simdlen: 512`` the compiled ``world_step_core`` took 11.4 ms instead of 7.0 ms
    at B = 4096 on an AVX-512 Intel Xeon, the OU step 7.3 instead of 3.1). ``cpp_wrapper`` calls the
    kernels from generated C++ instead of Python: x1.16 at B = 1, x1.08 at B = 64, no change at
    B = 4096 (per-call overhead). Elsewhere: the defaults."""
    if device.type != "cpu":
        return {}
    from torch._inductor import cpu_vec_isa

    isa = str(cpu_vec_isa.pick_vec_isa())
    if not isa.startswith("avx"):
        return {}
    return {"cpp.simdlen": 8, "max_fusion_size": 8, "cpp_wrapper": True}


class _FlatStepMDP:
    """TorchRL's ``_StepMDP`` (the root for the next step) for roots of plain TensorDicts of
    tensors at most two levels deep, as this env's are: the same entries (the same tensor
    objects), batch sizes and devices, built from the same key trees of the generic object,
    without its per-entry dispatch: 80 instead of 455 us per call (scratch timing; the compiled
    B = 1 call was 1.1 ms).
    Anything else (lazy stacks, non-tensor data, names, deeper nesting, or key trees of another
    shape) takes the generic object."""

    def __init__(self, generic):
        self.generic = generic
        self.exclude = generic.exclude_from_root  # {key: None (drop) or {sub: ...}}
        self.take = generic.keys_from_next  # {key: None (a leaf) or {sub: None}}
        self.flat = all(v is None for v in self.exclude.values()) and all(
            v is None or all(w is None for w in v.values()) for v in self.take.values()
        )

    def __call__(self, td: TensorDictBase) -> TensorDictBase:
        out = self._build(td) if self.flat and type(td) is TensorDict else None
        return self.generic(td) if out is None else out

    def _build(self, td: TensorDict) -> TensorDict | None:
        nxt = td._get_str("next", None)
        if type(nxt) is not TensorDict or td._has_names():
            return None
        # in _StepMDP's key order: the root's entries, then those of "next" not in the root;
        # a nested entry is [its entries, batch size, device] until the end
        out: dict[str, Any] = {}
        for key, value in td.items():
            if key in self.exclude:
                continue
            if type(value) is TensorDict:  # a shallow copy, as _StepMDP's value.copy()
                entries = dict(value.items())
                if value._has_names() or not all(isinstance(v, torch.Tensor) for v in entries.values()):
                    return None
                out[key] = [entries, value.batch_size, value.device]
            elif isinstance(value, torch.Tensor):
                out[key] = value
            else:
                return None
        for key, leaves in self.take.items():
            value = nxt._get_str(key, None)
            if value is None:
                continue  # absent keys are allowed, as in _StepMDP
            if leaves is None:
                if not isinstance(value, torch.Tensor):
                    return None
                out[key] = value
                continue
            if type(value) is not TensorDict or value._has_names():
                return None
            have = out.get(key)
            if not isinstance(have, list) or have[1] != value.batch_size:
                have = out[key] = [{}, value.batch_size, value.device]
            for leaf in leaves:
                x = value._get_str(leaf, None)
                if x is not None:
                    if not isinstance(x, torch.Tensor):
                        return None
                    have[0][leaf] = x
        new = TensorDict._new_unsafe
        for key, value in out.items():
            if isinstance(value, list):
                out[key] = new(value[0], batch_size=value[1], device=value[2])
        return new(out, batch_size=td.batch_size, device=td.device)


class UAVEnv(EnvBase):
    """Many independent scenarios of the paper's world, stepped at once.

    Args:
        cfg: an :class:`EnvConfig`, a mapping or an OmegaConf node (validated); ``None`` gives
            SPEC.md's defaults.
        batch_size: ``[B]``, the number of scenarios stepped together.
        device: where the tensors live.
        seed: seeds the env's own ``torch.Generator`` (scenario sampling, OU motion, ties).
        scenarios: optional fixed scenarios (a list of :class:`Scenario`, or a batched scenario
            TensorDict); batch row ``i`` is always reset to scenario ``i % len(scenarios)``.
        compile_step: run the step (``world_step_core``, reward sum and observation) through
            ``torch.compile`` (Inductor, static shapes). Off by default. The first step pays a
            one-off compile of about 20-30 s on a small CPU, once per process, batch size and
            device (Inductor's on-disk cache makes later runs take about 10 s); after that the
            whole TorchRL ``step_and_maybe_reset``, partial resets included, is about 1.7x
            faster on CPU at B = 1024-4096 and about 3x at B = 64 (one thread; see
            ``benchmarks/env_throughput.py --compile``). Worth it for long collection runs,
            not for tests or short evaluations. On CPU, the OU step and the GE service run
            inside the graph as small C kernels (:mod:`uavlae.envs.ckernels`, built once with
            the C compiler, split over OpenMP threads). Every CPU env, compiled or not, also
            draws its random numbers through the C replay of torch's generator (the same
            numbers) and runs the scenario sampler's occupancy grid, flood fill and
            candidate scans in C (the same scenarios). Events, flags
            and integer state equal the eager ones exactly; floats may differ in the last bit
            (Inductor's fused float32 math, ``cosf``/``log2f``).
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
        if self.device.type == "cpu":
            # the C kernels (built once; without them torch's code, with a warning): the random
            # draws and the scenario sampler's grid, flood and scans of every CPU env, the OU step and the GE
            # service of the compiled step
            ckernels.load()
        self._core = self._make_core(self.compiled)
        self._fixed: TensorDictBase | None = None
        self._pool: TensorDictBase | None = None
        self._pool_pos = 0
        self._init_cache: dict[NestedKey, torch.Tensor] = {}
        self._init_cache_of: TensorDictBase | None = None
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
        g, k = self.layout.n_ge, self.layout.n_ou
        n_nfz, n_rz, n_bz = self.layout.n_zone
        f = torch.float32

        def u(*shape, dtype=f):
            return Unbounded(shape=(B, *shape), dtype=dtype, device=self.device)

        def flag(*shape):
            return Categorical(2, shape=(B, *shape), dtype=torch.bool, device=self.device)

        shapes: dict[str, tuple[int, ...]] = {
            "nfz": (n_nfz, 4), "nfz_mask": (n_nfz,), "rz": (n_rz, 4), "rz_mask": (n_rz,),
            "bz": (n_bz, 4), "bz_mask": (n_bz,), "ge_pos": (g, 2), "ge_mask": (g,),
            "takeoff": (4,), "landing": (4,), "data_total": (), "position": (2,), "velocity": (2,),
            "energy_used": (), "energy_left": (), "slot_data": (), "data_collected": (),
            "step": (), "ge_remaining": (g,), "ou_pos": (k, 2), "ou_vel": (k, 2),
            "ou_mask": (k,), "served_ge": (), "d_bz": (), "d_nfz": (), "d_rz": (), "d_ou": (),
            "d_boundary": (), "d_la": (),
        }
        if GEO_KEY in self.raw_state_keys:
            h, w = grid_shape(self.cfg)
            shapes[GEO_KEY] = (g + 1, h * w)
        assert set(shapes) == set(self.raw_state_keys)
        state = {}
        for key in self.raw_state_keys:
            if key in _BOOL_STATE:
                state[key] = flag(*shapes[key])
            elif key in _INT_STATE:
                state[key] = u(*shapes[key], dtype=torch.int64)
            else:
                state[key] = u(*shapes[key])
        self.observation_spec = Composite(
            observation=u(self.layout.size),
            state=Composite(state, shape=b, device=self.device),
            reward_terms=Composite({n: u(1) for n in REWARD_KEYS}, shape=b, device=self.device),
            events=Composite({n: flag(1) for n in EVENT_KEYS}, shape=b, device=self.device),
            cost=u(1),
            shape=b,
            device=self.device,
        )
        # what a root coming from step_mdp must hold for maybe_reset's row-wise path
        self._reset_keys_expected = {"observation", *(("state", k) for k in self.raw_state_keys)}
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
        # on constants and the same compiled graph serves every step (no recompiles). The step is
        # one graph: on CPU the OU heading retries run on the compacted blocked OUs inside it
        # (physics._retry_headings_compacted), elsewhere in their dense form.
        return torch.compile(core, dynamic=False, fullgraph=True, options=_inductor_options(self.device))

    @property
    def _step_mdp(self):
        """TorchRL's step_mdp for this env's roots, without its per-entry dispatch (_FlatStepMDP)."""
        generic = EnvBase._step_mdp.fget(self)  # cached by TorchRL while the specs are locked
        fast = self.__dict__.get("_flat_step_mdp")
        if fast is None or fast.generic is not generic:
            fast = self.__dict__["_flat_step_mdp"] = _FlatStepMDP(generic)
        return fast

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

    def _initial_rows(self, scen: TensorDictBase) -> dict[NestedKey, torch.Tensor]:
        """The root entries that a reset writes for these scenarios and that are not all zero
        (``observation`` and every ``("state", k)``), one row per scenario."""
        state = initial_state(scen.to_dict(), self.cfg)
        rows: dict[NestedKey, torch.Tensor] = {"observation": self.layout.build(state)}
        rows.update({("state", k): state[k] for k in self.raw_state_keys})
        return rows

    def _cached_initial_rows(self, scen: TensorDictBase) -> dict[NestedKey, torch.Tensor]:
        """``_initial_rows`` of the whole scenario pool (or of the fixed scenarios), computed once
        per pool: a partial reset then only slices it."""
        if self._init_cache_of is not scen:
            self._init_cache = self._initial_rows(scen)
            self._init_cache_of = scen
        return self._init_cache

    def _fresh_rows(self, n: int, idx: torch.Tensor) -> dict[NestedKey, torch.Tensor]:
        """The fresh root entries of the ``n`` rows ``idx`` that a partial reset starts again,
        drawn in the same order as ``_reset`` draws them."""
        if self._fixed is not None:
            init = self._cached_initial_rows(self._fixed)
            which = idx % self._fixed.batch_size[0]
            return {k: v[which] for k, v in init.items()}
        if self.cfg.sampling.pool_size == 0:
            return self._initial_rows(sample_scenarios(self.cfg, n, self.rng, device=self.device))
        start = self._take(n)
        init = self._cached_initial_rows(self._pool)
        return {k: v[start : start + n] for k, v in init.items()}

    def maybe_reset(self, tensordict: TensorDictBase) -> TensorDictBase:
        """``EnvBase.maybe_reset`` for a root coming from ``step_mdp``: the done rows start a
        fresh scenario, the other rows are untouched; the same result as TorchRL's generic path
        (``reset`` of the done rows, then a ``where`` per entry), written with one out-of-place
        ``index_put``/``index_fill`` per entry on the done rows only, and the tensordict built
        directly (``TensorDict.apply`` and its per-entry checks cost more than the copies at
        B = 4096). Every returned tensor is new: the transition's ``"next"`` entries, which the
        root shares, keep the terminal data. Anything out of the ordinary (no ``done``, every
        row done, a root that is not a plain ``TensorDict`` of tensors at most two levels deep,
        or missing one of the env's entries) takes TorchRL's generic path."""
        done = tensordict.get("done", None) if type(tensordict) is TensorDict else None
        if done is None or done.shape != (*self.batch_size, 1):
            return super().maybe_reset(tensordict)
        rows = done.reshape(self.batch_size)
        n = int(rows.sum())
        if n == 0:
            return tensordict
        if n == self.batch_size[0]:
            return super().maybe_reset(tensordict)
        items = list(tensordict.items(True, True))
        if not self._reset_keys_expected <= {k for k, _ in items} or any(
            not isinstance(v, torch.Tensor) or (isinstance(k, tuple) and len(k) > 2) for k, v in items
        ):
            return super().maybe_reset(tensordict)  # not the flat two-level layout of tensors built below
        idx = rows.nonzero().squeeze(-1)
        fresh = self._fresh_rows(n, idx)
        b, new = self.batch_size, TensorDict._new_unsafe  # ours: skip re-validation
        top: dict[str, Any] = {}
        for key, value in items:
            if key == "_reset":
                continue
            rows_new = fresh.get(key)
            if rows_new is None:  # TorchRL pads what the reset does not produce with zeros
                value = value.index_fill(0, idx, 0)
            else:
                value = value.index_put((idx,), rows_new)
            if isinstance(key, tuple) and len(key) == 2:
                top.setdefault(key[0], {})[key[1]] = value
            else:
                top[key if isinstance(key, str) else key[0]] = value
        return new(
            {k: new(v, batch_size=b, device=self.device) if isinstance(v, dict) else v for k, v in top.items()},
            batch_size=b, device=self.device,
        )

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
        b, new = state["position"].shape[:1], TensorDict._new_unsafe  # ours: skip re-validation
        done, terminated, truncated = flags
        return new(
            {
                "observation": self.layout.build(state) if obs is None else obs,
                "state": new(state, batch_size=b),
                "reward_terms": new(terms, batch_size=b),
                "events": new(events, batch_size=b),
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
        st = dict(tensordict.get("state").items())  # one pass: TensorDict.get costs ~1.5 us a key
        missing = [k for k in self.raw_state_keys if k not in st]
        if missing:
            raise KeyError(f"UAVEnv.step: the input has no ('state', key) for {missing}: "
                           "step a root that reset() or step() made")
        state = {k: st[k] for k in self.raw_state_keys}
        action = tensordict.get("action")
        noise = draw_noise(state, self.cfg, self.rng)
        if self.compiled and self.device.type == "cpu":
            # ATen's vectorised cos/sin of the [B, K] new headings (0.04 ms at B = 4096), not the
            # compiled step's scalar ones (0.46 ms): the step's C++ is scalar (_inductor_options)
            noise["heading_cos"], noise["heading_sin"] = torch.cos(noise["heading"]), torch.sin(noise["heading"])
        return state, action, noise
