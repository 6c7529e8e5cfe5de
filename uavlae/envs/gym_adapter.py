"""``UAVGymEnv``: the same world, one scenario at a time, behind the gymnasium API.

It calls :func:`uavlae.envs.world.initial_state` and :func:`~uavlae.envs.world.world_step`
at batch 1 with the same :class:`~uavlae.envs.world.ObservationLayout` as
:class:`~uavlae.envs.uav_env.UAVEnv`; it does not go through TorchRL. With the same
scenario, seed and actions it reproduces ``UAVEnv(batch_size=[1])`` step for step, which makes
it the honest "one scenario per call" reference of the throughput benchmark.

Registered as ``"uavlae/UAV-v0"`` when the package is imported (:func:`uavlae.register_gym`), so
``gymnasium.make("uavlae:uavlae/UAV-v0")`` finds it in a fresh interpreter.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import gymnasium as gym
import numpy as np
import torch
from gymnasium import spaces
from tensordict import TensorDictBase

from uavlae import GYM_ID, register_gym
from uavlae.envs.config import EnvConfig, make_env_config
from uavlae.envs.world import EVENT_KEYS, REWARD_KEYS, ObservationLayout, initial_state, world_step

__all__ = ["GYM_ID", "UAVGymEnv", "register_gym"]


def _scenario_dict(scenario: Any, cfg: EnvConfig) -> dict[str, torch.Tensor]:
    """A ``Scenario`` / scenario TensorDict ([1] or []) / dict as batch-1 CPU tensors."""
    if not isinstance(scenario, (TensorDictBase, Mapping)):
        from uavlae.envs.scenario import stack_scenarios

        scenario = stack_scenarios([scenario], cfg)
    if isinstance(scenario, TensorDictBase):
        if scenario.batch_dims == 0:
            scenario = scenario.unsqueeze(0)
        if scenario.batch_size[0] != 1:
            raise ValueError(f"UAVGymEnv takes one scenario, got a batch of {scenario.batch_size[0]}")
        return {k: v.to("cpu") for k, v in scenario.to_dict().items()}
    out = {k: torch.as_tensor(v) for k, v in scenario.items()}
    if out["start"].ndim == 1:  # one unbatched scenario: add the batch dim
        out = {k: v.unsqueeze(0) for k, v in out.items()}
    return out


class UAVGymEnv(gym.Env):
    """One scenario of the paper's world per episode; numpy float32 in and out.

    Args:
        cfg: an :class:`EnvConfig`, mapping or OmegaConf node (``None``: docs/model.md defaults).
        scenario: a fixed ``Scenario`` for every reset; ``None`` samples a new one per reset
            (from the env's generator, like ``UAVEnv``).
        render_mode: ``None`` or ``"rgb_array"``.

    ``reset(seed=s, options={"scenario": sc})`` plays ``sc`` for that episode. ``step`` returns
    ``(obs, reward, terminated, truncated, info)``; ``info`` holds ``events`` (bools),
    ``reward_terms`` (floats), ``cost`` and ``state`` (the raw state as numpy, batch dim removed).
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": 4}

    def __init__(self, cfg: EnvConfig | Mapping | Any = None, scenario: Any = None, render_mode: str | None = None):
        super().__init__()
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise ValueError(f"render_mode must be one of {self.metadata['render_modes']} or None, got {render_mode!r}")
        self.cfg = make_env_config(cfg)
        self.render_mode = render_mode
        self.layout = ObservationLayout(self.cfg)
        self.observation_space = spaces.Box(-np.inf, np.inf, shape=(self.layout.size,), dtype=np.float32)
        self.action_space = spaces.Box(-1.0, 1.0, shape=(2,), dtype=np.float32)
        self._fixed = None if scenario is None else _scenario_dict(scenario, self.cfg)
        self.rng = torch.Generator(device="cpu")
        self._rng_seeded = False
        self._pool: TensorDictBase | None = None
        self._pool_pos = 0
        self.state: dict[str, torch.Tensor] | None = None
        self.scenario: dict[str, torch.Tensor] | None = None
        self._path: list[np.ndarray] = []

    # ------------------------------------------------------------------ helpers
    def _obs(self) -> np.ndarray:
        return self.layout.build(self.state)[0].numpy().astype(np.float32, copy=False)

    def _state_np(self) -> dict[str, np.ndarray]:
        return {k: v[0].numpy().copy() for k, v in self.state.items()}

    def _seed_rng(self, seed: int) -> None:
        self.rng.manual_seed(seed)
        self._rng_seeded = True
        self._pool, self._pool_pos = None, 0  # a new seed starts a new scenario stream

    def _draw(self) -> dict[str, torch.Tensor]:
        """The next sampled scenario, drawn exactly as ``UAVEnv`` at batch 1 draws it.

        ``UAVEnv`` samples ``cfg.sampling.pool_size`` scenarios at a time from its generator
        (0: one per reset) and hands them out in order; the same here, so the generator's
        stream (which also moves the OUs) stays in step with ``UAVEnv``'s.
        """
        from uavlae.envs.scenario import sample_scenarios

        size = self.cfg.sampling.pool_size
        if size == 0:
            return sample_scenarios(self.cfg, 1, self.rng, device="cpu").to_dict()
        if self._pool is None or self._pool_pos >= self._pool.batch_size[0]:
            self._pool, self._pool_pos = sample_scenarios(self.cfg, size, self.rng, device="cpu"), 0
        out = self._pool[self._pool_pos : self._pool_pos + 1]
        self._pool_pos += 1
        return out.to_dict()

    # ------------------------------------------------------------------ gymnasium API
    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        super().reset(seed=seed)
        if seed is not None:
            self._seed_rng(int(seed))  # the same stream as UAVEnv(seed=seed)
        elif not self._rng_seeded:
            self._seed_rng(int(self.np_random.integers(0, 2**63 - 1)))
        options = options or {}
        if options.get("scenario") is not None:
            scen = _scenario_dict(options["scenario"], self.cfg)
        elif self._fixed is not None:
            scen = self._fixed
        else:
            scen = self._draw()
        self.scenario = scen
        with torch.no_grad():
            self.state = initial_state(scen, self.cfg)
        self._path = [self.state["position"][0].numpy().copy()]
        info = {
            "events": {k: False for k in EVENT_KEYS},
            "reward_terms": {k: 0.0 for k in REWARD_KEYS},
            "cost": 0.0,
            "state": self._state_np(),
        }
        return self._obs(), info

    def step(self, action):
        if self.state is None:
            raise RuntimeError("call reset() before step()")
        a = torch.as_tensor(np.asarray(action, dtype=np.float32).reshape(1, 2))
        with torch.no_grad():
            nxt, events, terms, cost, terminated, truncated = world_step(self.state, a, self.cfg, self.rng)
            reward = torch.stack(list(terms.values()), dim=0).sum(0)  # the same sum as UAVEnv
        self.state = nxt
        self._path.append(nxt["position"][0].numpy().copy())
        info = {
            "events": {k: bool(v[0]) for k, v in events.items()},
            "reward_terms": {k: float(v[0]) for k, v in terms.items()},
            "cost": float(cost[0]),
            "state": self._state_np(),
        }
        return self._obs(), float(reward[0]), bool(terminated[0]), bool(truncated[0]), info

    def render(self):
        if self.render_mode != "rgb_array" or self.state is None:
            return None
        from uavlae.envs.render import draw_scenario, figure_to_rgb

        fig = draw_scenario(self.state, trajectories=[np.stack(self._path)], cfg=self.cfg,
                            figsize=(5.0, 5.0), dpi=60)
        return figure_to_rgb(fig)
