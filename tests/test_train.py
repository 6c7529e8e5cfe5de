"""End-to-end runs of the entry points with tiny settings: train, log, checkpoint, evaluate,
resume after SIGKILL (bit-identical to an uninterrupted run), export and fly."""

from __future__ import annotations

import json
import math
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from uavlae.checkpoint import LAST, PREV, load_checkpoint, save_checkpoint
from uavlae.factories import CONF_DIR, REPO_ROOT

pytestmark = pytest.mark.timeout(600)

TINY = [
    "trainer.total_frames=128", "trainer.env_batch_size=4", "trainer.frames_per_batch=32",
    "trainer.init_random_frames=32", "trainer.batch_size=16", "trainer.utd_ratio=0.25",
    "trainer.replay_capacity=512", "trainer.eval_episodes=2", "trainer.eval_max_steps=10",
    "trainer.eval_every_frames=64", "trainer.checkpoint_every_frames=64", "trainer.eval_plots=1",
    "trainer.progress_bar=false", "logger.wandb.mode=disabled",
]
ON_POLICY_TINY = ["algo.minibatch_size=32", "algo.epochs=1"]


def _cfg(*overrides: str):
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        return compose("config", overrides=list(overrides))


def _run(exp: str, run_dir: Path, *extra: str) -> dict:
    from uavlae.train import run

    more = ON_POLICY_TINY if exp in ("ppo", "cpo", "wang") else []
    return run(_cfg(f"+exp={exp}", f"run_dir={run_dir}", *TINY, *more, *extra))


def _deterministic_actions(run_dir: Path):
    """A run's learner rebuilt from its checkpoint, on a fresh env of 3 rows: ``(learner, env,
    reset root, the actor's deterministic actions there)``, what an export must reproduce."""
    from torchrl.envs.utils import ExplorationType, set_exploration_type

    from uavlae.factories import make_env, make_learner

    state, _ = load_checkpoint(run_dir)
    saved = OmegaConf.create(state["config"])
    env = make_env(saved.env, 3, seed=1)
    learner = make_learner(saved.algo, env)
    learner.load_state_dict(state["learner"])
    td = env.reset()
    with set_exploration_type(ExplorationType.DETERMINISTIC), torch.no_grad():
        expected = learner.actor(td.clone())["action"]
    return learner, env, td, expected


def _csv_steps(run_dir: Path, metric: str) -> list[int]:
    f = run_dir / "logs" / "scalars" / f"{metric}.csv"
    return [int(float(line.split(",")[0])) for line in f.read_text().splitlines() if line]


def _check_run_outputs(run_dir: Path, final: dict, *, trained: bool = True, frames: int = 128) -> None:
    for k in ("eval/DCR", "eval/CR", "eval/SLR", "eval/RVR", "eval/ECR", "eval/mean_term_r1"):
        assert k in final, k
    assert json.loads((run_dir / "final_metrics.json").read_text())["eval/DCR"] == final["eval/DCR"]
    assert (run_dir / "eval_set.json").is_file()
    evals = sorted((run_dir / "eval").iterdir())
    assert evals and (evals[-1] / "episodes.csv").is_file() and (evals[-1] / "trajectory_0.png").is_file()
    assert (evals[-1] / "metrics.json").is_file()
    assert _csv_steps(run_dir, "eval/DCR")
    cfg_json = json.loads((run_dir / "config.json").read_text())
    assert cfg_json["name"] and "api_key" not in json.dumps(cfg_json.get("llm", {})).replace("api_key_env", "")
    if trained:
        assert final["frames"] == frames
        assert _csv_steps(run_dir, "time/fps")[-1] == frames  # step = environment frames
        assert (run_dir / "checkpoints" / LAST).is_file()
        state, _ = load_checkpoint(run_dir)
        assert state["counters"]["frames"] == frames and state["config"]["name"] == cfg_json["name"]


@pytest.mark.parametrize("exp", ["sac", "ppo", "ddpg", "cpo", "wang", "sac_heuristic"])
def test_exp_trains_end_to_end(tmp_path, exp):
    final = _run(exp, tmp_path / exp)
    _check_run_outputs(tmp_path / exp, final)
    assert final["updates"] > 0
    steps = _csv_steps(tmp_path / exp, "time/fps")
    assert steps == sorted(steps) and steps[0] == 32
    if exp == "cpo":
        assert _csv_steps(tmp_path / exp, "train/lambda") and _csv_steps(tmp_path / exp, "train/kl")
    if exp == "wang":
        assert _csv_steps(tmp_path / exp, "train/intrinsic_reward_mean")
    if exp == "sac_heuristic":
        assert _csv_steps(tmp_path / exp, "override/source/heuristic")
    if exp == "sac":
        assert _csv_steps(tmp_path / exp, "train/alpha")


def test_off_policy_schedule_is_per_env_step_and_the_overlap_changes_no_number(tmp_path):
    from uavlae.summary import format_summary

    # TINY: B = 4, 128 frames, warm-up 32 frames, utd 0.25, replay sample 16. A step owes
    # 0.25 * 4 = 1 gradient step once frames >= 32 (the 8th to the 32nd step: 25 steps), each
    # run at the next step while its advice is in flight, the last one at the end.
    on = _run("sac_heuristic", tmp_path / "on", "trainer.baselines=false")
    assert on["updates"] == 25
    off = _run("sac_heuristic", tmp_path / "off", "trainer.baselines=false", "trainer.overlap_advice=false")
    assert on.pop("wall_s") > 0 and off.pop("wall_s") > 0  # the training wall clock differs run to run
    assert off == on  # the heuristic never reads the actor: sending it before the updates changes nothing
    assert on["override/advised"] == on["override/triggered"] > 0  # hold_steps=1, no budget: every one asked
    assert on["override/source/heuristic"] == on["override/triggered"]
    summary = json.loads((tmp_path / "on" / "summary.json").read_text())
    assert summary["frames"] == 128 and summary["updates"] == 25 and summary["full_run_frames"] == 1_000_000
    assert summary["override"]["advisor/rows_advised"] == on["override/advised"]
    text = format_summary(summary)
    n = int(on["override/triggered"])
    assert f"Advisor (heuristic): triggered on {n} of 128 frames ({100 * n / 128:.1f}%); {n} rows asked" in text


def test_closing_summary_names_the_baselines_and_the_pictures(tmp_path):
    from uavlae.summary import format_summary

    final = _run("sac", tmp_path / "s")
    for who in ("heuristic", "random"):
        for k in ("DCR", "CR", "SLR", "RVR", "ECR"):
            assert 0.0 <= final[f"baseline/{who}/{k}"] <= 1.0
    summary = json.loads((tmp_path / "s" / "summary.json").read_text())
    assert summary["metrics"]["heuristic"]["DCR"] == final["baseline/heuristic/DCR"]
    assert summary["metrics"]["uniform random"]["CR"] == final["baseline/random/CR"]
    text = format_summary(summary)
    assert "128 environment frames (0.013% of a full run's 1,000,000" in text
    assert "heuristic" in text and "uniform random" in text and "sac (trained actor)" in text
    assert str(tmp_path / "s" / "eval" / "frames_000000128" / "trajectory_*.png") in text
    assert list((tmp_path / "s" / "eval" / "baseline_heuristic").glob("trajectory_*.png"))


def test_compiled_env_and_sac_train_end_to_end(tmp_path, monkeypatch):
    # trainer.compile_env (training and evaluation envs) / algo.compile (of torchrl's SACLoss) through the whole loop
    import uavlae.train as tr

    made, evaluations = [], []
    real, real_evaluation = tr.make_env, tr.make_evaluation
    monkeypatch.setattr(tr, "make_env", lambda *a, **k: made.append(real(*a, **k)) or made[-1])
    monkeypatch.setattr(tr, "make_evaluation", lambda *a, **k: evaluations.append(real_evaluation(*a, **k)) or evaluations[-1])
    final = _run("sac", tmp_path / "c", "trainer.compile_env=true", "algo.loss_impl=torchrl", "algo.compile=true")
    _check_run_outputs(tmp_path / "c", final)
    assert final["updates"] > 0 and len(made) == 1 and made[0].compiled
    assert len(evaluations) == 1 and evaluations[0].evaluator.env.compiled  # the evaluation env too


@pytest.mark.parametrize("exp", ["heuristic", "heuristic_planner"])
def test_heuristic_evaluates(tmp_path, exp):
    final = _run(exp, tmp_path / "h", "trainer.eval_max_steps=40")
    _check_run_outputs(tmp_path / "h", final, trained=False)
    assert final["frames"] == 0 and not (tmp_path / "h" / "checkpoints").exists()


def test_evaluate_export_and_fly(tmp_path):
    from uavlae.evaluate import evaluate_checkpoint
    from uavlae.export import deterministic_actor_module, export_checkpoint
    from uavlae.fly import load_actor

    run_dir = tmp_path / "sac"
    _run("sac", run_dir)
    agg = evaluate_checkpoint(_cfg(f"checkpoint={run_dir}", "trainer.eval_max_steps=10", "trainer.eval_plots=1"))
    final = json.loads((run_dir / "final_metrics.json").read_text())
    assert agg["DCR"] == pytest.approx(final["eval/DCR"]) and agg["mean_return"] == pytest.approx(final["eval/mean_return"])
    assert list((run_dir / "evaluate").glob("last_frames128/episodes.csv"))

    # the exported module is the deterministic actor
    learner, env, td, expected = _deterministic_actions(run_dir)
    plain = deterministic_actor_module(learner, env.action_spec)
    torch.testing.assert_close(plain(td["observation"]), expected)
    out = export_checkpoint(run_dir, tmp_path / "actor.pt2")
    exported, meta = load_actor(out)
    torch.testing.assert_close(exported(td["observation"]), expected)
    torch.testing.assert_close(exported(td["observation"][:1]), expected[:1])  # any batch size
    assert meta["algo"] == "sac" and meta["obs_dim"] == td["observation"].shape[-1]
    assert [p.name for p in tmp_path.iterdir() if p.name.endswith(".tmp")] == []  # no temp file left
    torn = tmp_path / "torn.pt2"
    torn.write_bytes(out.read_bytes()[:100])
    with pytest.raises(ValueError, match="not an actor written by"):
        load_actor(torn)

    code = (
        "import sys, json; from uavlae.fly import main; "
        f"r = main(['--actor', {str(out)!r}, '--scenario', {str(run_dir / 'eval_set.json')!r}, '--index', '1']); "
        "assert 'torchrl' not in sys.modules, 'fly imported torchrl'; "
        "assert 0 <= r['DCR'] <= 1 and r['steps'] >= 1"
    )
    res = subprocess.run([sys.executable, "-c", code], cwd=REPO_ROOT, capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr[-3000:]
    assert '"DCR"' in res.stdout

    # the CLI: writes only the actor (no Hydra run folder, .hydra/ or log file where it runs)
    cwd = tmp_path / "cwd"
    cwd.mkdir()
    env = {**os.environ, "PYTHONPATH": str(REPO_ROOT)}
    cli = [sys.executable, "-m", "uavlae.export", f"checkpoint={run_dir}", f"out={cwd / 'a.pt2'}"]
    res = subprocess.run(cli, cwd=cwd, env=env, capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr[-3000:]
    assert sorted(p.name for p in cwd.iterdir()) == ["a.pt2"]
    torch.testing.assert_close(load_actor(cwd / "a.pt2")[0](td["observation"]), expected)
    # uavlae.evaluate's CLI prints its table once, under a line that says what it is
    cli = [sys.executable, "-m", "uavlae.evaluate", f"checkpoint={run_dir}", "trainer.eval_max_steps=10",
           f"experiment.eval_dir={tmp_path / 'ev'}", "logger.wandb.mode=disabled"]
    res = subprocess.run(cli, cwd=cwd, env=env, capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr[-3000:]
    assert res.stdout.count("DCR |") == 1 and "The paper metrics (2 episodes, one per scenario):\n" in res.stdout


@pytest.mark.parametrize("overrides", [["+exp=crossq"], ["+exp=sac", "algo=sac_ln"]], ids=["crossq", "sac_ln"])
def test_stronger_learners_train_and_export(tmp_path, overrides):
    """The learners beyond the paper through the whole loop (256 frames, 57 gradient steps), and
    their actors through ``python -m uavlae.export``: CrossQ's plain actor and SAC's LayerNorm
    actor both become the deterministic action of the trained actor."""
    from uavlae.fly import load_actor
    from uavlae.train import run

    run_dir = tmp_path / "run"
    final = run(_cfg(*overrides, f"run_dir={run_dir}", *TINY, "trainer.total_frames=256", "trainer.baselines=false"))
    _check_run_outputs(run_dir, final, frames=256)
    # B = 4, warm-up 32 frames, utd 0.25: one gradient step a step from the 8th to the 64th
    assert final["updates"] == 57 and _csv_steps(run_dir, "train/alpha")

    learner, env, td, expected = _deterministic_actions(run_dir)
    cwd = tmp_path / "cwd"
    cwd.mkdir()
    cli = [sys.executable, "-m", "uavlae.export", f"checkpoint={run_dir}", f"out={cwd / 'a.pt2'}"]
    res = subprocess.run(cli, cwd=cwd, env={**os.environ, "PYTHONPATH": str(REPO_ROOT)}, capture_output=True,
                         text=True, timeout=300)
    assert res.returncode == 0, res.stderr[-3000:]
    exported, meta = load_actor(cwd / "a.pt2")
    torch.testing.assert_close(exported(td["observation"]), expected)
    assert meta["algo"] == json.loads((run_dir / "config.json").read_text())["algo"]["name"]


def test_checkpoint_is_atomic_and_falls_back(tmp_path):
    save_checkpoint({"counters": {"frames": 1}}, tmp_path)
    save_checkpoint({"counters": {"frames": 2}}, tmp_path)
    d = tmp_path / "checkpoints"
    assert sorted(p.name for p in d.iterdir()) == [LAST, PREV]  # no temp files left
    assert load_checkpoint(tmp_path)[0]["counters"]["frames"] == 2
    (d / LAST).write_bytes((d / LAST).read_bytes()[:50])  # a torn write
    state, file = load_checkpoint(tmp_path)
    assert state["counters"]["frames"] == 1 and file.name == PREV


def _train_until_first_checkpoint_then_sigkill(run_dir: Path, args: list[str], poll_s: float, wandb_mode: str) -> None:
    """``python -m uavlae.train run_dir=RUN_DIR ARGS`` in a child, killed with SIGKILL (a crash:
    no handler runs) as soon as its first checkpoint exists; it must not have finished."""
    env = dict(os.environ, OMP_NUM_THREADS="1", WANDB_MODE=wandb_mode, WANDB_SILENT="true")
    # wandb exports WANDB_SERVICE once this process has used it; a child given it would register
    # its run with our service, which keeps the run "in use" after the SIGKILL, unlike a real crash
    env.pop("WANDB_SERVICE", None)
    cmd = [sys.executable, "-m", "uavlae.train", f"run_dir={run_dir}", *args]
    proc = subprocess.Popen(cmd, cwd=REPO_ROOT, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    last = run_dir / "checkpoints" / LAST
    deadline = time.monotonic() + 300
    while not last.exists() and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(poll_s)
    if proc.poll() is not None:
        pytest.fail(f"training ended before its first checkpoint: {proc.stderr.read().decode()[-3000:]}")
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait(30)
    proc.stderr.close()
    assert proc.returncode == -signal.SIGKILL
    assert not (run_dir / "final_metrics.json").exists()


RESUME = [
    "trainer.total_frames=384", "trainer.env_batch_size=4", "trainer.frames_per_batch=32",
    "trainer.init_random_frames=64", "trainer.batch_size=16", "trainer.utd_ratio=0.5",
    "trainer.replay_capacity=1024", "trainer.eval_episodes=2", "trainer.eval_max_steps=10",
    "trainer.eval_every_frames=128", "trainer.checkpoint_every_frames=64", "trainer.eval_plots=0",
    "trainer.progress_bar=false", "logger.wandb.mode=offline",
]


@pytest.mark.parametrize("exp", ["sac", "sac_heuristic", "sac_lag"])
def test_resume_after_sigkill_equals_uninterrupted_run(tmp_path, exp):
    # sac_heuristic: the heuristic advisor's plan cache shapes its actions, so it is checkpointed;
    # sac_lag: the cost critic, its target, the multiplier and its open measurement window
    from uavlae.train import run

    run_dir = tmp_path / "killed"
    _train_until_first_checkpoint_then_sigkill(run_dir, [f"+exp={exp}", *RESUME], poll_s=0.02, wandb_mode="offline")
    state, _ = load_checkpoint(run_dir)
    killed_at = state["counters"]["frames"]
    assert 0 < killed_at < 384
    run_id = state["logger"]["run_id"]

    resumed = run(_cfg(f"resume={run_dir}", "logger.wandb.mode=offline", "trainer.progress_bar=false"))
    assert resumed["frames"] == 384
    assert json.loads((run_dir / "config.json").read_text())["resume"].endswith(LAST)
    state, _ = load_checkpoint(run_dir)
    assert state["logger"]["run_id"] == run_id and state["counters"]["frames"] == 384
    wandb_runs = {p.name.rsplit("-", 2)[-2] + "-" + p.name.rsplit("-", 1)[-1] for p in (run_dir / "wandb").glob("offline-run-*")}
    assert wandb_runs == {run_id}
    steps = _csv_steps(run_dir, "time/fps")  # one CSV, no frame logged twice
    assert steps == sorted(set(steps)) and steps[-1] == 384

    straight = run(_cfg(f"+exp={exp}", f"run_dir={tmp_path / 'straight'}", *RESUME[:-1], "logger.wandb.mode=disabled"))
    # everything but the training wall clock (summed over the resumed parts, so below the whole)
    assert resumed.pop("wall_s") > 0 and straight.pop("wall_s") > 0
    assert resumed == straight


# ---------------------------------------------------------------------------- real local LLM

LLM_TINY = [
    "trainer.total_frames=4", "trainer.env_batch_size=2", "trainer.frames_per_batch=4",
    "trainer.init_random_frames=0", "trainer.batch_size=2", "trainer.utd_ratio=0.5",
    "trainer.replay_capacity=64", "trainer.eval_episodes=1", "trainer.eval_max_steps=3",
    "trainer.eval_every_frames=0", "trainer.checkpoint_every_frames=0", "trainer.eval_plots=1",
    "trainer.progress_bar=false", "logger.wandb.mode=disabled",
    "llm.max_tokens=96", "llm.reasoning_max_chars=40",
]


@pytest.mark.integration
@pytest.mark.parametrize("exp, extra", [("sac_llm", ["advisor.d_th=1000.0"]), ("sac_llm_fp", ["advisor.fp=1.0"]), ("llm", [])])
def test_llm_exps_against_the_local_server(tmp_path, local_llm, exp, extra):
    from uavlae.train import run

    run_dir = tmp_path / exp
    final = run(_cfg(f"+exp={exp}", f"run_dir={run_dir}", *LLM_TINY, f"llm.base_url={local_llm.base_url}",
                     f"llm.cache_path={tmp_path / 'cache.sqlite'}", *extra))
    _check_run_outputs(run_dir, final, trained=exp != "llm", frames=4)
    if exp == "llm":
        assert final["override/triggered"] > 0 and final["override/advisor/requests"] > 0
    else:
        assert final["frames"] == 4
        # every row was triggered: the LLM (or its fallback) acted on all 4 frames
        assert sum(json.loads(line.split(",")[1]) for line in
                   (run_dir / "logs/scalars/override/triggered.csv").read_text().splitlines()) == 4


LLM_RESUME = [
    "trainer.total_frames=160", "trainer.env_batch_size=2", "trainer.frames_per_batch=8",
    "trainer.init_random_frames=4", "trainer.batch_size=4", "trainer.utd_ratio=0.5",
    "trainer.replay_capacity=256", "trainer.eval_episodes=1", "trainer.eval_max_steps=3",
    "trainer.eval_every_frames=0", "trainer.checkpoint_every_frames=8", "trainer.eval_plots=0",
    "trainer.progress_bar=false", "trainer.baselines=false", "logger.wandb.mode=disabled",
    "llm.max_tokens=96", "llm.reasoning_max_chars=40",
    # every row triggered every slot; an answer held 3 slots; 6 rows asked in all (3 per row)
    "advisor.d_th=1000.0", "advisor.hold_steps=3", "advisor.max_calls=6",
]


@pytest.mark.integration
def test_sac_llm_resume_after_sigkill_replays_the_uninterrupted_run(tmp_path, local_llm):
    from uavlae.train import run

    cache = tmp_path / "cache.sqlite"
    llm = [f"llm.base_url={local_llm.base_url}", f"llm.cache_path={cache}"]
    straight = run(_cfg("+exp=sac_llm", f"run_dir={tmp_path / 'straight'}", *LLM_RESUME, *llm, "llm.cache_mode=read_write"))
    assert straight["frames"] == 160 and straight["override/calls_used"] == 6
    # 160 frames = 80 slots of 2 rows, all triggered; 6 asked, the held slots after them, then the actor
    assert straight["override/triggered"] == 160 and straight["override/budget_skipped"] > 0
    summary = json.loads((tmp_path / "straight" / "summary.json").read_text())
    assert summary["override"]["advisor/calls"] >= 1  # live answers, now in the cache
    assert summary["overlap_s"] > 0  # gradient steps ran while a request was in flight

    run_dir = tmp_path / "killed"
    _train_until_first_checkpoint_then_sigkill(
        run_dir, ["+exp=sac_llm", *LLM_RESUME, *llm, "llm.cache_mode=replay_only"], poll_s=0.005, wandb_mode="disabled")
    state, _ = load_checkpoint(run_dir)
    killed_at = state["counters"]["frames"]
    assert 0 < killed_at < 160

    # the saved config replays from the cache only: a request the first run did not make is an error
    resumed = run(_cfg(f"resume={run_dir}", "trainer.progress_bar=false", "logger.wandb.mode=disabled"))
    assert resumed.pop("wall_s") > 0 and straight.pop("wall_s") > 0  # the training wall clock differs run to run
    assert _replayed(resumed) == _replayed(straight)


def _replayed(final: dict) -> dict:
    """A run's final metrics less what a replay does not spend again: the cost's calls, tokens,
    money and seconds (its rows are replayed exactly)."""
    spent = ("cost/llm_", "cost/tokens_", "cost/money", "cost/wait_s")
    return {k: v for k, v in final.items() if not k.startswith(spent)}


LLM_AMORTIZE = [*[a for a in LLM_RESUME if not a.startswith(("advisor.hold_steps", "advisor.max_calls"))],
                # a small student that answers after 8 LLM answers, is never unsure, and has one
                # row in ten audited: the LLM answers the warm-up and the audits, the student the rest
                "advisor.amortize=true", "advisor.student.min_answers=8", "advisor.student.unsure=10.0",
                "advisor.student.novel_min=0", "advisor.student.audit_fraction=0.1", "advisor.student.hidden=16",
                "advisor.student.batch_size=16", "advisor.student.updates_per_answer=1.0"]


@pytest.mark.integration
def test_amortized_sac_llm_advises_every_trigger_and_resumes_by_replay(tmp_path, local_llm):
    """SAC+LLM with the student, against the real local model: every triggered row is advised,
    by the LLM or the student; killed and resumed with the answers replayed from the cache, the
    run (student included) ends exactly as the uninterrupted one."""
    from uavlae.train import run

    cache = tmp_path / "cache.sqlite"
    llm = [f"llm.base_url={local_llm.base_url}", f"llm.cache_path={cache}"]
    straight = run(_cfg("+exp=sac_llm", f"run_dir={tmp_path / 'straight'}", *LLM_AMORTIZE, *llm))
    rows = {k: straight[f"override/source/{k}"] for k in ("llm", "student", "fallback", "policy")}
    assert straight["override/triggered"] == 160 and rows["policy"] == 0  # every row triggered, none left to the actor
    assert rows["llm"] + rows["student"] + rows["fallback"] == 160 and rows["student"] > 80
    assert straight["override/advisor/student/llm_rows"] == rows["llm"] + rows["fallback"] >= 8
    assert straight["cost/rows_student"] == rows["student"] and straight["cost/tokens_in"] > 0
    assert "cost/money" not in straight  # the local model has no price (NaN, not a final metric)
    summary = (tmp_path / "straight" / "summary.json").read_text()
    assert '"rows_student"' in summary

    run_dir = tmp_path / "killed"
    _train_until_first_checkpoint_then_sigkill(
        run_dir, ["+exp=sac_llm", *LLM_AMORTIZE, *llm, "llm.cache_mode=replay_only"], poll_s=0.005,
        wandb_mode="disabled")
    assert 0 < load_checkpoint(run_dir)[0]["counters"]["frames"] < 160
    resumed = run(_cfg(f"resume={run_dir}", "trainer.progress_bar=false", "logger.wandb.mode=disabled"))
    assert resumed.pop("wall_s") > 0 and straight.pop("wall_s") > 0
    assert _replayed(resumed) == _replayed(straight)
    assert resumed["cost/llm_calls"] == 0  # all of it from the cache


def test_full_speed_by_hand():
    """uavlae.fly --full-speed's action: (0.3, 0.4) is 5 m/s at v_max = 10, so (0.6, 0.8); (1, 1)
    is clipped to 10 m/s on the diagonal, (0.7071, 0.7071) either way; (0.03, 0) is 0.3 m/s, under
    the 0.5 m/s floor, and stays; (1.6, 0) from a wider box is (1, 0)."""
    from uavlae.fly import full_speed

    out = full_speed(torch.tensor([[0.3, 0.4], [1.0, 1.0], [0.03, 0.0], [1.6, 0.0]]), 10.0)
    torch.testing.assert_close(out, torch.tensor([[0.6, 0.8], [0.70711, 0.70711], [0.03, 0.0], [1.0, 0.0]]),
                               atol=1e-5, rtol=0)


@pytest.mark.parametrize("actor_mode, scale, cruise", [("mean", 1.0, False), ("sample", 1.0, False), ("sample", 2.0, True)])
def test_safety_filter_run_exports_a_pilot_that_flies_as_the_evaluator(tmp_path, actor_mode, scale, cruise):
    """A run trained through the safety filter: the filtered action is stored and counted, the
    evaluation flies the actor through its filter and alone, the export is the pilot (actor and
    filter in one program) and `uavlae.fly --all` reproduces both evaluations exactly, with the
    actor's mean action and with draws from its policy (trainer.eval_actor=sample: the same
    seeded noise stream in the evaluator and in fly), also from an actor whose box is twice the
    env's (algo.action_scale=2) through a filter that cruises (safety_filter.cruise)."""
    from uavlae.envs import make_env_config, world
    from uavlae.export import PILOT_STATE_KEYS, export_checkpoint
    from uavlae.fly import PILOT_STATE_KEYS as FLY_KEYS, load_actor, main as fly_main, perceived, scenario_tensors
    from uavlae.policies.safety import SafetyFilter

    assert FLY_KEYS == PILOT_STATE_KEYS
    run_dir = tmp_path / "filtered"
    final = _run("sac", run_dir, "safety_filter.mode=train_and_deploy", "trainer.eval_max_steps=null",
                 "trainer.eval_episodes=3", f"trainer.eval_actor={actor_mode}", f"algo.action_scale={scale}", f"safety_filter.cruise={str(cruise).lower()}")
    assert 0 <= final["safety/train/intervention_rate"] <= 1 and final["safety/train/rows"] == 128
    assert "eval/actor/DCR" in final and "eval/safety/intervention_rate" in final
    summary = json.loads((run_dir / "summary.json").read_text())
    assert {"sac (actor + safety filter)", "sac (actor alone)"} <= set(summary["metrics"])

    out = export_checkpoint(run_dir, tmp_path / "pilot.pt2")
    pilot, meta = load_actor(out)
    assert meta["kind"] == "pilot" and meta["safety_filter"]["mode"] == "train_and_deploy"
    assert meta["safety_filter"]["cruise"] is cruise
    assert meta["actor"] == actor_mode and meta["noise_dim"] == 2 and meta["noise_seed"] == 12345
    # the exported filter acts as the in-process one on the same perceived state
    env_cfg = make_env_config(meta["env"])
    scen = json.loads((run_dir / "eval_set.json").read_text())
    state = world.initial_state(scenario_tensors(scen[0], env_cfg), env_cfg)
    state["position"] = torch.tensor([[60.0, 30.0]])
    s = perceived(state, env_cfg)
    s_full = dict(s)
    s_full.update(world.nearest_distances(s_full, env_cfg))
    zero = torch.zeros(1, 2)
    raw = pilot(s, torch.tensor(False), zero)
    expected, _, _ = SafetyFilter(env_cfg, meta["safety_filter"]).filter_action(s_full, raw)
    torch.testing.assert_close(pilot(s, torch.tensor(True), zero), expected)
    # --full-speed, a diagnosis: the same wish in its direction at v_max, then the pilot's filter
    from uavlae.fly import full_speed, policy_of

    fast = policy_of(pilot, meta, env_cfg, act="mean", at_full_speed=True)(state)
    wish = full_speed(raw, env_cfg.motion.v_max)
    expected_fast, _, _ = SafetyFilter(env_cfg, meta["safety_filter"]).filter_action(s_full, wish)
    torch.testing.assert_close(fast, expected_fast)
    # zero noise is the actor's mean action; a draw is another action inside the actor's box
    noisy = pilot(s, torch.tensor(False), torch.tensor([[1.5, -2.0]]))
    assert not torch.allclose(noisy, raw) and bool((noisy.abs() <= scale).all())

    for extra, prefix in (([], "eval/"), (["--no-filter"], "eval/actor/")):
        res = fly_main(["--actor", str(out), "--scenario", str(run_dir / "eval_set.json"), "--all", *extra])
        for k in ("DCR", "CR", "SLR", "RVR", "ECR"):
            assert res["metrics"][k] == pytest.approx(final[prefix + k], abs=1e-6), (prefix, k)
        if not extra:
            flown = res
    if actor_mode == "sample":  # the draws, not the mean: flying the mean instead gives other flights
        mean = fly_main(["--actor", str(out), "--scenario", str(run_dir / "eval_set.json"), "--all", "--act", "mean"])
        assert mean["metrics"]["ECR"] != pytest.approx(flown["metrics"]["ECR"], abs=1e-6)
        # uavlae.evaluate flies the run's own mode unless its command line names one, each in its folder
        from uavlae.evaluate import evaluate_checkpoint

        tiny = [o for o in TINY if not o.startswith(("trainer.eval_max_steps", "trainer.eval_episodes"))]
        again = evaluate_checkpoint(_cfg(f"checkpoint={run_dir}", *tiny))
        assert again["ECR"] == pytest.approx(final["eval/ECR"], abs=1e-9)
        assert (run_dir / "evaluate" / "last_frames128_sample" / "metrics.json").is_file()
        as_mean = evaluate_checkpoint(_cfg(f"checkpoint={run_dir}", *tiny, "trainer.eval_actor=mean"),
                                      ["trainer.eval_actor=mean"])
        assert as_mean["ECR"] == pytest.approx(mean["metrics"]["ECR"], abs=1e-6)
    # the stalls diagnosis flies the same flights: its unlanded count is the evaluation's, and
    # the filter changed the wish by at most the largest velocity difference (2 v_max)
    from uavlae.experiments.pilot import stalls
    found = stalls(out, run_dir / "eval_set.json")
    assert found["episodes"] == 3 and found["unlanded"] == 3 - sum(flown["landed"])
    assert 0 <= found["unlanded_held"] <= found["unlanded_at_obstacle"] <= found["unlanded"]
    assert 0 <= found["landed_filter_change_mean"] <= 2 * env_cfg.motion.v_max or found["unlanded"] == 3
    # speeds are the env's (|v| <= v_max); nothing landed, nothing to average
    for k in ("landed_wish_speed_mean", "landed_speed_mean"):
        assert (0 <= found[k] <= env_cfg.motion.v_max + 1e-6) if found["unlanded"] < 3 else math.isnan(found[k])


def test_keep_best_keeps_the_networks_of_the_best_evaluation(tmp_path):
    """Evaluations at 64 and 128 frames. best.pt holds the networks of the one with the highest
    DCR + SLR - CR - RVR (the earlier on a tie), and uavlae.evaluate on best.pt flies them to the
    numbers that evaluation recorded; last.pt stays the run's end."""
    from uavlae.checkpoint import load_checkpoint
    from uavlae.selection import selection_score

    assert selection_score({"DCR": 0.9, "SLR": 0.75, "CR": 0.0625, "RVR": 0.0}) == pytest.approx(1.5875)
    assert selection_score({"DCR": 0.9, "SLR": float("nan"), "CR": 0.0, "RVR": 0.0}) == float("-inf")
    run_dir = tmp_path / "r"
    final = _run("sac", run_dir, "trainer.keep_best=true", "trainer.baselines=false")
    scores = {}
    for f in (64, 128):
        m = json.loads((run_dir / "eval" / f"frames_{f:09d}" / "metrics.json").read_text())
        scores[f] = selection_score(m)
    want = 64 if scores[64] >= scores[128] else 128
    assert final["best/frames"] == want and final["best/score"] == pytest.approx(scores[want])
    best, _ = load_checkpoint(run_dir / "checkpoints" / "best.pt")
    assert best["counters"]["frames"] == want and best.get("replay_buffer") is None
    last, _ = load_checkpoint(run_dir)
    assert last["counters"]["frames"] == 128
    from uavlae.evaluate import evaluate_checkpoint

    got = evaluate_checkpoint(_cfg(f"checkpoint={run_dir / 'checkpoints' / 'best.pt'}", *TINY,
                                  f"experiment.eval_dir={tmp_path / 'again'}"))
    recorded = json.loads((run_dir / "eval" / f"frames_{want:09d}" / "metrics.json").read_text())
    for k in ("DCR", "SLR", "CR", "RVR", "ECR"):
        assert got[k] == pytest.approx(recorded[k], abs=1e-9)


def test_teacher_labels_reach_the_replay_buffer(tmp_path):
    """`+exp=pilot advisor.label_all=true`: every stored row carries the planner's label, the
    rows the actor flew itself included (the phase-out ends at 64 of 256 frames), and the
    checkpoint keeps them for a resume."""
    run_dir = tmp_path / "labels"
    _run("pilot", run_dir, "advisor.label_all=true", "advisor.phase_out_frames=64", "trainer.total_frames=256")
    rows = torch.load(run_dir / "checkpoints" / LAST, weights_only=False)["replay_buffer"]["filled_rows"]
    assert int(rows["advice_ok"].sum()) == 256
    assert float(rows["advice"].abs().max()) <= 1.0
    assert 0 < int((rows["action_source"] == 2).sum()) < 128  # the planner acted on a few early rows only


def test_the_evaluation_with_the_advisor_flies_the_actor_by_draws_as_the_evaluation_does(tmp_path):
    """trainer.eval_actor=sample with an advisor that never acts (proximity, d_th = 0 m: no
    distance is below it): the actor with its advisor flies the evaluation exactly as the actor
    alone does, draws and all, so the two rows differ by the advisor alone."""
    final = _run("sac_heuristic", tmp_path / "run", "advisor.d_th=0", "trainer.eval_actor=sample",
                 "trainer.baselines=false")
    assert final["advised/override/triggered"] == 0
    for k in ("DCR", "CR", "SLR", "RVR", "ECR"):
        assert final[f"advised/{k}"] == final[f"eval/{k}"], k
