"""``python -m uavlae.train +exp=NAME``: train (or, for ``heuristic`` / ``llm``, evaluate) one method.

The loop, top to bottom (every number in ``conf/``)::

    for batch in collector:                      # [B, T] executed transitions, step = env frames
        off-policy (sac, ddpg): replay.extend(batch); utd_ratio * frames gradient steps
        on-policy (ppo, cpo):   learner.update(batch)
        log train metrics, episode metrics, override / LLM counters, fps
        every eval_every_frames:       evaluate the deterministic actor on the fixed set
        every checkpoint_every_frames: atomic checkpoint (exact resume at this batch boundary)

``run(cfg)`` is importable (the tests call it in-process) and returns the final metrics.
``resume=RUN_DIR_OR_CHECKPOINT`` continues a run: same config, frames, RNG states, replay
buffer, CSV files and wandb run id.
"""

from __future__ import annotations

import json
import logging
import math
import time
import uuid
from pathlib import Path
from typing import Any

import hydra
import torch
from omegaconf import DictConfig, OmegaConf

from uavlae.algos import OFF_POLICY
from uavlae.checkpoint import load_checkpoint, rng_state, run_dir_of, save_checkpoint, seed_everything, set_rng_state
from uavlae.collect import TRANSITION_KEYS, UAVCollector, make_replay_buffer
from uavlae.envs import make_env_config
from uavlae.envs.metrics import PAPER_METRICS
from uavlae.evaluate import Evaluator, deterministic_actor, eval_set_path, load_or_make_eval_set
from uavlae.factories import (
    CONF_DIR,
    behaviour_actor,
    dump_json,
    make_controller,
    make_env,
    make_learner,
    make_logger,
    make_policy,
    make_trainer_config,
    redact_secrets,
    run_metadata,
    trim_csv_scalars,
    validate_config,
)
from uavlae.files import atomic_write

log = logging.getLogger(__name__)

# What a resumed run may take from the new command line; everything else is the saved config.
RESUME_RUNTIME_KEYS = ("threads", "trainer.progress_bar", "logger.wandb.mode")
# What the replay buffer keeps of a transition (the collector already dropped the raw state).
REPLAY_KEYS = (
    "observation", "action", "action_source",
    ("next", "observation"), ("next", "reward"), ("next", "cost"), ("next", "done"),
    ("next", "terminated"), ("next", "truncated"),
)


def _resolved(cfg: DictConfig) -> dict[str, Any]:
    return redact_secrets(OmegaConf.to_container(cfg, resolve=True))  # type: ignore[arg-type]


# Keys that may differ between a sweep's re-run and the run it finds in its run_dir.
REUSE_IGNORED_KEYS = ("resume", "experiment.reuse", *RESUME_RUNTIME_KEYS)


def _comparable(cfg_dict: dict[str, Any]) -> dict[str, Any]:
    c = OmegaConf.create(cfg_dict)
    c.run_dir = str(Path(c.run_dir).resolve())  # a resumed run saves its run_dir resolved
    for key in REUSE_IGNORED_KEYS:
        if OmegaConf.select(c, key) is not None:
            OmegaConf.update(c, key, None, merge=False)
    return OmegaConf.to_container(c)  # type: ignore[return-value]


def reuse_state(cfg: DictConfig) -> tuple[str, dict[str, Any] | None]:
    """With ``experiment.reuse``: what ``cfg.run_dir`` holds of this run. ``("done", final
    metrics)`` for a finished run, ``("resume", None)`` for one with a checkpoint, ``("new",
    None)`` otherwise. A run_dir that holds a run of another config is an error (a sweep re-run
    with changed settings must not mix the two)."""
    run_dir = Path(cfg.run_dir)
    saved_file = run_dir / "config.json"
    if not cfg.experiment.reuse or not saved_file.is_file():
        return "new", None
    wanted = _comparable(_resolved(cfg))
    saved = _comparable(json.loads(saved_file.read_text()))
    if wanted != saved:
        changed = sorted(k for k in set(_flat(wanted)) | set(_flat(saved)) if _flat(wanted).get(k) != _flat(saved).get(k))
        raise ValueError(
            f"{run_dir} holds a run of another config (differs in {changed[:8]}); "
            "remove it or set experiment.root elsewhere"
        )
    final = run_dir / "final_metrics.json"
    if final.is_file():
        return "done", json.loads(final.read_text())
    if (run_dir / "checkpoints" / "last.pt").is_file() or (run_dir / "checkpoints" / "prev.pt").is_file():
        return "resume", None
    return "new", None


def _flat(d: Any, prefix: str = "") -> dict[str, Any]:
    if not isinstance(d, dict):
        return {prefix: d}
    out: dict[str, Any] = {}
    for k, v in d.items():
        out.update(_flat(v, f"{prefix}{k}." if isinstance(v, dict) else f"{prefix}{k}"))
    return out


def _prepare(cfg: DictConfig) -> tuple[DictConfig, dict[str, Any] | None]:
    """Resolve the config; on ``resume`` load the checkpoint and continue with its config."""
    ckpt = None
    if cfg.resume:
        ckpt, file = load_checkpoint(cfg.resume)
        saved = OmegaConf.create(ckpt["config"])
        for key in RESUME_RUNTIME_KEYS:
            OmegaConf.update(saved, key, OmegaConf.select(cfg, key), merge=False)
        saved.resume = str(file)
        saved.run_dir = str(run_dir_of(file))
        cfg = saved
        log.info("resuming %s from %s at %d frames", cfg.name, file, ckpt["counters"]["frames"])
    else:
        cfg = OmegaConf.create(_resolved(cfg))
    OmegaConf.set_struct(cfg, True)
    validate_config(cfg)
    return cfg, ckpt


def _eval_out(run_dir: Path, frames: int) -> Path:
    return run_dir / "eval" / f"frames_{frames:09d}"


def _prefixed(prefix: str, metrics: dict[str, Any]) -> dict[str, float]:
    out = {}
    for k, v in metrics.items():
        if isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(float(v)):
            out[f"{prefix}/{k}"] = float(v)
    return out


def run(cfg: DictConfig) -> dict[str, Any]:
    """Train (or evaluate a controller) as ``cfg`` says; returns the final metrics."""
    state, final = reuse_state(cfg)
    if state == "done":
        log.info("%s: finished already (experiment.reuse): %s", cfg.name, Path(cfg.run_dir) / "final_metrics.json")
        return final  # type: ignore[return-value]
    if state == "resume":
        cfg = cfg.copy()
        OmegaConf.set_struct(cfg, False)
        cfg.resume = str(cfg.run_dir)
        OmegaConf.set_struct(cfg, True)
    cfg, ckpt = _prepare(cfg)
    torch.set_num_threads(int(cfg.threads))
    tr = make_trainer_config(cfg.trainer)
    env_cfg = make_env_config(cfg.env)
    run_dir = Path(cfg.run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    resolved = _resolved(cfg)
    dump_json(run_dir / "config.json", resolved)
    yaml_text = OmegaConf.to_yaml(OmegaConf.create(resolved))
    atomic_write(run_dir / "config.yaml", lambda fh: fh.write(yaml_text.encode("utf-8")))
    meta = run_metadata(resolved)
    dump_json(run_dir / "meta.json", meta)

    run_id = ckpt["logger"]["run_id"] if ckpt else f"{cfg.name}-{uuid.uuid4().hex[:10]}"
    if ckpt:
        trim_csv_scalars(run_dir / "logs", int(ckpt["counters"]["frames"]))
    logger = make_logger(cfg, run_dir, run_id, {**resolved, "meta": meta})
    if ckpt:
        logger.load_state_dict(ckpt["logger"])

    scenarios = load_or_make_eval_set(env_cfg, eval_set_path(run_dir, tr.eval_set), tr.eval_episodes, tr.eval_seed)
    evaluator = Evaluator(
        env_cfg,
        scenarios,
        seed=tr.eval_seed,
        max_steps=tr.eval_max_steps,
        n_plots=tr.eval_plots,
        device=cfg.device,
        compile_step=tr.compile_env,
    )
    try:
        if cfg.controller != "learner":
            return _evaluate_controller(cfg, env_cfg, evaluator, logger, run_dir)
        return _train(cfg, tr, env_cfg, evaluator, logger, run_dir, ckpt)
    finally:
        logger.close()


def _evaluate_controller(cfg: DictConfig, env_cfg: Any, evaluator: Evaluator, logger: Any, run_dir: Path) -> dict[str, Any]:
    """``heuristic`` / ``llm``: no learner; the controller flies the evaluation set."""
    controller = make_controller(cfg, env_cfg, action_spec=evaluator.env.action_spec)
    t0 = time.perf_counter()
    try:
        agg = evaluator.run(controller, _eval_out(run_dir, 0), title=str(cfg.name))
        stats = controller.snapshot() if hasattr(controller, "snapshot") else {}
    finally:
        close = getattr(controller, "close", None)
        if close is not None:
            close()
    metrics = {**_prefixed("eval", agg), **_prefixed("override", stats), "time/eval_s": time.perf_counter() - t0}
    logger.log_metrics(metrics, step=0)
    logger.log_images(_trajectory_images(_eval_out(run_dir, 0)), step=0)
    final = {"frames": 0, **metrics}
    dump_json(run_dir / "final_metrics.json", final)
    log.info("%s: %s", cfg.name, {k: round(agg[k], 4) for k in PAPER_METRICS})
    return final


def _train(
    cfg: DictConfig, tr: Any, env_cfg: Any, evaluator: Evaluator, logger: Any, run_dir: Path, ckpt: dict[str, Any] | None
) -> dict[str, Any]:
    from tqdm.auto import tqdm

    seed_everything(int(cfg.seed))
    env = make_env(env_cfg, tr.env_batch_size, seed=int(cfg.seed), device=cfg.device, compile_step=tr.compile_env)
    learner = make_learner(cfg.algo, env)
    off_policy = cfg.algo.name in OFF_POLICY
    has_advisor = cfg.advisor.kind != "none"
    policy = make_policy(cfg, behaviour_actor(learner), env_cfg)
    collector = UAVCollector(
        env,
        policy,
        frames_per_batch=tr.frames_per_batch,
        total_frames=tr.total_frames,
        init_random_frames=tr.init_random_frames if off_policy else 0,
        # not "loc"/"scale": the random warm-up does not write them, and a batch that straddles
        # init_random_frames would then stack steps with different keys
        keep_keys=TRANSITION_KEYS,
        seed=int(cfg.seed),
    )
    replay = make_replay_buffer(tr.replay_capacity, tr.batch_size, cfg.device, seed=int(cfg.seed)) if off_policy else None
    counters: dict[str, Any] = {
        "frames": 0, "episodes": 0, "batches": 0, "updates": 0, "utd_debt": 0.0, "next_eval": 0, "next_ckpt": 0,
        "wall_s": 0.0,
    }
    counters["next_eval"] = tr.eval_every_frames or tr.total_frames
    counters["next_ckpt"] = tr.checkpoint_every_frames or tr.total_frames
    last_eval: dict[str, float] = {}
    if ckpt:
        learner.load_state_dict(ckpt["learner"])
        collector.load_state_dict(ckpt["collector"])
        if replay is not None and ckpt.get("replay_buffer") is not None:
            replay.load_state_dict(ckpt["replay_buffer"])
        counters.update(ckpt["counters"])
        last_eval = dict(ckpt.get("last_eval", {}))
        set_rng_state(ckpt["rng"])  # last: building the modules above drew from the global RNG

    def checkpoint() -> Path:
        state = {
            "learner": learner.state_dict(),
            "collector": collector.state_dict(),
            "replay_buffer": replay.state_dict() if (replay is not None and tr.checkpoint_replay_buffer) else None,
            "rng": rng_state(),
            "counters": dict(counters),
            "last_eval": dict(last_eval),
            "logger": logger.state_dict(),
            "config": _resolved(cfg),
        }
        return save_checkpoint(state, run_dir, keep=tr.keep_checkpoints)

    def evaluate(frames: int) -> dict[str, float]:
        out = _eval_out(run_dir, frames)
        agg = evaluator.run(deterministic_actor(learner), out, title=f"{cfg.name} @ {frames} frames")
        logger.log_metrics({**_prefixed("eval", agg), "eval/episodes_trained": counters["episodes"]}, step=frames)
        logger.log_images(_trajectory_images(out), step=frames)
        return agg

    def budget_spent() -> bool:
        """The frame budget, or the episode budget (paper: 4000 episodes) when one is set."""
        episodes_done = tr.total_episodes is not None and counters["episodes"] >= tr.total_episodes
        return counters["frames"] >= tr.total_frames or episodes_done

    bar = tqdm(total=tr.total_frames, initial=counters["frames"], unit="frame", disable=not tr.progress_bar, dynamic_ncols=True)
    t_start, frames_start, wall_start = time.perf_counter(), counters["frames"], float(counters["wall_s"])
    train_logs: dict[str, float] = {}
    try:
        for batch in () if budget_spent() else collector:
            t_batch = time.perf_counter()
            frames = collector.frames
            n_new = frames - counters["frames"]
            counters["frames"] = frames
            counters["batches"] += 1
            counters["episodes"] += int(batch.get(("next", "done")).sum())
            counters["wall_s"] = wall_start + (t_batch - t_start)  # training wall clock over every resumed part
            if off_policy:
                replay.extend(batch.select(*REPLAY_KEYS, strict=False).reshape(-1))
                noise = getattr(learner, "noise", None)
                if noise is not None and hasattr(noise, "step"):
                    noise.step(n_new)  # DDPG: anneal the exploration noise by frames
                if frames >= tr.init_random_frames and len(replay) >= tr.batch_size:
                    counters["utd_debt"] += tr.utd_ratio * n_new
                    n_updates = int(counters["utd_debt"])
                    counters["utd_debt"] -= n_updates
                    for _ in range(n_updates):
                        train_logs = learner.update(replay.sample())
                    counters["updates"] += n_updates
            else:
                train_logs = learner.update(batch)
                counters["updates"] += 1
            t_update = time.perf_counter() - t_batch

            if counters["batches"] % tr.log_every_batches == 0:
                _, episodes = collector.episode_metrics()
                elapsed = time.perf_counter() - t_start
                metrics = {
                    **_prefixed("train", train_logs),
                    **_prefixed("episode", episodes),
                    **(_prefixed("override", collector.override_stats(reset=True)) if has_advisor else {}),
                    "time/fps": (frames - frames_start) / max(elapsed, 1e-9),
                    "time/update_s": t_update,
                    "train/updates": counters["updates"],
                    "train/episodes": counters["episodes"],
                    "train/replay_size": len(replay) if replay is not None else 0,
                }
                logger.log_metrics(metrics, step=frames)
            finished = budget_spent()
            if frames >= counters["next_eval"] or finished:
                last_eval = evaluate(frames)
                counters["last_eval_frames"] = frames
                every = tr.eval_every_frames or tr.total_frames
                counters["next_eval"] = (frames // every + 1) * every
            if frames >= counters["next_ckpt"] or finished:
                every = tr.checkpoint_every_frames or tr.total_frames
                counters["next_ckpt"] = (frames // every + 1) * every
                checkpoint()
            bar.update(n_new)
            post = {"fps": f"{(frames - frames_start) / max(time.perf_counter() - t_start, 1e-9):.0f}"}
            post.update({k: f"{last_eval[k]:.3f}" for k in ("DCR", "CR", "SLR") if k in last_eval})
            bar.set_postfix(post, refresh=False)
            if finished:
                break
    finally:
        bar.close()
        collector.shutdown()

    if counters.get("last_eval_frames") != counters["frames"]:  # resumed after the final batch
        last_eval = evaluate(counters["frames"])
        counters["last_eval_frames"] = counters["frames"]
    final = {
        "frames": counters["frames"],
        "episodes": counters["episodes"],
        "updates": counters["updates"],
        "wall_s": round(float(counters["wall_s"]), 1),
        **_prefixed("eval", last_eval),
        "actor_param_sum": float(sum(p.detach().double().abs().sum() for p in learner.actor.parameters())),
    }
    dump_json(run_dir / "final_metrics.json", final)
    log.info("%s done at %d frames: %s", cfg.name, counters["frames"], {k: round(last_eval.get(k, float("nan")), 4) for k in PAPER_METRICS})
    return final


def _trajectory_images(eval_dir: Path) -> dict[str, Path]:
    return {f"eval/trajectory_{p.stem.rsplit('_', 1)[-1]}": p for p in sorted(eval_dir.glob("trajectory_*.png"))}


@hydra.main(config_path=str(CONF_DIR), config_name="config", version_base="1.3")
def main(cfg: DictConfig) -> None:
    # one INFO line per HTTP request buries the progress bar; the LLM counters are in the logs
    logging.getLogger("httpx").setLevel(logging.WARNING)
    final = run(cfg)
    print(json.dumps(final, indent=1))


if __name__ == "__main__":
    main()
