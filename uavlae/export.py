"""Deployment export: the trained actor alone as a ``torch.export`` program (no torchrl at run time).

``python -m uavlae.export checkpoint=RUN_DIR_OR_FILE out=actor.pt2`` writes an exported
:class:`DeterministicActor` (observation ``[..., obs_dim]`` -> action ``[..., 2]`` in the action
box: the tanh of the Gaussian mean for SAC/PPO/CPO, the tanh of the output for DDPG, i.e. what
the actor does under ``ExplorationType.DETERMINISTIC``) with the env config embedded as
``meta.json``, so ``python -m uavlae.fly`` can rebuild the observation of the same world. A run
trained through the safety filter exports its pilot instead (:class:`Pilot`: the actor and the
filter in one program, with a noise input so that a recipe that flies draws from its policy,
``trainer.eval_actor=sample``, is reproduced by ``uavlae.fly`` from the same seeded stream).
Load it anywhere with torch alone: :func:`uavlae.fly.load_actor`, or
``torch.export.load(path).module()(observation)``.

The file is written atomically (a temporary file, then a rename), so an interrupted export never
leaves a truncated actor where a good one was.
"""

from __future__ import annotations

import copy
import json
from pathlib import Path
from typing import Any

import hydra
import torch
from omegaconf import DictConfig, OmegaConf
from torch import nn
from torchrl.modules import ProbabilisticActor

from uavlae.checkpoint import load_checkpoint
from uavlae.envs import make_env_config
from uavlae.envs.scenario import sample_scenarios
from uavlae.envs.world import ObservationLayout, initial_state, nearest_distances
from uavlae.errors import ConfigError
from uavlae.factories import make_env, make_learner, make_safety_filter, make_safety_filter_config
from uavlae.files import atomic_write, portable
from uavlae.policies.draws import squash
from uavlae.policies.sampling import eval_actor
from uavlae.runlog import package_versions, without_hydra_output


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


def actor_box(learner: Any, action_spec: Any) -> Any:
    """The box the learner's actor acts in: its own (``algo.action_scale`` widens SAC's) where it
    declares one, else the env's (``action_spec``)."""
    from torchrl.data import Bounded

    from uavlae.policies.networks import action_bounds

    spec = getattr(learner.actor, "spec", None)
    space = spec["action"] if spec is not None and "action" in spec.keys() else None
    return action_bounds(space if isinstance(space, Bounded) else action_spec)


def deterministic_actor_module(learner: Any, action_spec: Any) -> DeterministicActor:
    """A plain ``nn.Module`` copy of ``learner.actor``'s deterministic action."""
    box = actor_box(learner, action_spec)
    net = copy.deepcopy(_first_module(learner.actor)).cpu().eval()
    return DeterministicActor(net, box.space.low.cpu(), box.space.high.cpu()).eval()


def _save(program: Any, meta: dict[str, Any], path: str | Path) -> Path:
    """Write ``program`` with ``meta`` inside. The program is a file that travels (a committed
    pilot): the source locations torch.export records with each node name this machine's
    folders, so they are dropped; they play no part in running it."""
    for module in program.graph_module.modules():
        if isinstance(module, torch.fx.GraphModule):
            for node in module.graph.nodes:
                node.meta.pop("stack_trace", None)
    return atomic_write(path, lambda fh: torch.export.save(program, fh, extra_files={"meta.json": json.dumps(meta)}))


def export_actor(learner: Any, action_spec: Any, path: str | Path, meta: dict[str, Any]) -> Path:
    """Export the deterministic actor with ``torch.export`` and save it with ``meta`` (env config,
    versions) inside. The batch dimension is dynamic: any ``[N, obs_dim]`` observation works."""
    module = deterministic_actor_module(learner, action_spec)
    example = torch.zeros(2, int(meta["obs_dim"]))
    batch = torch.export.Dim("batch", min=1)
    with torch.no_grad():
        program = torch.export.export(module, (example,), dynamic_shapes={"observation": {0: batch}})
    return _save(program, meta, path)


# The raw state a pilot is given (docs/env_contract.md), less the nearest-distance entries it
# computes itself: what the DCU knows of its world, with the OUs beyond the perception radius masked.
PILOT_STATE_KEYS = (
    "nfz", "nfz_mask", "rz", "rz_mask", "bz", "bz_mask", "ge_pos", "ge_mask", "takeoff", "landing", "data_total",
    "position", "velocity", "energy_used", "energy_left", "slot_data", "data_collected", "step", "ge_remaining",
    "ou_pos", "ou_vel", "ou_mask", "served_ge",
)


class NoisyActor(nn.Module):
    """``(obs, noise) -> action``: a tanh-normal actor's draw for a given standard-normal ``noise``
    (:func:`uavlae.policies.draws.squash`; zero noise is its mean action), or a deterministic
    actor's action, which ignores the noise."""

    def __init__(self, learner: Any, action_spec: Any):
        super().__init__()
        box = actor_box(learner, action_spec)
        self.act_dim = int(box.space.low.numel())
        self.stochastic = isinstance(learner.actor, ProbabilisticActor)
        if self.stochastic:  # the head's TensorDictModule: obs -> (loc, scale)
            self.net = copy.deepcopy(learner.actor.module[0].module).cpu().eval()
        else:
            self.net = deterministic_actor_module(learner, action_spec)
        self.register_buffer("low", box.space.low.detach().clone().float().cpu())
        self.register_buffer("high", box.space.high.detach().clone().float().cpu())

    def forward(self, observation: torch.Tensor, noise: torch.Tensor) -> torch.Tensor:
        if not self.stochastic:
            return self.net(observation)
        loc, scale = self.net(observation)
        return squash(loc, scale, noise, self.low, self.high)


class Pilot(nn.Module):
    """The deployed pilot: ``(state, use_filter, noise) -> action``. It builds the observation from
    the raw state (the env's own :class:`~uavlae.envs.world.ObservationLayout`), lets the actor act
    (``noise``, ``[B, act_dim]`` standard normals, draws from its policy; zeros give its mean
    action: meta ``actor`` says which the recipe flies) and passes the action through the safety
    filter where ``use_filter`` (a bool tensor) holds: both are computed, so the program has no
    data-dependent branch."""

    def __init__(self, actor: NoisyActor, env_cfg: Any, safety: Any):
        super().__init__()
        self.actor = actor
        self.safety = safety
        self.env_cfg = env_cfg
        self.layout = ObservationLayout(env_cfg)

    def forward(self, state: dict[str, torch.Tensor], use_filter: torch.Tensor, noise: torch.Tensor) -> torch.Tensor:
        s = dict(state)
        s.update(nearest_distances(s, self.env_cfg))
        action = self.actor(self.layout.build(s), noise)
        filtered, _, _ = self.safety.filter_action(s, action)
        return torch.where(use_filter, filtered, action)


def export_pilot(learner: Any, action_spec: Any, env_cfg: Any, safety: Any, path: str | Path,
                 meta: dict[str, Any]) -> Path:
    """Export the actor and its safety filter as one :class:`Pilot` program (any batch size)."""
    actor = NoisyActor(learner, action_spec).eval()
    module = Pilot(actor, env_cfg, safety).eval()
    scen = sample_scenarios(env_cfg, 2, torch.Generator().manual_seed(0))
    example = {k: v for k, v in initial_state(scen.to_dict(), env_cfg).items() if k in PILOT_STATE_KEYS}
    batch = torch.export.Dim("batch", min=1)
    dynamic = {"state": {k: {0: batch} for k in example}, "use_filter": None, "noise": {0: batch}}
    with torch.no_grad():
        program = torch.export.export(module, (example, torch.tensor(True), torch.zeros(2, actor.act_dim)),
                                      dynamic_shapes=dynamic)
    return _save(program, {**meta, "noise_dim": actor.act_dim}, path)


def export_checkpoint(checkpoint: str | Path, out: str | Path, safety_cfg: Any = None,
                      actor_mode: str | None = None) -> Path:
    """Export a checkpoint's actor: with a safety filter (``safety_cfg``, else the run's own
    ``safety_filter``; mode not ``off``) as a :class:`Pilot`, else the actor alone (its mean
    action). A pilot's meta records how its actor flies (``actor_mode``, else the run's
    ``trainer.eval_actor``) and the seed of the noise stream ``uavlae.fly`` draws for it."""
    state, file = load_checkpoint(checkpoint)
    saved = OmegaConf.create(state["config"])
    env_cfg = make_env_config(saved.env)
    env = make_env(env_cfg, 1, seed=0)
    learner = make_learner(saved.algo, env)
    learner.load_state_dict(state["learner"])
    safety_cfg = saved.get("safety_filter") if safety_cfg is None else safety_cfg
    safety = make_safety_filter(safety_cfg, env_cfg)
    meta = {
        "kind": "actor" if safety is None else "pilot",
        "env": env_cfg.model_dump(mode="json"),
        "algo": saved.algo.name,
        "name": saved.name,
        "frames": int(state["counters"]["frames"]),
        "checkpoint": portable(str(file), Path.cwd()),
        "obs_dim": int(env.observation_spec["observation"].shape[-1]),
        # the evaluator's OU random stream, so `uavlae.fly --all` reproduces its numbers
        "eval_seed": int(saved.trainer.eval_seed),
        "eval_max_steps": saved.trainer.get("eval_max_steps"),
        "versions": package_versions(),
    }
    if safety is None:
        return export_actor(learner, env.action_spec, out, meta)
    meta["safety_filter"] = make_safety_filter_config(safety_cfg).model_dump(mode="json")
    mode = str(actor_mode or OmegaConf.select(saved, "trainer.eval_actor", default="mean"))
    # the evaluator's own check: an unknown mode, or draws from a deterministic actor, are refused
    # in the words a training run would use
    eval_actor(learner.actor, mode, int(saved.trainer.eval_seed))
    meta["actor"] = mode
    meta["noise_seed"] = int(saved.trainer.eval_seed)
    if env_cfg.ego_features and env_cfg.reward.progress_metric == "geodesic":
        raise ConfigError("a pilot reads only what the DCU perceives: env.ego_features with "
                         "reward.progress_metric=geodesic reads a planner's distance field (a training-only aid)")
    return export_pilot(learner, env.action_spec, env_cfg, safety, out, meta)


@hydra.main(config_path="conf", config_name="config", version_base="1.3")
def main(cfg: DictConfig) -> None:
    from hydra.core.hydra_config import HydraConfig

    from uavlae.entry import refused_in_job

    with refused_in_job():
        if not cfg.checkpoint or not cfg.get("out"):
            raise ConfigError("checkpoint= and out= are both needed; usage: python -m uavlae.export "
                              "checkpoint=RUN_DIR_OR_FILE out=actor.pt2 [safety_filter.mode=deploy]")
        task = [o.split("=", 1)[0].lstrip("+~") for o in HydraConfig.get().overrides.task]
        named = any(k.startswith("safety_filter") for k in task)
        mode = str(cfg.trainer.eval_actor) if "trainer.eval_actor" in task else None
        print(export_checkpoint(cfg.checkpoint, cfg.out, cfg.safety_filter if named else None, mode))


if __name__ == "__main__":
    import sys

    from uavlae.entry import command
    sys.argv = without_hydra_output(sys.argv)
    command(main)
