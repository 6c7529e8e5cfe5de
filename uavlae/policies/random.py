"""The uniform-random controller: the floor a learner must beat to count as having learned.

Every row draws its action uniformly in the env's action box, from a generator of its own
(``seed``), so the global RNGs are untouched and a seed gives the same actions every time.
"""

from __future__ import annotations

from typing import Any

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase


class UniformRandomPolicy(TensorDictModuleBase):
    """Writes ``"action"``: uniform in ``[low, high]`` of ``action_spec``, whatever it observes."""

    in_keys: list = []
    out_keys = ["action"]

    def __init__(self, action_spec: Any, seed: int):
        super().__init__()
        self.low = action_spec.space.low
        self.high = action_spec.space.high
        self.generator = torch.Generator().manual_seed(int(seed))

    def forward(self, td: TensorDictBase) -> TensorDictBase:
        shape = (*td.batch_size, *self.low.shape[-1:])
        u = torch.rand(shape, generator=self.generator).to(self.low.device)
        td.set("action", self.low + (self.high - self.low) * u)
        return td
