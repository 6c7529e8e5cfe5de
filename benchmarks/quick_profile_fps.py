"""Training frames/s of each method in the ``quick`` profile's setting (uavlae/conf/profile/quick.yaml),
one short run each on one thread, and the wall clock of the whole non-LLM quick profile that
follows from them (the basis of its size; uavlae/experiments/README.md, "Profiles").

    make bench-quick-fps        # -> benchmarks/quick_profile_fps.json

Each method trains ``--frames`` frames in-process with the profile's settings (compiled env,
B = 64, 0.25 gradient steps a frame); its rate is taken after the random warm-up and the
compile (from the cumulative ``time/fps`` log: the frames and seconds between two log points).
An evaluation of the profile's evaluation set is timed on its own. The estimate multiplies
these by the runs ``make quick`` launches (the sweeps' grids as the Makefile passes them), adds
each run's fixed cost (warm-up, a cold compile, the final evaluation) and divides by two cores;
``--estimate-only`` derives it again from the file's measured runs.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import tempfile
import time
from pathlib import Path

import torch
from hydra import compose, initialize_config_dir

from uavlae.factories import CONF_DIR
from uavlae.files import dump_json
from uavlae.machine import describe_machine

OUT = Path(__file__).with_name("quick_profile_fps.json")
LEARNERS = ("sac", "sac_heuristic", "ddpg", "ppo", "cpo")


def _cfg(*overrides: str):
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        return compose("config", overrides=["+profile=quick", *overrides])


def _scalar(run_dir: Path, name: str) -> list[tuple[float, float]]:
    f = run_dir / "logs" / "scalars" / f"{name}.csv"
    return [tuple(map(float, ln.split(",")[:2])) for ln in f.read_text().splitlines() if ln]  # type: ignore[misc]


def measure(method: str, frames: int, tmp: Path) -> dict:
    from uavlae.train import run

    run_dir = tmp / method
    t0 = time.perf_counter()
    run(_cfg(f"+exp={method}", f"run_dir={run_dir}", f"trainer.total_frames={frames}", "trainer.eval_every_frames=0",
             "trainer.checkpoint_every_frames=0", "trainer.checkpoint_replay_buffer=false", "trainer.eval_plots=0",
             "logger.wandb.mode=disabled", "trainer.progress_bar=false"))
    wall = time.perf_counter() - t0
    fps = _scalar(run_dir, "time/fps")
    # cumulative fps -> elapsed seconds at each log point; the rate between the point after the
    # warm-up (and the compile, which happens in the first batch) and the last one
    warm = int(_cfg(f"+exp={method}").trainer.init_random_frames) if method not in ("ppo", "cpo") else 0
    start = next((i for i, (f, _) in enumerate(fps) if f > max(warm, fps[0][0])), len(fps) - 2)
    (f0, r0), (f1, r1) = fps[start], fps[-1]
    rate = (f1 - f0) / (f1 / r1 - f0 / r0)
    evals = _scalar(run_dir, "eval/DCR")
    return {"method": method, "frames": int(fps[-1][0]), "wall_s": round(wall, 1), "train_fps_after_warmup": round(rate, 1),
            "from_frames": int(f0), "final_eval_DCR": evals[-1][1] if evals else None}


def time_eval(tmp: Path) -> float:
    """Seconds of one evaluation of a controller on the profile's evaluation set (no compile)."""
    from uavlae.train import run

    t0 = time.perf_counter()
    run(_cfg("+exp=heuristic", f"run_dir={tmp / 'h'}", "trainer.eval_plots=3", "logger.wandb.mode=disabled",
             "trainer.compile_env=false"))
    return time.perf_counter() - t0


# `make quick`'s sensitivity grids (Makefile QUICK_SENS): the default setting and one value on each
# side of it on each of the seven axes
SENS_POINTS = 1 + 2 * 7
# `make quick-sens-landed` (Makefile QUICK_SENS_LANDED): PPO at the quick profile's frames, two
# seeds, the same grids without the batch-size axis
LANDED_POINTS, LANDED_SEEDS = 1 + 2 * 6, 2


def _n(values: object) -> int:
    return len(str(values).split(","))


def estimate(rates: dict[str, float], eval_s: float, compile_s: float) -> dict:
    """The non-LLM quick profile as `make quick` runs it: uavlae/conf/profile/quick.yaml's frames and
    seeds for the train sweep, quick_sensitivity.yaml's for the sensitivity sweeps."""
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        q = compose("config", overrides=["+sweep=train", "+profile=quick", "+exp=sac"], return_hydra_config=True)
        s = compose("config", overrides=["+sweep=sens_r1", "+profile=quick_sensitivity", "+exp=sac"], return_hydra_config=True)
    train_frames, sens_frames = int(q.trainer.total_frames), int(s.trainer.total_frames)
    seeds, sens_seeds = _n(q.hydra.sweeper.params.seed), _n(s.hydra.sweeper.params.seed)
    train = sum(seeds * (train_frames / rates[m] + compile_s) for m in LEARNERS)
    controllers = 2 * seeds * eval_s  # heuristic and random on the training set
    sens_points = SENS_POINTS
    sens = sens_points * sens_seeds * (sens_frames / rates["sac"] + compile_s)
    settings = 5 + 5 + 3 + 3 + 3
    scen = settings * (len(LEARNERS) + 2) * seeds * eval_s
    core_s = train + controllers + sens + scen
    return {"train_frames": train_frames, "sensitivity_frames": sens_frames, "seeds": seeds,
            "sensitivity_runs": sens_points * sens_seeds, "scenario_evaluations": settings * (len(LEARNERS) + 2) * seeds,
            "core_s": {"train": round(train), "controllers": round(controllers), "sensitivity": round(sens), "scenarios": round(scen)},
            "total_core_h": round(core_s / 3600, 2), "wall_h_on_2_cores": round(core_s / 2 / 3600, 2),
            # not a step of `make quick`: its own target, outside the totals above
            "quick_sens_landed": {"runs": LANDED_POINTS * LANDED_SEEDS,
                                  "core_h": round(LANDED_POINTS * LANDED_SEEDS * (train_frames / rates["ppo"] + compile_s) / 3600, 2)}}


def fixed_cost(rows: list[dict]) -> float:
    """Seconds a run costs beyond its post-warm-up frames at their rate: the random warm-up, the
    compile of the training and evaluation envs and the final evaluation. The largest over the
    methods (the first, which compiled with a cold cache): every run is charged a cold compile."""
    return max(r["wall_s"] - (r["frames"] - r["from_frames"]) / r["train_fps_after_warmup"] for r in rows)


def summarise(res: dict) -> dict:
    rows = res["runs"]
    res["fixed_cost_per_run_s"] = round(fixed_cost(rows), 1)
    rates = {r["method"]: r["train_fps_after_warmup"] for r in rows}
    if set(rates) == set(LEARNERS):
        res["quick_profile_estimate"] = estimate(rates, res["heuristic_run_s"], res["fixed_cost_per_run_s"])
    return res


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--frames", type=int, default=16384, help="training frames of each method's measurement")
    p.add_argument("--methods", nargs="+", default=list(LEARNERS), choices=LEARNERS)
    p.add_argument("--out", type=Path, default=OUT)
    p.add_argument("--estimate-only", action="store_true",
                   help="keep --out's measured runs and derive the estimate from them again (after a change of the profiles)")
    a = p.parse_args(argv)
    if a.estimate_only:
        res = summarise(json.loads(a.out.read_text()))
        res["estimate_command"] = "python benchmarks/quick_profile_fps.py " + " ".join(sys.argv[1:] if argv is None else argv)
        dump_json(a.out, res)
        print(res.get("quick_profile_estimate"))
        return
    torch.set_num_threads(1)
    tmp = Path(tempfile.mkdtemp(prefix="quick_fps_"))
    try:
        rows = []
        for m in a.methods:
            torch.compiler.reset()  # each run compiles its own envs; one process would hit dynamo's recompile limit
            rows.append(measure(m, a.frames, tmp))
            print(rows[-1], flush=True)
        torch.compiler.reset()
        eval_s = time_eval(tmp)
        res = summarise({"command": "python benchmarks/quick_profile_fps.py " + " ".join(sys.argv[1:] if argv is None else argv),
                         "date": time.strftime("%Y-%m-%d %H:%M:%S %Z"), "machine": describe_machine(torch_threads=1),
                         "runs": rows, "heuristic_run_s": round(eval_s, 1)})
        dump_json(a.out, res)
        print(res.get("quick_profile_estimate"))
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    main()
