"""A run's lifecycle, against real processes where a process is the point: one process owns a run
folder; SIGTERM ends a run with a checkpoint and the same command with ``resume=`` continues it
exactly; a resume that conflicts with the recorded run is refused, naming each key, and an
extension of the frame budget is honoured; a rerun after a kill before the first checkpoint
starts clean; bad input stops before anything is written; files follow the umask; checkpoints
are the size of what they hold; the package has no import cycle and no overlong function."""

from __future__ import annotations

import ast
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

from tests.test_train import REPO_ROOT, RESUME, TINY, _cfg, _csv_steps
from uavlae.checkpoint import LAST, load_checkpoint


def _child(run_dir: Path, *args: str) -> subprocess.Popen:
    env = dict(os.environ, OMP_NUM_THREADS="1", WANDB_MODE="disabled", WANDB_SILENT="true")
    env.pop("WANDB_SERVICE", None)
    cmd = [sys.executable, "-m", "uavlae.train", f"run_dir={run_dir}", *args]
    return subprocess.Popen(cmd, cwd=REPO_ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def _wait_for(path: Path, proc: subprocess.Popen, timeout: float = 300) -> None:
    deadline = time.monotonic() + timeout
    while not path.exists() and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.02)
    if proc.poll() is not None:
        pytest.fail(f"the run ended before {path.name} appeared: {proc.stderr.read()[-3000:]}")


def test_a_second_process_is_refused_while_the_first_owns_the_folder(tmp_path):
    run_dir = tmp_path / "r"
    first = _child(run_dir, "+exp=sac", *RESUME[:-1], "logger.wandb.mode=disabled", "trainer.total_frames=100000")
    try:
        _wait_for(run_dir / "config.json", first)
        t0 = time.monotonic()
        second = _child(run_dir, "+exp=sac", *RESUME[:-1], "logger.wandb.mode=disabled")
        out, err = second.communicate(timeout=120)
        assert second.returncode != 0 and time.monotonic() - t0 < 60
        assert f"run folder {run_dir} is in use by process {first.pid}" in err
        assert first.poll() is None  # the owner runs on, untouched
    finally:
        first.kill()
        first.communicate()


@pytest.mark.parametrize("exp", ["sac_heuristic", "ppo"])
def test_sigterm_checkpoints_and_resume_continues_exactly(tmp_path, exp):
    from uavlae.train import run

    on_policy = ["algo.minibatch_size=16", "algo.epochs=1"] if exp == "ppo" else []
    args = [f"+exp={exp}", *RESUME[:-1], "logger.wandb.mode=disabled", *on_policy]
    run_dir = tmp_path / "stopped"
    proc = _child(run_dir, *args)
    _wait_for(run_dir / "checkpoints" / LAST, proc)
    proc.send_signal(signal.SIGTERM)
    out, err = proc.communicate(timeout=300)
    if proc.returncode == 0:  # it finished before the signal arrived: nothing to check
        pytest.skip("the run ended before SIGTERM reached it")
    assert proc.returncode == 128 + signal.SIGTERM
    assert f"continue with: python -m uavlae.train resume={run_dir}" in err
    stopped_at = load_checkpoint(run_dir)[0]["counters"]["frames"]
    assert 0 < stopped_at < 384 and not (run_dir / "final_metrics.json").exists()
    resumed = run(_cfg(f"resume={run_dir}", "logger.wandb.mode=disabled", "trainer.progress_bar=false"))
    straight = run(_cfg(*args, f"run_dir={tmp_path / 'straight'}"))
    assert resumed.pop("wall_s") > 0 and straight.pop("wall_s") > 0
    assert resumed == straight
    steps = _csv_steps(run_dir, "time/fps")
    assert steps == sorted(set(steps)) and steps[-1] == 384  # no frame logged twice


def test_one_stop_delivered_twice_still_checkpoints(tmp_path):
    """SIGTERM sent to the process group and passed on again by a parent (GNU make, timeout)
    arrives twice at once: still one graceful stop with its checkpoint, not an abrupt end."""
    run_dir = tmp_path / "twice"
    # batches of 2,048 frames and 1,024 updates: the stop waits a second or more for its batch
    proc = _child(run_dir, "+exp=sac", *RESUME[:-1], "logger.wandb.mode=disabled", "trainer.total_frames=100000",
                  "trainer.frames_per_batch=2048", "trainer.env_batch_size=16", "trainer.checkpoint_every_frames=2048")
    _wait_for(run_dir / "checkpoints" / LAST, proc)
    proc.send_signal(signal.SIGTERM)
    time.sleep(0.3)  # the second after the first was handled (sent together, they merge into one)
    proc.send_signal(signal.SIGTERM)
    out, err = proc.communicate(timeout=300)
    # stopped after its checkpoint (the repeat may still end the process once the stop is done)
    assert "stopped by signal 15 at " in err and f"continue with: python -m uavlae.train resume={run_dir}" in err
    assert 0 < load_checkpoint(run_dir)[0]["counters"]["frames"] < 100000


def test_a_stop_asked_again_later_ends_at_once():
    """The same signal within GracefulStop.SAME_STOP_S (2 s) of the first is that stop again:
    nothing more happens; 2.1 s after it, it is a second request: the handler that was there
    before runs (by default, the end of the process)."""
    from uavlae.lifecycle import GracefulStop

    now, seen = [100.0], []
    original = signal.signal(signal.SIGTERM, lambda *_: seen.append("previous"))
    try:
        with GracefulStop(clock=lambda: now[0]) as stop:
            os.kill(os.getpid(), signal.SIGTERM)
            now[0] += 1.9
            os.kill(os.getpid(), signal.SIGTERM)
            assert stop.signum == signal.SIGTERM and seen == []
            now[0] += 0.2
            os.kill(os.getpid(), signal.SIGTERM)
            assert seen == ["previous"]
    finally:
        signal.signal(signal.SIGTERM, original)


def test_a_wait_without_steps_ends_at_once_on_a_stop():
    """Inside interruptible() (a local LLM server starting) the first SIGTERM raises StopRequested
    out of the wait itself; outside it, the stop is only noted, and check() raises it at the next
    step boundary."""
    from uavlae.lifecycle import GracefulStop, StopRequested

    with GracefulStop() as stop:
        t0 = time.monotonic()
        with pytest.raises(StopRequested), stop.interruptible():
            os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(30)  # the wait: cut short, not slept out
        assert time.monotonic() - t0 < 5 and stop.signum == signal.SIGTERM
        with pytest.raises(StopRequested):
            stop.interruptible().__enter__()  # asked before the wait begins: it does not begin
    with GracefulStop() as stop:
        stop.check()  # nothing asked: nothing raised
        os.kill(os.getpid(), signal.SIGTERM)
        assert stop.requested  # noted, the work goes on to its step boundary
        with pytest.raises(StopRequested):
            stop.check()


def test_resume_refuses_a_conflict_and_honours_an_extension(tmp_path):
    from uavlae.train import run

    run_dir = tmp_path / "s"
    run(_cfg("+exp=sac", f"run_dir={run_dir}", *TINY))
    with pytest.raises(ValueError, match=r"algo.name: recorded 'sac', asked 'ppo'") as err:
        run(_cfg("+exp=ppo", f"resume={run_dir}", "logger.wandb.mode=disabled"))
    assert "name: recorded 'sac', asked 'ppo'" in str(err.value)
    with pytest.raises(ValueError, match=r"algo.actor_lr: recorded 0.0001, asked 0.003"):
        run(_cfg(f"resume={run_dir}", "algo.actor_lr=0.003"))
    done = run(_cfg(f"resume={run_dir}"))  # nothing asked: finished, kept as it is
    assert done["frames"] == 128
    extended = run(_cfg(f"resume={run_dir}", "trainer.total_frames=192", "logger.wandb.mode=disabled",
                        "trainer.progress_bar=false"))
    assert extended["frames"] == 192 and extended["updates"] > done["updates"]
    assert json.loads((run_dir / "config.json").read_text())["trainer"]["total_frames"] == 192
    assert _csv_steps(run_dir, "eval/DCR")[-1] == 192


def test_a_new_run_into_a_used_folder_is_refused(tmp_path):
    from uavlae.train import run

    run(_cfg("+exp=sac", f"run_dir={tmp_path / 'r'}", *TINY))
    with pytest.raises(ValueError, match=r"holds a run already: continue it with resume="):
        run(_cfg("+exp=sac", f"run_dir={tmp_path / 'r'}", *TINY))


def test_a_rerun_after_a_kill_before_the_first_checkpoint_starts_clean(tmp_path, monkeypatch):
    """What a kill before the first checkpoint leaves: the config, a CSV row, an evaluation
    folder; the rerun (a sweep's, with reuse) removes them and logs each frame once."""
    from uavlae.train import run

    monkeypatch.chdir(tmp_path)
    args = ["+exp=sac", "run_dir=r", "experiment.reuse=true", *TINY]
    first = run(_cfg(*args))
    for p in ("final_metrics.json", "summary.json"):
        (tmp_path / "r" / p).unlink()
    for p in (tmp_path / "r" / "checkpoints").iterdir():
        p.unlink()
    rerun = run(_cfg(*args))
    assert rerun.pop("wall_s") > 0 and first.pop("wall_s") > 0 and rerun == first
    steps = _csv_steps(tmp_path / "r", "time/fps")
    assert steps == sorted(set(steps))


def _nothing_written(run_dir: Path) -> None:
    assert not run_dir.exists() or not any(p.name != ".hydra" for p in run_dir.iterdir())


@pytest.mark.parametrize("bad, message", [
    (["trainer.total_frames=16"], r"total_frames=16 is below one collector batch \(trainer.frames_per_batch=32\)"),
    (["trainer.total_frames=128", "trainer.init_random_frames=5000"],
     r"total_frames=128 does not exceed the random warm-up \(trainer.init_random_frames=5000\)"),
    (["device=cuda"], r"device='cuda': this torch .* sees no CUDA device"),
])
def test_bad_budgets_and_devices_stop_before_anything_is_written(tmp_path, bad, message):
    from uavlae.train import run

    if "device=cuda" in bad and torch.cuda.is_available():
        pytest.skip("this machine has a CUDA device")
    with pytest.raises(ValueError, match=message):
        run(_cfg("+exp=sac", f"run_dir={tmp_path / 'r'}", *TINY, *bad))
    _nothing_written(tmp_path / "r")


def test_a_missing_eval_set_is_an_error_unless_asked_to_sample(tmp_path):
    from uavlae.train import run

    missing = tmp_path / "sets" / "none.json"
    with pytest.raises(FileNotFoundError, match=r"trainer.eval_set=.*none.json' does not exist.*sample_eval_set=true"):
        run(_cfg("+exp=sac", f"run_dir={tmp_path / 'r'}", *TINY, f"trainer.eval_set={missing}"))
    assert not missing.exists() and not (tmp_path / "r" / "config.json").exists()
    run(_cfg("+exp=sac", f"run_dir={tmp_path / 'r'}", *TINY, f"trainer.eval_set={missing}", "trainer.sample_eval_set=true"))
    assert missing.is_file()


def _write_set(path: Path, edit) -> None:
    data = json.loads((REPO_ROOT / "results" / "eval_set_32.json").read_text())[:3]
    edit(data[1])
    path.write_text(json.dumps(data))


@pytest.mark.parametrize("edit, rule", [
    (lambda d: d.update(rz=[[400.0, 300.0, 560.0, 380.0]]), "rz rectangle malformed or outside the area"),
    (lambda d: d.update(nfz=[list(d["bz"][0])]), "BZ/NFZ rectangles overlap"),
    (lambda d: d["ge_pos"].__setitem__(0, [(d["bz"][0][0] + d["bz"][0][2]) / 2, (d["bz"][0][1] + d["bz"][0][3]) / 2]),
     "GE inside a zone or closer than safety.d_min to one"),
    (lambda d: d["ge_data"].__setitem__(0, -2.0), "GE data negative"),
])
def test_scenario_files_are_validated_on_load(tmp_path, edit, rule):
    from uavlae.train import run

    path = tmp_path / "set.json"
    _write_set(path, edit)
    with pytest.raises(ValueError, match=rf"{path}: scenario 1 breaks: .*{rule}"):
        run(_cfg("+exp=sac", f"run_dir={tmp_path / 'r'}", *TINY, f"trainer.eval_set={path}"))
    assert not (tmp_path / "r" / "config.json").exists()


@pytest.mark.parametrize("umask, mode", [(0o022, 0o644), (0o027, 0o640)])
def test_files_follow_the_umask(tmp_path, umask, mode):
    from uavlae.files import dump_json

    old = os.umask(umask)
    try:
        path = dump_json(tmp_path / "a.json", {"x": 1})
    finally:
        os.umask(old)
    assert path.stat().st_mode & 0o777 == mode


def test_checkpoints_hold_the_filled_buffer_only(tmp_path):
    """make run's settings (1024 frames) with the default 1M-transition buffer: the checkpoint
    holds 1024 rows, megabytes, where the full capacity would be about 1.4 GB."""
    from uavlae.train import run

    run_dir = tmp_path / "m"
    run(_cfg("+exp=sac", f"run_dir={run_dir}", "trainer.total_frames=1024", "trainer.init_random_frames=256",
             "trainer.eval_episodes=2", "trainer.eval_max_steps=10", "trainer.eval_plots=0", "trainer.progress_bar=false",
             "logger.wandb.mode=disabled", "trainer.baselines=false"))
    size = (run_dir / "checkpoints" / LAST).stat().st_size
    assert size < 5_000_000
    state, _ = load_checkpoint(run_dir)
    assert state["replay_buffer"]["n"] == 1024


# ---------------------------------------------------------------------------- the code's shape


def _modules() -> dict[str, Path]:
    root = REPO_ROOT / "uavlae"
    out = {}
    for f in root.rglob("*.py"):
        name = ".".join(f.relative_to(REPO_ROOT).with_suffix("").parts)
        out[name.removesuffix(".__init__")] = f
    return out


def _imports(name: str, f: Path, mods: dict[str, Path]) -> set[str]:
    """Every uavlae module ``name`` imports, at the top or inside functions."""
    out = set()
    for node in ast.walk(ast.parse(f.read_text())):
        targets = []
        if isinstance(node, ast.Import):
            targets = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module:
            targets = [f"{node.module}.{a.name}" for a in node.names] + [node.module]
        for t in targets:
            while t and t not in mods:
                t = t.rpartition(".")[0]
            if t and t != name:
                out.add(t)
    return out


def test_no_import_cycle_counting_imports_inside_functions():
    mods = _modules()
    graph = {m: _imports(m, f, mods) for m, f in mods.items()}
    # a package importing its own submodules is no cycle: drop the edges from a package to its children
    graph = {m: {d for d in deps if not d.startswith(m + ".")} for m, deps in graph.items()}
    state: dict[str, int] = {}
    cycles = []

    def visit(m: str, path: list[str]) -> None:
        state[m] = 1
        for d in sorted(graph[m]):
            if state.get(d) == 1:
                cycles.append(path[path.index(d):] + [d] if d in path else [m, d])
            elif d not in state:
                visit(d, [*path, d])
        state[m] = 2

    for m in sorted(graph):
        if m not in state:
            visit(m, [m])
    assert cycles == []


def test_no_function_of_the_package_is_longer_than_a_screen():
    long = []
    for name, f in _modules().items():
        for node in ast.walk(ast.parse(f.read_text())):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                n = node.end_lineno - node.lineno + 1
                if n > 80:
                    long.append(f"{name}.{node.name}: {n} lines")
    assert long == []
