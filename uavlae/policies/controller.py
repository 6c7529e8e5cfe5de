"""The shared shell of the rule-based controllers (the greedy heuristic, the global planner):
read the raw state entries, compute a velocity, write it as an action in [-1, 1]^2."""

from __future__ import annotations

from collections.abc import Mapping

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torch import Tensor


class StateController(TensorDictModuleBase):
    """A controller of the raw ``("state", ...)`` entries: subclasses set ``state_keys`` (and
    ``in_keys`` from them), ``env_cfg``, and implement ``_velocity(s) -> [B, 2]`` in m/s."""

    state_keys: tuple[str, ...] = ()
    out_keys = ["action"]

    @torch.no_grad()
    def act(self, state: Mapping[str, Tensor] | TensorDictBase) -> Tensor:
        """Action ``[B, 2]`` in [-1, 1] from the raw state entries (``[B, ...]`` or unbatched)."""
        s = {k: state[k] for k in self.state_keys}
        unbatched = s["position"].dim() == 1
        if unbatched:
            s = {k: v.unsqueeze(0) for k, v in s.items()}
        v = self._velocity(s)
        action = (v / self.env_cfg.motion.v_max).clamp(-1.0, 1.0)
        return action.squeeze(0) if unbatched else action

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        tensordict.set("action", self.act(tensordict.get("state")))
        return tensordict

    def _velocity(self, s: dict[str, Tensor]) -> Tensor:
        raise NotImplementedError
