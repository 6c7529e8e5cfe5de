"""Time to target: wall-clock until the deterministic SAC actor reaches DCR >= 0.9,
CR <= 0.1 and SLR >= 0.9 on the fixed evaluation set, for our SAC (``uavlae.train``) and for
Stable-Baselines3's SAC on the gymnasium adapter, side by side in one run on one machine.

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/time_to_target.py --cap-minutes 9
    (make bench-ttt; SB3 is the `bench` extra: pip install -e '.[bench]')

Same for both (paper Table 4 / uavlae/conf/algo/sac.yaml): actor lr 1e-4, critic lr 3e-4, alpha lr 3e-4
with automatic entropy tuning from alpha = 1 and target entropy -2, batch 256, gamma 0.99,
tau 0.005, two hidden layers of 64 (ReLU), 5000 uniform-random frames first, one gradient step
per environment frame, 16 scenarios stepped together (ours: UAVEnv batch 16; SB3: a DummyVecEnv
of 16 ``UAVGymEnv`` with 16 gradient steps per vector step), one torch thread. Ours runs with its
default SAC update (``algo.loss_impl=fused``: SACLoss's gradients written out). The result files
written before the fused update existed ran the compiled torchrl loss (``algo.compile=true`` in
their recorded commands). ``--ours-override`` adds Hydra overrides.

Both are evaluated by the same code (``uavlae.evaluate.Evaluator``: the deterministic actor on the
same saved scenarios, all at once), every ``--eval-every`` frames. The time to target counts
everything from the start of the method (set-up, collection, updates, evaluations) to the end of
the first evaluation that meets the target; frames/s counts training time only (evaluations
excluded). Each method stops at the target or at its wall-clock cap (checked at every gradient
step); then the best evaluation seen is reported. The cores are shared with other jobs, so the
absolute figures mean little; the ratio measured in this one run is the result (docs/style.md rule 10).
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

import torch
from uavlae.machine import describe_machine  # noqa: E402
from uavlae.factories import dump_json  # noqa: E402
from uavlae.files import portable  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
TARGET = {"DCR": (">=", 0.9), "CR": ("<=", 0.1), "SLR": (">=", 0.9)}
SAC_HP = {"actor_lr": 1e-4, "critic_lr": 3e-4, "alpha_lr": 3e-4, "batch_size": 256, "gamma": 0.99, "tau": 0.005,
          "hidden": [64, 64], "init_random_frames": 5000, "utd_ratio": 1.0, "env_batch": 16}



def meets(agg: dict) -> bool:
    return all((agg[k] >= v) if op == ">=" else (agg[k] <= v) for k, (op, v) in TARGET.items())


def score(agg: dict) -> float:
    """Orders evaluations for "best": the target's three terms, each capped at its threshold."""
    return min(agg["DCR"], 0.9) / 0.9 + min(agg["SLR"], 0.9) / 0.9 + (1.0 - max(agg["CR"] - 0.1, 0.0))


class Stop(Exception):
    """Raised from inside a training loop: target met or wall-clock cap reached."""


class Clock:
    """Wall clock of one method: evaluations, evaluation time, target and cap."""

    def __init__(self, cap_s: float):
        self.t0 = time.perf_counter()
        self.cap_s = cap_s
        self.eval_s = 0.0
        self.evals: list[dict] = []
        self.reached: dict | None = None
        self.stop_reason = ""

    def elapsed(self) -> float:
        return time.perf_counter() - self.t0

    def check_cap(self) -> None:
        if self.elapsed() > self.cap_s:
            self.stop_reason = "cap"
            raise Stop

    def record(self, frames: int, agg: dict, eval_s: float) -> None:
        self.eval_s += eval_s
        row = {"frames": frames, "wall_s": round(self.elapsed(), 2), "eval_s": round(eval_s, 2),
               **{k: float(agg[k]) for k in ("DCR", "CR", "SLR", "RVR", "ECR")}}
        self.evals.append(row)
        print(f"  eval @ {frames} frames, {row['wall_s']:.0f} s: "
              + ", ".join(f"{k} {row[k]:.3f}" for k in ("DCR", "CR", "SLR", "RVR", "ECR")), flush=True)
        if meets(agg):
            self.reached = row
            self.stop_reason = "target"
            raise Stop
        self.check_cap()

    def summary(self, name: str, frames: int) -> dict:
        wall = self.elapsed()
        best = max(self.evals, key=lambda r: score(r)) if self.evals else None
        return {
            "method": name,
            "reached": self.reached is not None,
            "time_to_target_s": self.reached["wall_s"] if self.reached else None,
            "frames_to_target": self.reached["frames"] if self.reached else None,
            "stop_reason": self.stop_reason or "done",
            "cap_s": self.cap_s,
            "wall_s": round(wall, 1),
            "eval_s_total": round(self.eval_s, 1),
            "frames": frames,
            "train_frames_per_s": round(frames / max(wall - self.eval_s, 1e-9), 2),
            "best_eval": best,
            "evals": self.evals,
        }


def sb3_gradient_steps() -> int:
    """SB3 steps all ``env_batch`` envs at once, then takes this many gradient steps: the same
    gradient steps per frame (``utd_ratio``) as ours."""
    steps = SAC_HP["env_batch"] * SAC_HP["utd_ratio"]
    if steps < 1 or steps != int(steps):
        raise SystemExit(f"--env-batch x --utd must be a whole number >= 1 for SB3, got {steps}")
    return int(steps)


def env_config(name: str):
    """The ``uavlae/conf/env/<name>.yaml`` world, validated: both methods train and evaluate on it."""
    from hydra import compose, initialize_config_dir

    from uavlae.envs import make_env_config
    from uavlae.factories import CONF_DIR

    with initialize_config_dir(str(CONF_DIR), version_base="1.3"):
        return make_env_config(compose("config", overrides=[f"env={name}"]).env)


def run_ours(a: argparse.Namespace, eval_set: Path, run_dir: Path) -> dict:
    """``uavlae.train.run`` on ``+exp=sac``, with the evaluator and learner timed and stoppable."""
    from hydra import compose, initialize_config_dir

    import uavlae.evaluate as ev
    import uavlae.train as tr
    from uavlae.factories import CONF_DIR

    overrides = ["+exp=sac", f"seed={a.seed}", "threads=1", f"run_dir={run_dir}", "trainer.total_frames=100000000",
                 f"trainer.eval_every_frames={a.eval_every}", f"trainer.eval_set={eval_set}",
                 f"trainer.eval_episodes={a.eval_episodes}", f"trainer.eval_seed={a.eval_seed}",
                 "trainer.progress_bar=false", "trainer.eval_plots=0", "trainer.checkpoint_every_frames=0",
                 "trainer.checkpoint_replay_buffer=false", "logger.wandb.mode=disabled",
                 f"trainer.env_batch_size={SAC_HP['env_batch']}", f"trainer.utd_ratio={SAC_HP['utd_ratio']}",
                 f"env={a.env}", *a.ours_override]
    with initialize_config_dir(str(CONF_DIR), version_base="1.3"):
        cfg = compose("config", overrides=overrides)
    clock = Clock(a.cap_minutes * 60)
    frames = {"n": 0}
    orig_run, orig_make_learner = ev.Evaluator.run, tr.make_learner

    def timed_run(self, policy, out_dir=None, **kw):
        t = time.perf_counter()
        agg = orig_run(self, policy, out_dir, **kw)
        frames["n"] = int(Path(out_dir).name.split("_")[1])  # <run_dir>/eval/frames_000008192
        eval_s = time.perf_counter() - t
        if a.keep_actors and hasattr(policy, "state_dict"):  # beside episodes.csv, outside the clock
            torch.save(policy.state_dict(), Path(out_dir) / "actor.pt")
        clock.record(frames["n"], agg, eval_s)
        return agg

    def stoppable_learner(*args, **kwargs):
        learner = orig_make_learner(*args, **kwargs)
        update = learner.update

        def checked_update(batch):
            clock.check_cap()
            return update(batch)

        learner.update = checked_update
        return learner

    ev.Evaluator.run, tr.make_learner = timed_run, stoppable_learner
    print(f"[ours] uavlae.train {' '.join(overrides)}", flush=True)
    clock.t0 = time.perf_counter()
    try:
        tr.run(cfg)
    except Stop:
        pass
    finally:
        ev.Evaluator.run, tr.make_learner = orig_run, orig_make_learner
    # frames reached at the stop: the collector's count is the last eval's or later; read the CSV
    fps_csv = run_dir / "logs" / "scalars" / "time" / "fps.csv"
    if fps_csv.exists():
        lines = fps_csv.read_text().strip().splitlines()
        if lines:
            frames["n"] = max(frames["n"], int(float(lines[-1].split(",")[0])))
    out = clock.summary("uavlae_sac", frames["n"])
    out["command"] = portable("python -m uavlae.train " + " ".join(overrides), ROOT)
    return out


def make_sb3_sac(vec, seed: int, *, learning_starts: int, gradient_steps: int):
    """Stable-Baselines3's SAC with Table 4's hyperparameters (``SAC_HP``) on the vector env ``vec``."""
    from stable_baselines3 import SAC

    class SplitLRSAC(SAC):
        """SB3's SAC has one learning rate; Table 4 has two (actor 1e-4, critic 3e-4)."""

        def _update_learning_rate(self, optimizers) -> None:
            for opt, lr in ((self.actor.optimizer, SAC_HP["actor_lr"]), (self.critic.optimizer, SAC_HP["critic_lr"]),
                            (self.ent_coef_optimizer, SAC_HP["alpha_lr"])):
                if opt is not None:
                    for g in opt.param_groups:
                        g["lr"] = lr

    return SplitLRSAC(
        "MlpPolicy", vec, learning_rate=SAC_HP["critic_lr"], buffer_size=1_000_000,
        learning_starts=learning_starts, batch_size=SAC_HP["batch_size"], tau=SAC_HP["tau"],
        gamma=SAC_HP["gamma"], train_freq=1, gradient_steps=gradient_steps, ent_coef="auto_1.0", target_entropy="auto",
        policy_kwargs={"net_arch": list(SAC_HP["hidden"]), "activation_fn": torch.nn.ReLU},
        seed=seed, device="cpu", verbose=0,
    )


def run_sb3(a: argparse.Namespace, eval_set: Path) -> dict:
    """Stable-Baselines3 SAC on 16 ``UAVGymEnv``, evaluated by the same ``Evaluator``."""
    import stable_baselines3
    from stable_baselines3.common.callbacks import BaseCallback
    from stable_baselines3.common.vec_env import DummyVecEnv

    from uavlae.envs.gym_adapter import UAVGymEnv
    from uavlae.envs.scenario import load_scenarios
    from uavlae.evaluate import Evaluator

    env_cfg = env_config(a.env)
    n = SAC_HP["env_batch"]
    clock = Clock(a.cap_minutes * 60)
    vec = DummyVecEnv([lambda: UAVGymEnv(env_cfg) for _ in range(n)])
    vec.seed(a.seed)
    model = make_sb3_sac(vec, a.seed, learning_starts=SAC_HP["init_random_frames"], gradient_steps=sb3_gradient_steps())
    evaluator = Evaluator(env_cfg, load_scenarios(eval_set), seed=a.eval_seed, n_plots=0)

    def actor(td):  # the deterministic SB3 actor (tanh of the mean) on UAVEnv's observation
        td.set("action", model.actor(td.get("observation"), deterministic=True))
        return td

    class EvalCallback(BaseCallback):
        def __init__(self):
            super().__init__()
            self.next_eval = a.eval_every

        def _on_step(self) -> bool:
            try:
                clock.check_cap()
                if self.num_timesteps >= self.next_eval:
                    self.next_eval += a.eval_every
                    t = time.perf_counter()
                    agg = evaluator.run(actor)
                    clock.record(self.num_timesteps, agg, time.perf_counter() - t)
            except Stop:
                return False
            return True

    print(f"[sb3] stable-baselines3 {stable_baselines3.__version__} SAC, {n} UAVGymEnv, gradient_steps={sb3_gradient_steps()}", flush=True)
    clock.t0 = time.perf_counter()
    model.learn(total_timesteps=100_000_000, callback=EvalCallback())
    out = clock.summary("sb3_sac", int(model.num_timesteps))
    out["sb3_version"] = stable_baselines3.__version__
    return out


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--cap-minutes", type=float, default=15.0, help="wall-clock cap of each method")
    p.add_argument("--eval-every", type=int, default=6144, help="frames between evaluations (both methods)")
    p.add_argument("--eval-episodes", type=int, default=32)
    p.add_argument("--eval-seed", type=int, default=12345)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--methods", nargs="+", default=["uavlae_sac", "sb3_sac"], choices=["uavlae_sac", "sb3_sac"])
    p.add_argument("--env-batch", type=int, default=SAC_HP["env_batch"],
                   help="scenarios stepped together, both methods (default 16)")
    p.add_argument("--utd", type=float, default=SAC_HP["utd_ratio"],
                   help="gradient steps per environment frame, both methods (default 1)")
    p.add_argument("--ours-override", nargs="*", default=[],
                   help="extra Hydra overrides of our run (e.g. algo.loss_impl=torchrl algo.compile=true)")
    p.add_argument("--env", default="default",
                   help="uavlae/conf/env group both methods train and evaluate on (default: SPEC's world; "
                        "shaped: + progress reward and ego-centric observation columns)")
    p.add_argument("--run-dir", default=None,
                   help="keep our run here (eval/frames_*/episodes.csv, ...) instead of a temporary folder")
    p.add_argument("--keep-actors", action="store_true",
                   help="save our deterministic actor's state_dict beside each evaluation (eval/frames_*/actor.pt)")
    p.add_argument("--out", default=str(ROOT / "benchmarks" / "time_to_target.json"))
    a = p.parse_args(argv)
    SAC_HP.update(env_batch=a.env_batch, utd_ratio=a.utd)
    sb3_gradient_steps()  # fail early on a combination SB3 cannot run

    torch.set_num_threads(1)
    os.environ.setdefault("WANDB_MODE", "disabled")
    from uavlae.evaluate import load_or_make_eval_set

    work = Path(a.run_dir) if a.run_dir else Path(tempfile.mkdtemp(prefix="ttt_"))
    if (work / "ours").exists():
        raise SystemExit(f"--run-dir {work} already holds a run (ours/): name a new folder")
    work.mkdir(parents=True, exist_ok=True)
    eval_set = work / "eval_set.json"
    load_or_make_eval_set(env_config(a.env), eval_set, a.eval_episodes, a.eval_seed)
    result = {"measured_at": time.strftime("%Y-%m-%d %H:%M:%S %Z"), "machine": describe_machine(),
              "command": portable("python benchmarks/time_to_target.py " + " ".join(sys.argv[1:] if argv is None else argv),
                                  ROOT),
              "target": {k: f"{op} {v}" for k, (op, v) in TARGET.items()}, "hyperparameters": SAC_HP,
              "eval_every_frames": a.eval_every, "eval_episodes": a.eval_episodes, "eval_seed": a.eval_seed,
              "seed": a.seed, "cap_minutes": a.cap_minutes, "env": a.env, "ours_overrides": a.ours_override, "methods": {}}
    for m in a.methods:
        print(f"== {m} (cap {a.cap_minutes:g} min)", flush=True)
        result["methods"][m] = run_ours(a, eval_set, work / "ours") if m == "uavlae_sac" else run_sb3(a, eval_set)
        dump_json(Path(a.out), result)
    ms = result["methods"]
    if "uavlae_sac" in ms and "sb3_sac" in ms:
        o, s = ms["uavlae_sac"], ms["sb3_sac"]
        result["ratio_train_fps_ours_over_sb3"] = round(o["train_frames_per_s"] / s["train_frames_per_s"], 3)
        if o["reached"] and s["reached"]:
            result["speedup_time_to_target_sb3_over_ours"] = round(s["time_to_target_s"] / o["time_to_target_s"], 3)
    for m, r in ms.items():
        ttt = f"{r['time_to_target_s']:.0f} s" if r["reached"] else f"not reached in {r['cap_s'] / 60:g} min"
        b = r["best_eval"] or {}
        print(f"{m}: {ttt}; {r['frames']} frames, {r['train_frames_per_s']} train frames/s; best eval "
              + ", ".join(f"{k} {b[k]:.3f}" for k in ("DCR", "CR", "SLR") if k in b) + f" @ {b.get('frames')} frames")
    if "ratio_train_fps_ours_over_sb3" in result:
        print(f"train frames/s ratio ours / SB3: {result['ratio_train_fps_ours_over_sb3']}")
    dump_json(Path(a.out), result)


if __name__ == "__main__":
    main()
