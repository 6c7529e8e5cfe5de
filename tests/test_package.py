"""The package as a user gets it from ``pip install``: a wheel that carries its configs and its
experiments, installed outside the checkout, trains from an empty folder and writes its run there;
its console scripts evaluate and report that run; gymnasium finds the env by the id it documents
for third-party packages; and the library never imports its experiments layer."""

from __future__ import annotations

import ast
import json
import os
import shutil
import subprocess
import sys
import sysconfig
import tomllib
from pathlib import Path

import pytest

from uavlae.factories import REPO_ROOT

# one worker builds and installs the wheel once for every test of this file (make test: --dist loadgroup)
pytestmark = [pytest.mark.timeout(600), pytest.mark.xdist_group("wheel")]

PYPROJECT = tomllib.loads((REPO_ROOT / "pyproject.toml").read_text())
VERSION = PYPROJECT["project"]["version"]
TINY = [
    "trainer.total_frames=128", "trainer.env_batch_size=4", "trainer.frames_per_batch=32",
    "trainer.init_random_frames=32", "trainer.batch_size=16", "trainer.eval_episodes=2", "trainer.eval_max_steps=10",
    "trainer.eval_every_frames=0", "trainer.checkpoint_every_frames=0", "trainer.eval_plots=1",
]


def _run(cmd: list[str], cwd: Path, timeout: int = 300) -> subprocess.CompletedProcess:
    # no PYTHONPATH: nothing of the checkout may leak into the installed package's interpreter; no
    # WANDB_SERVICE: an earlier in-process wandb run of this test session leaves its service's
    # address there, and a child that joins that service instead of starting its own may write no run file
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "WANDB_SERVICE")}
    env.update(OMP_NUM_THREADS="1", UAVLAE_NUM_THREADS="1", WANDB_MODE="offline", WANDB_SILENT="true")
    res = subprocess.run(cmd, cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout)
    assert res.returncode == 0, f"{cmd}\n{res.stdout[-3000:]}\n{res.stderr[-3000:]}"
    return res


@pytest.fixture(scope="module")
def installed(tmp_path_factory) -> Path:
    """A wheel built from a copy of the package's sources, installed into a fresh venv whose
    only other packages are this interpreter's (torch and the rest, reused through a path file:
    the editable install of the checkout is not among them, since its own .pth is not read)."""
    tmp = tmp_path_factory.mktemp("wheel")
    src = tmp / "src"
    src.mkdir()
    for name in ("pyproject.toml", "README.md", "LICENSE"):
        shutil.copy(REPO_ROOT / name, src / name)
    shutil.copytree(REPO_ROOT / "uavlae", src / "uavlae", ignore=shutil.ignore_patterns("__pycache__", "*.pyc"))
    dist = tmp / "dist"
    _run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "-q", "-w", str(dist), str(src)],
         cwd=tmp)
    wheel = next(dist.glob("uavlae-*.whl"))
    venv = tmp / "venv"
    _run([sys.executable, "-m", "venv", "--without-pip", str(venv)], cwd=tmp)
    python = venv / "bin" / "python"
    purelib = Path(_run([str(python), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                        cwd=tmp).stdout.strip())
    ours = {sysconfig.get_paths()["purelib"], sysconfig.get_paths()["platlib"]}
    (purelib / "uavlae_deps.pth").write_text("".join(p + "\n" for p in sorted(ours)))
    _run([sys.executable, "-m", "pip", "--python", str(python), "install", "--no-deps", "-q", str(wheel)], cwd=tmp)
    return venv


def test_the_wheel_carries_configs_and_experiments_but_no_results(installed):
    python = installed / "bin" / "python"
    code = ("import uavlae, uavlae.experiments.report as r; from uavlae.factories import CONF_DIR; "
            "print(uavlae.__file__, uavlae.__version__, CONF_DIR, r.__file__)")
    init, version, conf, report = _run([str(python), "-c", code], cwd=installed).stdout.split()
    site = installed / "lib"
    assert Path(init).is_relative_to(site) and Path(report).is_relative_to(site)  # not the checkout's
    assert version == VERSION
    assert (Path(conf) / "config.yaml").is_file() and (Path(conf) / "exp" / "sac.yaml").is_file()
    assert (Path(conf) / "hydra" / "launcher" / "slurm.yaml").is_file()
    assert not list(Path(init).parent.parent.glob("results")) and not list(Path(init).parent.glob("tests"))
    scripts = {p.name for p in (installed / "bin").glob("uavlae-*")}
    assert scripts == {"uavlae-train", "uavlae-evaluate", "uavlae-export", "uavlae-fly", "uavlae-demo", "uavlae-report",
                       "uavlae-llm-server"}


def test_installed_package_trains_from_an_empty_folder_evaluates_and_reports(installed, tmp_path):
    python, bin_ = installed / "bin" / "python", installed / "bin"
    work = tmp_path / "empty"
    work.mkdir()
    # not a terminal: progress lines (here one per env step) instead of a bar
    _run([str(python), "-m", "uavlae.train", "+exp=sac", *TINY, "trainer.baselines=false",
          "trainer.progress_every_s=0.000001"], cwd=work)
    (run_dir,) = (work / "runs" / "sac").iterdir()  # the run lies under the folder it was started in
    lines = [ln for ln in (run_dir / "train.log").read_text().splitlines() if "sac seed0: " in ln]
    assert "sac seed0: 4 / 128 frames (3.1%)" in lines[0] and "frames/s, ETA" in lines[0]
    assert "128 / 128 frames (100.0%)" in lines[-1] and "last evaluation at 128: DCR" in lines[-1]
    final = json.loads((run_dir / "final_metrics.json").read_text())
    assert final["frames"] == 128 and 0.0 <= final["eval/DCR"] <= 1.0
    meta = json.loads((run_dir / "meta.json").read_text())
    assert meta["packages"]["uavlae"] == VERSION
    assert meta["git"] == {"commit": None, "dirty": None}  # no checkout holds the installed package
    assert list((run_dir / "wandb").glob("offline-run-*/run-*.wandb")), sorted(map(str, run_dir.rglob("*")))
    # the console scripts: evaluate the run's checkpoint, export its actor, fly it, report the folder
    _run([str(bin_ / "uavlae-evaluate"), f"checkpoint={run_dir}", "trainer.eval_episodes=2", "trainer.eval_max_steps=10",
          "trainer.eval_plots=0"], cwd=work)
    (evaluation,) = (run_dir / "evaluate").glob("*/evaluation.json")
    assert json.loads(evaluation.read_text())["spec"]["frames"] == 128
    assert not (work / "outputs").exists()  # a command that reads a run writes no Hydra folder here
    _run([str(bin_ / "uavlae-export"), f"checkpoint={run_dir}", "out=actor.pt2"], cwd=work)
    flown = _run([str(bin_ / "uavlae-fly"), "--actor", "actor.pt2", "--scenario", str(run_dir / "eval_set.json")], cwd=work)
    assert "DCR" in flown.stdout
    _run([str(bin_ / "uavlae-report"), "runs", "--out", "report"], cwd=work)
    md = (work / "report" / "report.md").read_text()
    # the training run and its evaluation; with no commit, each names the version that made it
    assert "Runs: 2 collected" in md and f"Commits: uavlae {VERSION}  \n" in md
    assert str(work) not in md and str(tmp_path) not in md  # paths relative to where it ran


def test_gymnasium_finds_the_env_by_its_third_party_id_in_a_fresh_interpreter(installed):
    code = (
        "import warnings, gymnasium\n"
        "from gymnasium.utils.env_checker import check_env\n"
        "warnings.filterwarnings('ignore', message='.*Box observation space m')\n"
        "env = gymnasium.make('uavlae:uavlae/UAV-v0')\n"
        "check_env(env.unwrapped)\n"
        "obs, info = env.reset(seed=0)\n"
        "print(env.spec.id, type(env.unwrapped).__module__, obs.shape[0])\n"
    )
    for python in (installed / "bin" / "python", Path(sys.executable)):  # installed, and the checkout's editable
        gid, module, size = _run([str(python), "-c", code], cwd=installed).stdout.split()
        assert (gid, module) == ("uavlae/UAV-v0", "uavlae.envs.gym_adapter") and int(size) > 0


def test_the_library_never_imports_its_experiments_layer():
    """``uavlae.experiments`` imports the library; no other module of uavlae imports it."""
    offenders = []
    for f in sorted((REPO_ROOT / "uavlae").rglob("*.py")):
        if "experiments" in f.relative_to(REPO_ROOT / "uavlae").parts[:1]:
            continue
        for node in ast.walk(ast.parse(f.read_text())):
            names = [a.name for a in node.names] if isinstance(node, ast.Import) else (
                [node.module or ""] if isinstance(node, ast.ImportFrom) else [])
            offenders += [f"{f.relative_to(REPO_ROOT)}: {n}" for n in names if n.startswith("uavlae.experiments")]
    assert offenders == []
