"""The noise of a sampled flight, with torch alone (``uavlae.fly`` imports it without torchrl).

A tanh-normal actor's draw is ``low + (high - low) · (tanh(loc + scale · ε) + 1) / 2`` with
ε ~ N(0, I); ε = 0 gives its mean action. The evaluator (:class:`uavlae.policies.sampling.SampledActor`)
and ``uavlae.fly`` draw ε from the same seeded stream, one ``[rows, act_dim]`` block a step, so
the exported pilot reproduces the evaluator's flight.
"""

from __future__ import annotations

import torch
from torch import Tensor


def squash(loc: Tensor, scale: Tensor, noise: Tensor, low: Tensor, high: Tensor) -> Tensor:
    """The tanh-normal action of ``loc``, ``scale`` and a standard-normal ``noise`` on the box [low, high]."""
    return low + (high - low) * (torch.tanh(loc + scale * noise) + 1.0) * 0.5


def noise_stream(seed: int) -> torch.Generator:
    """The generator of a sampled flight's noise, started at ``seed``."""
    return torch.Generator().manual_seed(int(seed))


def draw(generator: torch.Generator, rows: int, act_dim: int) -> Tensor:
    """One step's noise: ``[rows, act_dim]`` standard normals from ``generator`` (on the CPU)."""
    return torch.randn(rows, act_dim, generator=generator)
