"""Golden runs: the same seed gives the same ``final_metrics.json``, bit for bit, through any
refactor of the training loop (``sac``, ``sac_heuristic``, ``ppo``).

The golden values in ``tests/golden/`` were written by this module (``UAVLAE_WRITE_GOLDEN=1``)
on the machine they name. Float results of the same code differ in their last bits between CPU
vendors and instruction sets (matrix kernels sum in another order), so the exact comparison
runs where the CPU vendor and torch's CPU capability match the golden file's; elsewhere the
values must agree to a relative 1e-3 (these runs are short, so rounding has little room to
grow). A deliberate change of behaviour updates the golden files in a commit of its own that
says why. ``wall_s`` (the training wall clock) is the one key left out.
"""

from __future__ import annotations

import json
import os
import platform
from pathlib import Path

import pytest
import torch

GOLDEN = Path(__file__).parent / "golden"
EXPS = ("sac", "sac_heuristic", "ppo")
RUN = [
    "trainer.total_frames=256", "trainer.env_batch_size=8", "trainer.frames_per_batch=64",
    "trainer.init_random_frames=64", "trainer.batch_size=32", "trainer.utd_ratio=0.25",
    "trainer.replay_capacity=1024", "trainer.eval_episodes=3", "trainer.eval_max_steps=40",
    "trainer.eval_every_frames=128", "trainer.checkpoint_every_frames=128", "trainer.eval_plots=0",
    "trainer.progress_bar=false", "logger.wandb.mode=disabled", "seed=3",
]
PPO = ["algo.minibatch_size=32", "algo.epochs=2"]


def machine_key() -> dict[str, str]:
    vendor = "unknown"
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("vendor_id"):
                vendor = line.split(":", 1)[1].strip()
                break
    except OSError:
        vendor = platform.processor() or "unknown"
    return {"cpu_vendor": vendor, "cpu_capability": torch.backends.cpu.get_cpu_capability(),
            "torch": torch.__version__.split("+")[0]}


def golden_run(exp: str, tmp: Path) -> dict:
    from tests.test_train import _cfg
    from uavlae.train import run

    final = run(_cfg(f"+exp={exp}", f"run_dir={tmp / exp}", *RUN, *(PPO if exp == "ppo" else [])))
    on_disk = json.loads((tmp / exp / "final_metrics.json").read_text())
    assert on_disk == json.loads(json.dumps(final))
    on_disk.pop("wall_s")
    return on_disk


@pytest.mark.parametrize("exp", EXPS)
def test_golden_final_metrics(exp, tmp_path):
    got = golden_run(exp, tmp_path)
    path = GOLDEN / f"final_metrics_{exp}.json"
    if os.environ.get("UAVLAE_WRITE_GOLDEN") == "1":
        path.write_text(json.dumps({"machine": machine_key(), "final_metrics": got}, indent=1, sort_keys=True) + "\n")
    golden = json.loads(path.read_text())
    want = golden["final_metrics"]
    assert sorted(got) == sorted(want)
    if golden["machine"] == machine_key():
        assert got == want
    else:
        for k, v in want.items():
            assert got[k] == pytest.approx(v, rel=1e-3, abs=1e-6), k
