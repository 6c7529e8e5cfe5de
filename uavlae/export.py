"""Deployment export: the trained actor alone as a ``torch.export`` program (no torchrl at run time).

``python -m uavlae.export checkpoint=RUN_DIR_OR_FILE out=actor.pt2`` writes an exported
:class:`DeterministicActor` (observation ``[..., obs_dim]`` -> action ``[..., 2]`` in the action
box: the tanh of the Gaussian mean for SAC/PPO/CPO, the tanh of the output for DDPG, i.e. what
the actor does under ``ExplorationType.DETERMINISTIC``) with the env config embedded as
``meta.json``, so ``python -m uavlae.fly`` can rebuild the observation of the same world.
Load it anywhere with torch alone: :func:`uavlae.fly.load_actor`, or
``torch.export.load(path).module()(observation)``.

The file is written atomically (a temporary file, then a rename), so an interrupted export never
leaves a truncated actor where a good one was.
"""

from __future__ import annotations

import copy
import json
import sys
from pathlib import Path
from typing import Any

import hydra
import torch
from omegaconf import DictConfig, OmegaConf
from torch import nn

from uavlae.files import atomic_write
from uavlae.factories import package_versions, without_hydra_output


class DeterministicActor(nn.Module):
    """``obs -> low + (high - low) * (tanh(loc) + 1) / 2`` with ``loc`` the first ``act_dim``
    outputs of the network (for a tanh-normal head, the Gaussian mean)."""

    def __init__(self, net: nn.Module, low: torch.Tensor, high: torch.Tensor):
        super().__init__()
        self.net = net
        self.act_dim = int(low.numel())
        self.register_buffer("low", low.detach().clone().float())
        self.register_buffer("high", high.detach().clone().float())

    def forward(self, observation: torch.Tensor) -> torch.Tensor:
        loc = self.net(observation)[..., : self.act_dim]
        return self.low + (self.high - self.low) * (torch.tanh(loc) + 1.0) * 0.5


def _first_module(td_module: Any) -> nn.Module:
    """The plain network of a torchrl actor: ProbabilisticActor -> MLP(+NormalParamExtractor),
    TensorDictSequential(param, TanhModule) -> MLP."""
    mod = td_module
    while True:
        if hasattr(mod, "module") and isinstance(mod.module, nn.Module) and not isinstance(mod.module, nn.ModuleList):
            mod = mod.module
            continue
        if hasattr(mod, "module") and isinstance(mod.module, nn.ModuleList):
            mod = mod.module[0]
            continue
        break
    if isinstance(mod, nn.Sequential):
        # drop the NormalParamExtractor: the mean is the first half of the MLP's output
        mod = mod[0]
    return mod


def deterministic_actor_module(learner: Any, action_spec: Any) -> DeterministicActor:
    """A plain ``nn.Module`` copy of ``learner.actor``'s deterministic action."""
    from uavlae.policies.networks import action_bounds

    box = action_bounds(action_spec)
    net = copy.deepcopy(_first_module(learner.actor)).cpu().eval()
    return DeterministicActor(net, box.space.low.cpu(), box.space.high.cpu()).eval()


def export_actor(learner: Any, action_spec: Any, path: str | Path, meta: dict[str, Any]) -> Path:
    """Export the deterministic actor with ``torch.export`` and save it with ``meta`` (env config,
    versions) inside. The batch dimension is dynamic: any ``[N, obs_dim]`` observation works."""
    module = deterministic_actor_module(learner, action_spec)
    example = torch.zeros(2, int(meta["obs_dim"]))
    batch = torch.export.Dim("batch", min=1)
    with torch.no_grad():
        program = torch.export.export(module, (example,), dynamic_shapes={"observation": {0: batch}})
    return atomic_write(path, lambda fh: torch.export.save(program, fh, extra_files={"meta.json": json.dumps(meta)}))


def export_checkpoint(checkpoint: str | Path, out: str | Path) -> Path:
    from uavlae.checkpoint import load_checkpoint
    from uavlae.envs import make_env_config
    from uavlae.factories import make_env, make_learner

    state, file = load_checkpoint(checkpoint)
    saved = OmegaConf.create(state["config"])
    env_cfg = make_env_config(saved.env)
    env = make_env(env_cfg, 1, seed=0)
    learner = make_learner(saved.algo, env)
    learner.load_state_dict(state["learner"])
    meta = {
        "env": env_cfg.model_dump(mode="json"),
        "algo": saved.algo.name,
        "name": saved.name,
        "frames": int(state["counters"]["frames"]),
        "checkpoint": str(file),
        "obs_dim": int(env.observation_spec["observation"].shape[-1]),
        "versions": package_versions(),
    }
    return export_actor(learner, env.action_spec, out, meta)


@hydra.main(config_path="conf", config_name="config", version_base="1.3")
def main(cfg: DictConfig) -> None:
    if not cfg.checkpoint or not cfg.get("out"):
        raise SystemExit("usage: python -m uavlae.export checkpoint=RUN_DIR_OR_FILE out=actor.pt2")
    print(export_checkpoint(cfg.checkpoint, cfg.out))


if __name__ == "__main__":
    sys.argv = without_hydra_output(sys.argv)
    main()
