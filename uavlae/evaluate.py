"""Evaluation on a fixed, seeded set of scenarios (SPEC.md §5; paper §6.2); no training code.

The evaluation set is sampled once with ``trainer.eval_seed`` and saved as JSON
(``<run_dir>/eval_set.json``, or ``trainer.eval_set``), then reloaded, so every evaluation of a
run (and of every method compared on it) flies the same scenarios. A learner is evaluated by
its actor alone, deterministically (``ExplorationType.DETERMINISTIC``: the tanh of the mean; no
LLM, no heuristic, as in deployment). Each evaluation writes the per-episode records
(``episodes.csv``), the aggregates (``metrics.json``: DCR, CR, SLR, RVR, ECR, the mean of every
reward term, ...) and a PNG of the first few trajectories.

``python -m uavlae.evaluate checkpoint=RUN_DIR_OR_FILE`` evaluates a training checkpoint.
"""

from __future__ import annotations

import logging
import os
import sys
from pathlib import Path
from typing import Any

import hydra
import torch
from omegaconf import DictConfig, OmegaConf
from torchrl.envs.utils import ExplorationType, set_exploration_type

from uavlae.envs import EnvConfig, UAVEnv, make_env_config
from uavlae.envs.metrics import PAPER_METRICS, format_metrics, rollout_metrics, save_aggregates, save_records
from uavlae.envs.scenario import Scenario, load_scenarios, sample_scenarios, save_scenarios, unstack_scenarios
from uavlae.factories import CONF_DIR, without_hydra_output

log = logging.getLogger(__name__)


def eval_set_path(run_dir: str | os.PathLike[str], eval_set: str | None) -> Path:
    return Path(eval_set).expanduser() if eval_set else Path(run_dir) / "eval_set.json"


def load_or_make_eval_set(env_cfg: EnvConfig, path: str | os.PathLike[str], n: int, seed: int) -> list[Scenario]:
    """The scenarios at ``path``; when the file is absent, ``n`` scenarios sampled with ``seed``
    (a generator of their own: the global RNGs are untouched) and saved there first."""
    path = Path(path)
    if path.is_file():
        scenarios = load_scenarios(path)
        if len(scenarios) != n:
            log.info("evaluation set %s has %d scenarios (trainer.eval_episodes=%d): using the file", path, len(scenarios), n)
        return scenarios
    g = torch.Generator().manual_seed(int(seed))
    scenarios = unstack_scenarios(sample_scenarios(env_cfg, int(n), g))
    path.parent.mkdir(parents=True, exist_ok=True)
    save_scenarios(path, scenarios)
    return scenarios


class Evaluator:
    """Runs a policy over the evaluation set, one episode per scenario, all rows at once.

    Args:
        env_cfg: the world.
        scenarios: the evaluation set.
        seed: seeds the evaluation env before every evaluation (same OU motion each time).
        max_steps: step budget per episode (``None``: ``env_cfg.t_max``).
        n_plots: trajectories drawn per evaluation.
        device: where the env runs.
        compile_step: step the evaluation env through ``torch.compile`` (``UAVEnv(compile_step=True)``:
            the same outputs, ~2x faster per evaluation after a one-off compile on the first).
    """

    def __init__(
        self,
        env_cfg: EnvConfig,
        scenarios: list[Scenario],
        *,
        seed: int,
        max_steps: int | None = None,
        n_plots: int = 3,
        device: str | torch.device = "cpu",
        compile_step: bool = False,
    ):
        self.env_cfg = make_env_config(env_cfg)
        self.scenarios = list(scenarios)
        self.seed = int(seed)
        self.max_steps = max_steps
        self.n_plots = int(n_plots)
        self.env = UAVEnv(
            self.env_cfg,
            batch_size=len(self.scenarios),
            device=device,
            seed=self.seed,
            scenarios=self.scenarios,
            compile_step=compile_step,
        )

    def run(self, policy: Any, out_dir: str | os.PathLike[str] | None = None, *, title: str = "") -> dict[str, float]:
        """Evaluate ``policy`` (deterministic exploration); write files under ``out_dir``."""
        self.env.set_seed(self.seed)
        with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
            records, agg, trajectories = rollout_metrics(self.env, policy, max_steps=self.max_steps, cfg=self.env_cfg)
        if out_dir is not None:
            out = Path(out_dir)
            save_records(records, out / "episodes.csv")
            save_aggregates(agg, out / "metrics.json")
            self.plot(trajectories, out, title)
        return agg

    def plot(self, trajectories: list[torch.Tensor], out: Path, title: str = "") -> None:
        from uavlae.envs.render import draw_scenario

        for i in range(min(self.n_plots, len(trajectories))):
            draw_scenario(
                self.scenarios[i], [trajectories[i]], path=out / f"trajectory_{i}.png",
                title=f"{title} scenario {i}".strip(), cfg=self.env_cfg,
            )


def deterministic_actor(learner: Any) -> Any:
    """The learner's actor alone (no exploration noise, no override)."""
    return learner.actor


def evaluate_checkpoint(cfg: DictConfig) -> dict[str, float]:
    """Evaluate ``cfg.checkpoint`` (a file or a run dir) on its run's evaluation set."""
    from uavlae.checkpoint import load_checkpoint, run_dir_of
    from uavlae.factories import make_env, make_learner

    if not cfg.checkpoint:
        raise ValueError("uavlae.evaluate needs checkpoint=PATH (a checkpoint file or a run dir)")
    state, file = load_checkpoint(cfg.checkpoint)
    saved = OmegaConf.create(state["config"])
    run_dir = run_dir_of(file)
    env_cfg = make_env_config(saved.env)
    tr = cfg.trainer  # evaluation settings come from this command line (defaults: the trainer's)
    scenarios = load_or_make_eval_set(env_cfg, eval_set_path(run_dir, tr.eval_set), tr.eval_episodes, tr.eval_seed)
    probe = make_env(env_cfg, 1, seed=0, device=cfg.device)
    learner = make_learner(saved.algo, probe)
    learner.load_state_dict(state["learner"])
    evaluator = Evaluator(env_cfg, scenarios, seed=tr.eval_seed, max_steps=tr.eval_max_steps, n_plots=tr.eval_plots, device=cfg.device)
    frames = int(state["counters"]["frames"])
    out = run_dir / "evaluate" / f"{file.stem}_frames{frames}"
    agg = evaluator.run(deterministic_actor(learner), out, title=f"{saved.name} @ {frames} frames")
    log.info("%s\n%s", out, format_metrics(agg))
    return agg


@hydra.main(config_path=str(CONF_DIR), config_name="config", version_base="1.3")
def main(cfg: DictConfig) -> None:
    torch.set_num_threads(int(cfg.threads))
    agg = evaluate_checkpoint(cfg)
    print(format_metrics(agg, PAPER_METRICS))


if __name__ == "__main__":
    sys.argv = without_hydra_output(sys.argv)
    main()
