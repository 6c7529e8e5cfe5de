"""A command as a user meets it, each case a real ``python -m uavlae.train`` process: a world that
measures nothing refused before any work, one line naming the key, no run folder left; a missing
API key refused naming its variable; a bad value, an unknown key, a bad scenario file and a
missing resume folder each one message without a traceback or Hydra's hint; a SIGTERM during
the actor's flight with its advisor honoured at that step, the checkpoint kept and the resume
line printed, and the resumed run finishing under the with-advisor budget. Then the pieces
in-process: a bug keeps its traceback, what a failed job leaves in its folders."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from tests.test_train import _cfg
from uavlae.checkpoint import load_checkpoint
from uavlae.factories import REPO_ROOT

pytestmark = pytest.mark.timeout(600)


def _env(**more: str) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if k not in ("WANDB_SERVICE", "UAVLAE_DEBUG", "HYDRA_FULL_ERROR")}
    env.update(OMP_NUM_THREADS="1", UAVLAE_NUM_THREADS="1", WANDB_MODE="disabled", PYTHONPATH=str(REPO_ROOT), **more)
    return env


def _train(cwd: Path, *args: str, env: dict[str, str] | None = None) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "uavlae.train", *args], cwd=cwd, env=env or _env(),
                          capture_output=True, text=True, timeout=300)


def _refused(proc: subprocess.CompletedProcess, message: str) -> None:
    """Exit status 2 and stderr exactly ``error: <message>``: no traceback, no Hydra hint."""
    assert proc.returncode == 2, proc.stderr[-3000:]
    assert proc.stderr == f"error: {message}\n", proc.stderr
    assert "frames/s" not in proc.stdout  # nothing trained


def _no_run_folder(cwd: Path) -> None:
    assert not [p for p in (cwd / "runs").rglob("*") if not p.is_dir()]  # Hydra's folder went with the refusal


def test_a_world_without_ges_is_refused_before_any_work(tmp_path):
    """The issue's first case: DCR would be 0/0, and the default run would train for an hour."""
    proc = _train(tmp_path, "+exp=sac", "env.ge.count.min=0", "env.ge.count.max=0")
    _refused(proc, "env.ge.count.min=0: a scenario without GEs has no data to collect (DCR = collected / total is "
                   "0/0) and lands at once (every GE is empty); allowed: 1 <= env.ge.count.min <= env.ge.count.max")
    _no_run_folder(tmp_path)


def test_a_missing_api_key_is_refused_with_one_line_naming_its_variable(tmp_path):
    env = _env()
    env.pop("DEEPSEEK_API_KEY", None)
    proc = _train(tmp_path, "+exp=sac_llm", "llm=deepseek", env=env)
    _refused(proc, "llm.api_key_env: the environment variable DEEPSEEK_API_KEY is not set (or empty), and "
                   "https://api.deepseek.com/v1 answers nobody without a key; export DEEPSEEK_API_KEY=<your key> "
                   "and run again")
    _no_run_folder(tmp_path)


def _bad_set(tmp_path: Path) -> list[str]:
    data = json.loads((REPO_ROOT / "results" / "eval_set_32.json").read_text())[:3]
    data[1]["rz"] = [[400.0, 300.0, 560.0, 380.0]]  # past the area's east edge
    (tmp_path / "set.json").write_text(json.dumps(data))
    return ["+exp=sac", f"trainer.eval_set={tmp_path / 'set.json'}"]


@pytest.mark.parametrize("case", ["bad_value", "unknown_key", "bad_scenario_file", "missing_resume_folder"])
def test_an_error_is_one_message_without_a_traceback(tmp_path, case):
    args, message = {
        "bad_value": (["+exp=sac", "trainer.total_frames=-5"],
                      "invalid trainer config:\n  trainer.total_frames: Input should be greater than or equal to 1 "
                      "(got -5)"),
        "unknown_key": (["+exp=sac", "trainer.foo=1"],
                        "Could not override 'trainer.foo'.\nTo append to your config use +trainer.foo=1\n"
                        "Key 'foo' is not in struct\n    full_key: trainer.foo\n    object_type=dict"),
        "bad_scenario_file": (_bad_set(tmp_path), f"{tmp_path / 'set.json'}: scenario 1 breaks: rz rectangle "
                                                  "malformed or outside the area"),
        "missing_resume_folder": (["resume=runs/sac/none"],
                                  "no checkpoint at runs/sac/none (looked for last.pt / prev.pt in it and in its "
                                  "checkpoints/)"),
    }[case]
    _refused(_train(tmp_path, *args), message)
    _no_run_folder(tmp_path)


def test_uavlae_debug_shows_the_traceback_of_a_user_error(tmp_path):
    proc = _train(tmp_path, "+exp=sac", "trainer.total_frames=-5", env=_env(UAVLAE_DEBUG="1"))
    assert proc.returncode == 1 and "Traceback (most recent call last)" in proc.stderr
    assert proc.stderr.rstrip().endswith("trainer.total_frames: Input should be greater than or equal to 1 (got -5)")


class _Lines:
    """A child's stdout read as it comes, waiting for a line that holds some text."""

    def __init__(self, stream):
        self.lines: list[str] = []
        self.seen = threading.Event()
        self.want = ""
        threading.Thread(target=self._read, args=(stream,), daemon=True).start()

    def _read(self, stream) -> None:
        for line in iter(stream.readline, ""):
            self.lines.append(line)
            if self.want and self.want in line:
                self.seen.set()

    def wait_for(self, text: str, timeout: float) -> bool:
        self.want = text
        if any(text in ln for ln in self.lines):
            return True
        return self.seen.wait(timeout)


@pytest.mark.integration
def test_sigterm_during_the_with_advisor_evaluation_keeps_the_checkpoint_and_prints_the_resume_line(
        tmp_path, local_llm):
    """The issue's +exp=sac_llm case, made small: training asks the LLM nothing (advisor.max_calls=0),
    then the actor flies with it at every row (d_th 1000 m, no budget), every row a question to the
    local LLM. A SIGTERM once its progress shows is honoured at the end of that step: exit
    128 + 15, the resume line, the checkpoint of the finished training, no final metrics. Resumed
    with a budget of two rows, the run finishes, and its summary says the budget bit."""
    from uavlae.summary import format_summary
    from uavlae.train import run

    run_dir = tmp_path / "run"
    args = ["+exp=sac_llm", f"run_dir={run_dir}", "trainer.total_frames=16", "trainer.env_batch_size=2",
            "trainer.frames_per_batch=8", "trainer.init_random_frames=8", "trainer.batch_size=8",
            "trainer.replay_capacity=64", "trainer.eval_episodes=2", "trainer.eval_max_steps=40",
            "trainer.eval_every_frames=0", "trainer.checkpoint_every_frames=0", "trainer.eval_plots=0",
            "trainer.progress_bar=false", "trainer.progress_first_s=0", "trainer.progress_every_s=0.5",
            "trainer.baselines=false", "trainer.eval_advisor_max_calls=null", "advisor.max_calls=0",
            "advisor.d_th=1000.0", f"llm.base_url={local_llm.base_url}", "llm.cache_mode=off",
            "logger.wandb.mode=disabled"]
    proc = subprocess.Popen([sys.executable, "-m", "uavlae.train", *args], cwd=tmp_path, env=_env(),
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    out = _Lines(proc.stdout)
    try:
        assert out.wait_for("sac_llm with its advisor: step", 300), "".join(out.lines)[-3000:]
        proc.send_signal(signal.SIGTERM)
        t0 = time.monotonic()
        err = proc.stderr.read()
        proc.wait(120)
        took = time.monotonic() - t0
    finally:
        proc.kill()
    assert proc.returncode == 128 + signal.SIGTERM, err[-3000:]
    assert err.strip().splitlines()[-1] == (
        "stopped by signal 15 during the final evaluations, after training 16 frames (checkpointed); continue with: "
        f"python -m uavlae.train resume={run_dir}")
    assert took < 60  # a step of two rows to the LLM, not the whole evaluation
    assert load_checkpoint(run_dir)[0]["counters"]["frames"] == 16
    assert not (run_dir / "final_metrics.json").exists()

    final = run(_cfg(f"resume={run_dir}", "trainer.eval_advisor_max_calls=2", "logger.wandb.mode=disabled"),
                ["trainer.eval_advisor_max_calls=2"])
    assert final["frames"] == 16 and final["advised/override/budget_skipped"] > 0
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["advised_eval"]["max_calls"] == 2 and summary["advised_eval"]["llm_requests"] == 2
    assert summary["override"].get("advisor/requests", 0) == 0  # training asked nothing: its count stays apart
    assert "trainer.eval_advisor_max_calls=2 rows were asked, then the actor flew" in format_summary(summary)


# ---------------------------------------------------------------------------- the pieces, in-process


def test_a_bug_keeps_its_traceback_and_a_user_error_is_one_line(capsys, monkeypatch):
    from uavlae.entry import command
    from uavlae.errors import ConfigError

    monkeypatch.delenv("UAVLAE_DEBUG", raising=False)
    monkeypatch.delenv("HYDRA_FULL_ERROR", raising=False)

    def bug() -> None:
        raise KeyError("a bug")

    def refused() -> None:
        raise ConfigError("trainer.x=1: not a setting")

    with pytest.raises(KeyError):
        command(bug)
    with pytest.raises(SystemExit) as exit_:
        command(refused)
    assert exit_.value.code == 2 and capsys.readouterr().err == "error: trainer.x=1: not a setting\n"
    assert "HYDRA_FULL_ERROR" not in os.environ  # set for Hydra while the command ran, then put back
    monkeypatch.setenv("UAVLAE_DEBUG", "1")
    with pytest.raises(ConfigError):
        command(refused)


def test_a_failed_job_removes_a_folder_of_hydras_files_and_leaves_error_txt_beside_a_run(tmp_path):
    from uavlae.entry import recorded
    from uavlae.errors import ConfigError

    hydra_only, run, other = tmp_path / "h", tmp_path / "r", tmp_path / "o"
    for d in (hydra_only, run, other):
        (d / ".hydra").mkdir(parents=True)
        (d / ".hydra" / "overrides.yaml").write_text("[]\n")
        (d / "train.log").write_text("")
    (run / "config.json").write_text("{}")
    (other / "notes.txt").write_text("mine")
    for hydra_dir, run_dir in ((hydra_only, hydra_only), (run, run), (other, other)):
        with pytest.raises(ConfigError), recorded(hydra_dir, lambda d=run_dir: d, "train.log"):
            raise ConfigError("env.ge.count.min=0: no GE")
    assert not hydra_only.exists()
    assert (run / "error.txt").read_text() == "env.ge.count.min=0: no GE\n" and (run / ".hydra").is_dir()
    assert (other / "notes.txt").is_file() and (other / ".hydra").is_dir() and not (other / "error.txt").exists()
    with pytest.raises(ZeroDivisionError), recorded(None, lambda: run, "train.log"):
        1 / 0  # a bug: its traceback beside the run
    assert (run / "error.txt").read_text().startswith("Traceback (most recent call last)")


def test_the_libraries_own_messages_go_to_the_runs_log_unless_asked_for(tmp_path, monkeypatch):
    """torchrl's coloured console handler gives way to the root logger's file handler (Hydra's
    train.log in the run folder); wandb is silenced unless the environment says otherwise."""
    import logging

    from uavlae.runlog import route_library_output

    monkeypatch.delenv("WANDB_SILENT", raising=False)
    torchrl, root = logging.getLogger("torchrl"), logging.getLogger()
    before = list(torchrl.handlers)
    log_file = logging.FileHandler(tmp_path / "train.log")
    root.addHandler(log_file)
    try:
        route_library_output(True)  # asked for: nothing changes
        assert torchrl.handlers == before and "WANDB_SILENT" not in os.environ
        route_library_output(False)
        consoles = [h for h in torchrl.handlers
                    if isinstance(h, logging.StreamHandler) and not isinstance(h, logging.FileHandler)]
        assert consoles == [] and log_file in torchrl.handlers and os.environ["WANDB_SILENT"] == "true"
        torchrl.info("Initialized LazyTensorStorage")
        log_file.flush()
        assert "Initialized LazyTensorStorage" in (tmp_path / "train.log").read_text()
    finally:
        root.removeHandler(log_file)
        torchrl.handlers[:] = before
        log_file.close()
