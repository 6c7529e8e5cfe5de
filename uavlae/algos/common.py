"""Small pieces every learner shares: strict config base, config parsing, optimiser steps."""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from typing import Any, TypeVar

import torch
from pydantic import BaseModel
from tensordict import TensorDictBase

from uavlae.validation import StrictModel, parse_model

C = TypeVar("C", bound=BaseModel)


StrictConfig = StrictModel  # the learners' configs share the project's strict base


def parse_config(model: type[C], cfg: Any = None, **overrides: Any) -> C:
    """Validate ``cfg`` (None, a mapping, an OmegaConf node or ``model``) into ``model``.

    Raises ``ValueError`` naming every offending field with the value it got.
    """
    name = cfg.get("name", model.__name__) if hasattr(cfg, "get") else model.__name__
    return parse_model(model, cfg, prefix="algo", title=str(name), **overrides)


def adam(params: Iterable[torch.Tensor], lr: float) -> torch.optim.Adam:
    """Adam with the fused kernel: one call per step instead of a Python loop over tensors."""
    return torch.optim.Adam(list(params), lr=lr, fused=True)


def optimiser_step(
    optimisers: Mapping[str, torch.optim.Optimizer],
    loss: torch.Tensor,
    max_grad_norm: float | None,
) -> dict[str, torch.Tensor]:
    """One backward of ``loss`` and a step of every optimiser.

    The learners sum losses whose gradients touch disjoint parameter sets (torchrl detaches
    the critic in the actor loss and the actor in the critic target), so one backward equals
    separate ones. Gradients are clipped per parameter group (a group's ``"name"``, else the
    optimiser's name: one group per optimiser gives per-optimiser clipping); the pre-clip norms
    are returned.
    """
    for opt in optimisers.values():
        opt.zero_grad(set_to_none=True)
    loss.backward()
    return apply_gradients(optimisers, max_grad_norm)


def apply_gradients(
    optimisers: Mapping[str, torch.optim.Optimizer], max_grad_norm: float | None
) -> dict[str, torch.Tensor]:
    """Clip (per parameter group, see :func:`optimiser_step`) and step every optimiser on the
    gradients already in ``.grad``; returns the pre-clip norms."""
    norms = {}
    for name, opt in optimisers.items():
        if max_grad_norm is not None:
            for group in opt.param_groups:
                params = [p for p in group["params"] if p.grad is not None]
                if params:
                    key = f"grad_norm_{group.get('name', name)}"
                    norms[key] = torch.nn.utils.clip_grad_norm_(params, max_grad_norm)
        opt.step()
    return norms


def to_floats(values: Mapping[str, Any] | TensorDictBase, keys: Iterable[str] | None = None) -> dict[str, float]:
    """Scalar tensors -> plain floats for the logger (one ``.item()`` each)."""
    items = values.items() if keys is None else ((k, values[k]) for k in keys)
    out = {}
    for k, v in items:
        if isinstance(v, torch.Tensor):
            if v.numel() != 1:
                v = v.float().mean()
            out[str(k)] = float(v.detach().item())
        elif isinstance(v, (int, float)):
            out[str(k)] = float(v)
    return out


def parts_state_dict(parts: Mapping[str, Any], num_updates: int) -> dict[str, Any]:
    """A learner's checkpoint: ``state_dict()`` of each named part (a mapping of parts, e.g. the
    optimisers, becomes a mapping of state dicts) plus the update counter."""
    out: dict[str, Any] = {
        k: {n: o.state_dict() for n, o in v.items()} if isinstance(v, Mapping) else v.state_dict()
        for k, v in parts.items()
    }
    out["num_updates"] = num_updates
    return out


def load_parts_state_dict(parts: Mapping[str, Any], state: Mapping[str, Any]) -> int:
    """Restore what :func:`parts_state_dict` wrote, in place; returns the update counter.
    ``nn.Module.load_state_dict`` copies in place, so optimisers and target updaters keep
    pointing at the restored tensors."""
    for k, v in parts.items():
        if isinstance(v, Mapping):
            for n, o in v.items():
                o.load_state_dict(state[k][n])
        else:
            v.load_state_dict(state[k])
    return int(state["num_updates"])
