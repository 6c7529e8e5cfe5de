"""The experiments' machinery: every sweep composes, the report aggregates synthetic runs with
known numbers (means, intervals, missing and broken runs), sweeps reuse and resume their runs,
uavlae.evaluate honours env overrides, and two-job multiruns run on joblib and on a local Ray
instance end to end (train sweep -> scenario sweep -> report)."""

from __future__ import annotations

import csv
import json
import math
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from uavlae.experiments import report
from uavlae.factories import CONF_DIR, REPO_ROOT, validate_config

pytestmark = pytest.mark.timeout(600)

SWEEPS = sorted(p.stem for p in (CONF_DIR / "sweep").glob("*.yaml") if not p.stem.startswith("_"))
TINY = [
    "trainer.total_frames=128", "trainer.env_batch_size=4", "trainer.frames_per_batch=32",
    "trainer.init_random_frames=32", "trainer.batch_size=16", "trainer.utd_ratio=0.25",
    "trainer.replay_capacity=512", "trainer.eval_episodes=2", "trainer.eval_max_steps=10",
    "trainer.eval_every_frames=64", "trainer.checkpoint_every_frames=64", "trainer.eval_plots=1",
    "trainer.progress_bar=false", "logger.wandb.mode=disabled", "trainer.compile_env=false",
]


def _cfg(*overrides: str, hydra: bool = False):
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        return compose("config", overrides=list(overrides), return_hydra_config=hydra)


# ---------------------------------------------------------------------------- composition


def test_the_paper_sweeps_exist():
    assert set(SWEEPS) >= {
        "train", "train_llm", "train_fp", "scenario_n_ou", "scenario_n_ge", "scenario_n_nfz", "scenario_n_bz",
        "scenario_n_rz", "sens_actor_lr", "sens_critic_lr", "sens_batch_size", "sens_r1", "sens_r2", "sens_r5",
        "sens_r8", "llm_dth", "llm_prompt",
    }


@pytest.mark.parametrize("profile", [None, "quick", "paper"])
@pytest.mark.parametrize("sweep", SWEEPS)
def test_every_sweep_composes_at_its_first_and_last_point(sweep, profile):
    extra = [f"+profile={profile}"] if profile else []
    base = _cfg(f"+sweep={sweep}", *extra, hydra=True)
    params = {k: str(v).split(",") for k, v in base.hydra.sweeper.params.items()}
    assert "+exp" in params and "seed" in params, params
    if profile == "quick":
        assert params["seed"] == ["0", "1", "2"]
    if profile == "paper":
        assert len(params["seed"]) >= 5 and base.trainer.total_episodes == 4000 and base.trainer.eval_episodes >= 100
    for pick in (0, -1):
        point = [f"{k}={v[pick]}" for k, v in params.items()]
        cfg = _cfg(f"+sweep={sweep}", *extra, *point)
        resolved = OmegaConf.create(OmegaConf.to_container(cfg, resolve=True))
        OmegaConf.set_struct(resolved, True)
        validate_config(resolved)
        assert resolved.experiment.sweep and resolved.experiment.reuse
        root = resolved.experiment.root
        where = resolved.experiment.eval_dir if sweep.startswith("scenario_") else resolved.run_dir
        assert where.startswith(f"{root}/{resolved.experiment.sweep}/") and where.endswith(f"/seed{resolved.seed}")


def test_scenario_sweep_fixes_the_count_and_the_checkpoint():
    cfg = _cfg("+sweep=scenario_n_ge", "+exp=ppo", "seed=2", "env.ge.count.max=12")
    assert (cfg.env.ge.count.min, cfg.env.ge.count.max) == (12, 12)
    assert cfg.checkpoint == "runs/experiments/train/ppo/seed2"
    assert cfg.experiment.eval_dir == "runs/experiments/scenario_n_ge/n_ge=12/ppo/seed2"
    assert cfg.trainer.eval_set == "runs/experiments/eval_sets/n_ge_12.json"


def test_sensitivity_runs_share_the_default_point():
    a = _cfg("+sweep=sens_actor_lr", "+exp=sac", "algo.actor_lr=1.0e-4")
    b = _cfg("+sweep=sens_r8", "+exp=sac", "env.reward.sigma.7=1.0")
    c = _cfg("+sweep=sens_r8", "+exp=sac", "env.reward.sigma.7=2.0")
    assert a.run_dir == b.run_dir != c.run_dir
    assert c.env.reward.sigma[7] == 2.0 and c.run_dir.endswith("_w8.0_0.4_0.6_2.0/sac/seed0")
    # the profile comes after the sweep on the command line and sets its seeds and budget
    q = _cfg("+sweep=sens_r1", "+profile=quick_sensitivity", hydra=True)
    assert q.hydra.sweeper.params.seed == "0,1" and q.trainer.total_frames == 120000
    assert q.experiment.profile == "quick" and q.env.reward.progress_weight > 0


def test_llm_sweeps_share_the_complete_prompt_at_15_m():
    a = _cfg("+sweep=llm_dth", "+exp=sac_llm", "advisor.d_th=15.0")
    b = _cfg("+sweep=llm_prompt", "+exp=sac_llm", "llm.prompt_ablation=none")
    c = _cfg("+sweep=llm_prompt", "+exp=sac_llm", "llm.prompt_ablation=no_safety")
    d = _cfg("+sweep=llm_dth", "+exp=sac_llm", "advisor.d_th=5.0")
    assert a.run_dir == b.run_dir == "runs/experiments/llm_setting/d_th=15.0_prompt=none/sac_llm/seed0"
    assert c.run_dir.endswith("d_th=15.0_prompt=no_safety/sac_llm/seed0") and d.run_dir.endswith("d_th=5.0_prompt=none/sac_llm/seed0")


@pytest.mark.parametrize("launcher, target", [
    ("local", "JoblibLauncher"), ("ray_local", "RayLauncher"), ("slurm", "SlurmLauncher"), ("slurm_local", "LocalLauncher"),
])
def test_launchers_compose(launcher, target):
    cfg = _cfg("+sweep=train", f"hydra/launcher={launcher}", hydra=True)
    assert cfg.hydra.launcher._target_.endswith(target)
    if launcher.startswith("slurm"):
        assert cfg.hydra.launcher.cpus_per_task == 1 and cfg.hydra.launcher.gpus_per_node == 0


def test_the_local_twin_asks_for_the_slurm_jobs_resources():
    slurm = _cfg("+sweep=train", "hydra/launcher=slurm", hydra=True).hydra.launcher
    local = _cfg("+sweep=train", "hydra/launcher=slurm_local", hydra=True).hydra.launcher
    shared = set(OmegaConf.load(CONF_DIR / "hydra" / "launcher" / "slurm_local.yaml")) - {"defaults"}
    assert shared == {"timeout_min", "cpus_per_task", "gpus_per_node", "tasks_per_node", "mem_gb", "nodes"}
    assert {k: local[k] for k in shared} == {k: slurm[k] for k in shared}


def test_sweeps_default_to_joblib_with_two_jobs():
    cfg = _cfg("+sweep=train", hydra=True)
    assert cfg.hydra.launcher._target_.endswith("JoblibLauncher") and cfg.hydra.launcher.n_jobs == 2


# ---------------------------------------------------------------------------- statistics


def test_t_quantiles_and_intervals_by_hand():
    # Student's t table: t_{0.975} for 1, 2, 4 and 29 degrees of freedom
    assert report.t_quantile(0.975, 1) == pytest.approx(12.7062, abs=2e-3)
    assert report.t_quantile(0.975, 2) == pytest.approx(4.3027, abs=1e-3)
    assert report.t_quantile(0.975, 4) == pytest.approx(2.7764, abs=1e-3)
    assert report.t_quantile(0.975, 29) == pytest.approx(2.0452, abs=1e-3)
    m, lo, hi, n = report.mean_ci([0.5, 0.7, 0.9])  # sd 0.2, half width 4.3027 * 0.2 / sqrt(3)
    assert (m, n) == (pytest.approx(0.7), 3)
    assert (lo, hi) == (pytest.approx(0.7 - 0.49683, abs=1e-4), pytest.approx(0.7 + 0.49683, abs=1e-4))
    m, lo, hi, n = report.mean_ci([0.25, float("nan")])
    assert m == 0.25 and n == 1 and math.isnan(lo) and math.isnan(hi)
    assert report.fmt_ci(0.7, 0.2, 1.2) == "0.700 [0.200, 1.200]" and report.fmt_ci(0.25, math.nan, math.nan) == "0.250"


# ---------------------------------------------------------------------------- the report


def _metrics(dcr: float, slr: float, cr: float = 0.1, rvr: float = 0.0, ecr: float = 0.2) -> dict[str, float]:
    return {"DCR": dcr, "CR": cr, "SLR": slr, "RVR": rvr, "ECR": ecr}


def _train_dir(root: Path, method: str, seed: int, m: dict[str, float], *, sweep: str = "train", point: str = "default",
               controller: str = "learner", frames: int = 1000, total: int = 1000, final: bool = True,
               extra_cfg: dict | None = None, returns: list[tuple[int, int, float]] | None = None) -> Path:
    d = root / "train" / method / f"seed{seed}" if sweep == "train" else root / sweep / point / method / f"seed{seed}"
    d.mkdir(parents=True, exist_ok=True)
    cfg = {"name": method, "seed": seed, "controller": controller, "trainer": {"total_frames": total, "total_episodes": None},
           "experiment": {"sweep": sweep, "point": point, "method": method, "profile": "quick"},
           "env": {"reward": {"progress_weight": 8.0, "progress_metric": "geodesic", "sigma": [8.0, 0.4, 0.4, 0.4, 0.6, 0.4, 0.6, 1.0, 0.01]},
                   "ego_features": True},
           "algo": {"actor_lr": 1e-4, "critic_lr": 3e-4}}
    cfg["trainer"]["batch_size"] = 256
    for k, v in (extra_cfg or {}).items():
        node = cfg
        *parts, last = k.split(".")
        for p in parts:
            node = node[p] if not isinstance(node, list) else node[int(p)]
        if isinstance(node, list):
            node[int(last)] = v
        else:
            node[last] = v
    (d / "config.json").write_text(json.dumps(cfg))
    (d / "meta.json").write_text(json.dumps({"git": {"commit": "abcdef1234567", "dirty": False},
                                              "packages": {"torch": "2.13.0+cpu"}, "machine": {"cpu": "Test CPU", "logical_cores": 2},
                                              "command": f"python -m uavlae.train +exp={method} seed={seed}"}))
    if final:
        (d / "final_metrics.json").write_text(json.dumps({"frames": frames, "episodes": frames // 100, "updates": 5,
                                                          **{f"eval/{k}": v for k, v in m.items()}}))
    if returns:
        (d / "logs" / "scalars" / "episode").mkdir(parents=True)
        (d / "logs" / "scalars" / "train").mkdir(parents=True)
        (d / "logs" / "scalars" / "episode" / "mean_return.csv").write_text("".join(f"{f},{r}\n" for f, _, r in returns))
        (d / "logs" / "scalars" / "train" / "episodes.csv").write_text("".join(f"{f},{e}\n" for f, e, _ in returns))
    return d


def _eval_dir(root: Path, sweep: str, point: str, method: str, seed: int, m: dict[str, float]) -> Path:
    d = root / sweep / point / method / f"seed{seed}"
    d.mkdir(parents=True, exist_ok=True)
    rec = {"spec": {"method": method, "seed": seed, "frames": 1000}, "name": method, "metrics": m, "n_scenarios": 4,
           "experiment": {"sweep": sweep, "point": point, "profile": "quick"}, "env": {"reward": {"progress_weight": 0.0}},
           "meta": {"git": {"commit": "1234567890ab", "dirty": False}}}
    (d / "evaluation.json").write_text(json.dumps(rec))
    return d


def _synthetic(root: Path) -> None:
    # sac: DCR 0.5 / 0.7 / 0.9 (mean 0.7, interval +-0.49683), SLR 0.6 / 0.6 / 0.9
    for s, (dcr, slr) in enumerate([(0.5, 0.6), (0.7, 0.6), (0.9, 0.9)]):
        _train_dir(root, "sac", s, _metrics(dcr, slr), returns=[(0, 0, 0.0), (500, 5, 10.0 * (s + 1)), (1000, 10, 20.0 * (s + 1))])
    calls = root / "train" / "sac" / "seed0" / "logs" / "scalars" / "override" / "advisor"
    calls.mkdir(parents=True)
    (calls / "calls.csv").write_text("500,3\n1000,4\n")  # two logged windows: 7 calls in all
    # ddpg: tight and high -> learned; random: DCR 0 / 0.1 / 0.2, SLR 0 / 0 / 0
    for s, dcr in enumerate([0.80, 0.82, 0.84]):
        _train_dir(root, "ddpg", s, _metrics(dcr, dcr))
    for s, dcr in enumerate([0.0, 0.1, 0.2]):
        _train_dir(root, "random", s, _metrics(dcr, 0.0), controller="random", frames=0)
    # broken, unfinished (no final file), unfinished (short of its budget)
    broken = _train_dir(root, "ppo", 0, _metrics(1, 1))
    (broken / "final_metrics.json").write_text("{not json")
    _train_dir(root, "ppo", 1, _metrics(1, 1), final=False)
    _train_dir(root, "ppo", 2, _metrics(1, 1), frames=500, total=1000)
    # a scenario sweep: N_OU = 3 and 7, two seeds of sac, one of random; one broken evaluation
    for k, base in ((3, 0.8), (7, 0.4)):
        for s in (0, 1):
            _eval_dir(root, "scenario_n_ou", f"n_ou={k}", "sac", s, _metrics(base + 0.1 * s, base))
        _eval_dir(root, "scenario_n_ou", f"n_ou={k}", "random", 0, _metrics(0.05, 0.0))
    (_eval_dir(root, "scenario_n_ou", "n_ou=5", "sac", 0, _metrics(0, 0)) / "evaluation.json").write_text('{"spec": {}}')
    # sensitivity: actor lr at 1e-4 (default, shared) and 1e-3, r8 weight at 2.0
    for s in (0, 1):
        _train_dir(root, "sac", s, _metrics(0.6 + 0.2 * s, 0.5), sweep="sensitivity", point="default")
        _train_dir(root, "sac", s, _metrics(0.2, 0.1 * s), sweep="sensitivity", point="alr1e-3", extra_cfg={"algo.actor_lr": 1e-3})
        _train_dir(root, "sac", s, _metrics(0.9, 0.9), sweep="sensitivity", point="r8_2", extra_cfg={"env.reward.sigma.7": 2.0})


def _llm_run(root: Path, d_th: float, prompt: str, dcr: float, frames: int = 500) -> Path:
    d = _train_dir(root, "sac_llm", 0, _metrics(dcr, 0.0), sweep="llm_setting", point=f"d_th={d_th}_prompt={prompt}",
                   frames=frames, total=frames)
    cfg = json.loads((d / "config.json").read_text())
    cfg["advisor"], cfg["llm"] = {"kind": "llm", "d_th": d_th}, {"prompt_ablation": prompt}
    (d / "config.json").write_text(json.dumps(cfg))
    # 10 rows answered over two windows: 6 new calls (one an ask-again), 5 answers from the cache
    final = json.loads((d / "final_metrics.json").read_text()) | {"override/advised": 10.0}
    (d / "final_metrics.json").write_text(json.dumps(final))
    adv = d / "logs" / "scalars" / "override" / "advisor"
    adv.mkdir(parents=True)
    (adv / "calls.csv").write_text("250,4\n500,2\n")
    (adv / "cache_hits.csv").write_text("250,1\n500,4\n")
    return d


def test_llm_axes_and_the_runs_beside_plain_sac_at_equal_frames(tmp_path):
    import matplotlib

    matplotlib.use("Agg")
    root = tmp_path / "runs"
    # d_th 5 / 15 / 25 with the complete prompt; no_data and no_compliance at 15 m (the defaults: the
    # values most runs share); a no_safety run at 5 m is on neither axis
    for d_th, prompt, dcr in ((5.0, "none", 0.1), (15.0, "none", 0.3), (25.0, "none", 0.5), (15.0, "no_data", 0.2),
                              (15.0, "no_compliance", 0.4), (5.0, "no_safety", 0.9)):
        _llm_run(root, d_th, prompt, dcr)
    # plain SAC, two seeds, run to 1000 frames; its evaluation at 500 frames: DCR 0.2 and 0.4
    for s, dcr in ((0, 0.2), (1, 0.4)):
        d = _train_dir(root, "sac", s, _metrics(0.8, 0.8))
        (d / "eval" / "frames_000000500").mkdir(parents=True)
        (d / "eval" / "frames_000000500" / "metrics.json").write_text(json.dumps(_metrics(dcr, 0.0)))
    t = report.build(root, tmp_path / "out")["tables"]
    dth = {r["d_th (m)"]: r["DCR"] for r in t["fig13_llm_setting_d_th"]}
    assert dth == pytest.approx({5.0: 0.1, 15.0: 0.3, 25.0: 0.5})
    prompt = {r["prompt"]: r["DCR"] for r in t["fig14_llm_setting_prompt"]}
    assert prompt == pytest.approx({"none": 0.3, "no_data": 0.2, "no_compliance": 0.4})
    eq = t["llm_equal_frames"]
    assert eq[0]["method"] == "sac" and eq[0]["frames"] == "500" and eq[0]["n_seeds"] == 2
    assert eq[0]["DCR"] == pytest.approx(0.3) and eq[0]["DCR_hi"] - 0.3 == pytest.approx(12.7062 * 0.1, abs=1e-3)
    assert len(eq) == 7 and {r["setting"] for r in eq[1:]} >= {"llm_setting/d_th=15.0_prompt=none"}
    assert eq[0]["advisor_calls"] == "" and {r["advisor_calls"] for r in eq[1:]} == {"6 (10 rows, 5 cached)"}
    assert (tmp_path / "out" / "fig14_llm_setting_prompt.png").stat().st_size > 1000
    # nothing skipped: the file keeps its columns for whoever reads it
    assert (tmp_path / "out" / "skipped.csv").read_text().splitlines() == ["path,reason"]


def _episodes(run_dir: Path, frames: int, dcr: list[float], landed: list[bool]) -> None:
    d = run_dir / "eval" / f"frames_{frames:09d}"
    d.mkdir(parents=True)
    rows = ["row,data_collected,data_total,landed"] + [f"{i},{10 * x},10.0,{bool(l)}" for i, (x, l) in enumerate(zip(dcr, landed))]
    (d / "episodes.csv").write_text("\n".join(rows) + "\n")


def test_learned_with_one_seed_compares_the_final_evaluations_episodes(tmp_path):
    root = tmp_path / "runs"
    # sac: per-episode DCR 1.0 0.8 0.9 0.9 (mean 0.9, sd 0.08165, t(3) 3.1824: [0.770, 1.030]), all landed
    _episodes(_train_dir(root, "sac", 0, _metrics(0.9, 1.0)), 1000, [1.0, 0.8, 0.9, 0.9], [True] * 4)
    # ppo: 0.3 0.0 0.3 0.2 (mean 0.2, sd 0.14142: [-0.025, 0.425]) overlaps random's DCR
    _episodes(_train_dir(root, "ppo", 0, _metrics(0.2, 1.0)), 1000, [0.3, 0.0, 0.3, 0.2], [True] * 4)
    # random: 0.1 0.0 0.2 0.1 (mean 0.1, sd 0.08165: [-0.030, 0.230]), never landed ([0, 0])
    _episodes(_train_dir(root, "random", 0, _metrics(0.1, 0.0), controller="random", frames=0), 0,
              [0.1, 0.0, 0.2, 0.1], [False] * 4)
    # ddpg: one seed without its episodes file -> undetermined
    _train_dir(root, "ddpg", 0, _metrics(0.9, 1.0))
    rows = {r["method"]: r for r in report.build(root, tmp_path / "out")["tables"]["learned"]}
    assert rows["sac"]["DCR"] == "0.900 [0.770, 1.030]" and rows["sac"]["SLR"] == "1.000 [1.000, 1.000]"
    assert rows["sac"]["random_DCR"] == "0.100 [-0.030, 0.230]" and rows["sac"]["random_SLR"] == "0.000 [0.000, 0.000]"
    assert rows["sac"]["learned"] == "yes (one seed: intervals over its 4 evaluation episodes)"
    assert rows["ppo"]["DCR"] == "0.200 [-0.025, 0.425]"
    assert rows["ppo"]["learned"] == "no (one seed: intervals over its 4 evaluation episodes)"
    assert rows["ddpg"]["learned"].startswith("undetermined")


def _full_episodes(run_dir: Path, frames: int, **cols: list) -> None:
    """An ``episodes.csv`` with every record column: the given ones, zeros and False elsewhere."""
    from uavlae.envs.metrics import RECORD_COLUMNS, save_records

    n = len(next(iter(cols.values())))
    rows = [{c: cols[c][i] if c in cols else (i if c == "row" else 0) for c in RECORD_COLUMNS} for i in range(n)]
    save_records(rows, run_dir / "eval" / f"frames_{frames:09d}" / "episodes.csv")


def test_rows_with_their_episodes_get_the_stratified_bootstrap(tmp_path):
    """Two seeds of sac, each landing on scenario 0 of 2: SLR 0.5 on both seeds, so a t interval
    over seeds is [0.5, 0.5]; the bootstrap draws the scenarios too: both 0 (SLR 1), both 1 (0) a
    quarter of the time each, so [0, 1]. A method without its episodes keeps the t interval,
    marked (t) in the tables."""
    root = tmp_path / "runs"
    for s in (0, 1):
        _full_episodes(_train_dir(root, "sac", s, _metrics(0.5, 0.5)), 1000, data_collected=[10, 0],
                       data_total=[10.0, 10.0], landed=[True, False], energy_used=[1, 1], energy_total=[4, 4])
        _train_dir(root, "ddpg", s, _metrics(0.6 + 0.2 * s, 0.5))
    out = report.build(root, tmp_path / "out")
    rows = {r["method"]: r for r in out["tables"]["train_final"]}
    sac, ddpg = rows["sac"], rows["ddpg"]
    assert sac["interval"] == "bootstrap" and (sac["SLR"], sac["SLR_lo"], sac["SLR_hi"]) == (0.5, 0.0, 1.0)
    assert (sac["DCR"], sac["DCR_lo"], sac["DCR_hi"]) == (0.5, 0.0, 1.0)
    assert ddpg["interval"] == "t" and ddpg["DCR_hi"] - 0.7 == pytest.approx(12.7062 * 0.1, abs=1e-3)
    md = (tmp_path / "out" / "report.md").read_text()
    assert "| sac | 0.500 [0.000, 1.000] |" in md and "| ddpg | 0.700 [-0.571, 1.971] (t) |" in md


def test_llm_alone_paused_beside_every_method_on_its_scored_scenarios(tmp_path):
    root = tmp_path / "runs"
    # the LLM alone, paused by its call budget after 2 of the 4 scenarios
    alone = _train_dir(root, "llm", 0, _metrics(0.1, 0.0, cr=0.0, ecr=0.3), controller="llm", frames=0)
    (alone / "final_metrics.json").write_text(json.dumps({
        "frames": 0, **{f"eval/{k}": v for k, v in _metrics(0.1, 0.0, cr=0.0, ecr=0.3).items()},
        "eval/complete": 0, "eval/episodes_scored": 2, "eval/episodes_total": 4,
        "llm/calls": 2000, "llm/http_calls": 1500, "llm/fallbacks": 3, "llm/wall_s": 3000.0}))
    # the heuristic, two seeds; on scenarios 0-1: DCR 15/20 = 0.75 and 20/20 = 1.0 (0.875), SLR 0.5
    # and 1.0, ECR 400/2000 = 0.2 both. Its bootstrap over those two scenarios (not all four): the
    # lowest DCR, 0.5, is seed 0 drawn twice and scenario 1 twice (1/16 > 2.5%), the highest, 1.0,
    # far more often: [0.5, 1.0]
    total, e_total = [10.0] * 4, [1000.0] * 4
    for s, (data, landed) in enumerate((([10, 5, 0, 0], [True, False, True, True]), ([10, 10, 0, 0], [True, True, False, False]))):
        d = _train_dir(root, "heuristic", s, _metrics(0.5, 0.5), controller="heuristic", frames=0)
        _full_episodes(d, 0, data_collected=data, data_total=total, landed=landed, energy_used=[100, 300, 999, 999],
                       energy_total=e_total)
    # sac, one seed: 6/20 = 0.3 collected, one of two collided
    d = _train_dir(root, "sac", 0, _metrics(0.9, 0.9))
    _full_episodes(d, 1000, data_collected=[2, 4, 9, 9], data_total=total, collided=[False, True, False, False],
                   energy_used=[0] * 4, energy_total=e_total)
    # ddpg evaluated on one scenario only: not one episode per scenario, left out
    _full_episodes(_train_dir(root, "ddpg", 0, _metrics(0.9, 0.9)), 1000, data_collected=[1], data_total=[10.0],
                   energy_used=[0], energy_total=[1000.0])
    res = report.build(root, tmp_path / "out")
    rows = {r["method"]: r for r in res["tables"]["llm_alone"]}
    assert list(rows) == ["llm", "sac", "heuristic"]  # the LLM alone, then the others in the report's order
    assert rows["llm"]["scenarios"] == "0-1 (2 of 4)" and rows["llm"]["episodes"] == "2"
    assert rows["llm"]["DCR"] == pytest.approx(0.1) and rows["llm"]["ECR"] == pytest.approx(0.3)
    assert rows["llm"]["advisor_calls"] == "2000 decisions, 1500 HTTP, 3 fallbacks" and rows["llm"]["wall_s"] == 3000.0
    h = rows["heuristic"]
    assert (h["n_seeds"], h["DCR"], h["SLR"], h["ECR"]) == (2, pytest.approx(0.875), pytest.approx(0.75), pytest.approx(0.2))
    assert h["interval"] == "bootstrap" and (h["DCR_lo"], h["DCR_hi"]) == (0.5, 1.0)
    assert (rows["sac"]["DCR"], rows["sac"]["CR"], rows["sac"]["n_seeds"]) == (pytest.approx(0.3), pytest.approx(0.5), 1)
    # the paused run is still no finished run: out of the train table, listed as skipped
    assert {r["method"] for r in res["tables"]["train_final"]} == {"heuristic", "sac", "ddpg"}
    assert any("llm" in p and "2 of 4 episodes scored" in why for p, why in res["skipped"])


def test_llm_alone_in_shards_is_compared_on_the_scenarios_it_scored(tmp_path):
    """Two shards finished scenarios 0, 1 and 3 of 5 (2 in flight): the others are scored on
    those three rows, not on the first three."""
    root = tmp_path / "runs"
    alone = _train_dir(root, "llm", 0, _metrics(0.1, 0.0), controller="llm", frames=0)
    (alone / "final_metrics.json").write_text(json.dumps({
        "frames": 0, **{f"eval/{k}": v for k, v in _metrics(0.1, 0.0).items()},
        "eval/complete": 0, "eval/episodes_scored": 3, "eval/episodes_total": 5, "llm/calls": 3000}))
    _full_episodes(alone, 0, row=[0, 1, 3], data_collected=[1, 1, 1], data_total=[10.0] * 3, energy_used=[0] * 3,
                   energy_total=[1000.0] * 3)
    # the heuristic: 10, 4, (0), 6, (0) of 10 collected -> DCR on rows 0, 1, 3 = 20/30
    d = _train_dir(root, "heuristic", 0, _metrics(0.5, 0.5), controller="heuristic", frames=0)
    _full_episodes(d, 0, data_collected=[10, 4, 0, 6, 0], data_total=[10.0] * 5, energy_used=[0] * 5,
                   energy_total=[1000.0] * 5)
    rows = {r["method"]: r for r in report.build(root, tmp_path / "out")["tables"]["llm_alone"]}
    assert rows["llm"]["scenarios"] == rows["heuristic"]["scenarios"] == "0-1, 3 (3 of 5)"
    assert rows["heuristic"]["DCR"] == pytest.approx(20 / 30)
    assert report._spans([0, 1, 2, 4, 6, 7]) == "0-2, 4, 6-7" and report._spans([5]) == "5"


def test_report_on_synthetic_runs(tmp_path):
    import matplotlib

    matplotlib.use("Agg")
    root = tmp_path / "runs"
    _synthetic(root)
    res = report.build(root, tmp_path / "out")
    out = tmp_path / "out"
    t = res["tables"]
    skipped = dict(res["skipped"])
    assert skipped["train/ppo/seed0"].startswith("broken: final_metrics.json")
    assert skipped["train/ppo/seed1"] == "unfinished: no final_metrics.json"
    assert skipped["train/ppo/seed2"] == "unfinished: 500 of 1000 frames"
    assert skipped["scenario_n_ou/n_ou=5/sac/seed0"].startswith("broken: evaluation.json lacks")
    assert len(skipped) == 4
    assert res["runs"] == 9 + 6 + 6

    final = {r["method"]: r for r in t["train_final"]}
    assert [r["method"] for r in t["train_final"]] == ["sac", "ddpg", "random"]  # the paper's order
    assert final["sac"]["DCR"] == pytest.approx(0.7)
    assert final["sac"]["DCR_lo"] == pytest.approx(0.7 - 0.49683, abs=1e-4)
    assert final["sac"]["DCR_hi"] == pytest.approx(0.7 + 0.49683, abs=1e-4)
    assert final["random"]["DCR"] == pytest.approx(0.1) and final["random"]["n_seeds"] == 3
    learned = {r["method"]: r["learned"] for r in t["learned"]}
    # sac's DCR interval [0.203, 1.197] overlaps random's [-0.148, 0.348]; ddpg's [0.770, 0.870] does not
    assert learned == {"sac": "no", "ddpg": "yes"}

    fig5 = {(r["N_OU"], r["method"]): r for r in t["fig5_scenario_n_ou"]}
    assert fig5[(3, "sac")]["DCR"] == pytest.approx(0.85) and fig5[(7, "sac")]["DCR"] == pytest.approx(0.45)
    assert fig5[(3, "sac")]["n_seeds"] == 2 and math.isnan(fig5[(3, "random")]["DCR_lo"])
    # 95% interval of two values: mean +- 12.706 * sd / sqrt(2), sd = 0.0707
    assert fig5[(3, "sac")]["DCR_hi"] - fig5[(3, "sac")]["DCR"] == pytest.approx(12.7062 * 0.05, abs=1e-3)
    summary = {r["method"]: r for r in t["fig10_summary"]}
    # seed 0: (0.8 + 0.4) / 2 = 0.6; seed 1: (0.9 + 0.5) / 2 = 0.7
    assert summary["sac"]["DCR"] == pytest.approx(0.65) and summary["sac"]["SLR"] == pytest.approx(0.6)

    alr = {(r["actor_lr"], r["method"]): r for r in t["fig11_sensitivity_actor_lr"]}
    assert set(alr) == {(1e-4, "sac"), (1e-3, "sac")}  # the r8 = 2 runs are on another axis
    assert alr[(1e-4, "sac")]["DCR"] == pytest.approx(0.7) and alr[(1e-3, "sac")]["SLR"] == pytest.approx(0.05)
    r8 = {r["r8"]: r for r in t["fig12_sensitivity_r8"]}
    assert set(r8) == {1.0, 2.0} and r8[2.0]["DCR"] == pytest.approx(0.9)

    # training curves: the band's mean at 5 episodes is the mean of 10, 20, 30
    xs, ms, lo, hi = report.band([report.training_curve(r, "episodes") for r in report.collect(root)[0]
                                  if r.sweep == "train" and r.method == "sac"], n_points=3)
    assert xs == [0, 5, 10] and ms == pytest.approx([0, 20, 40])
    for stem in ("fig3_training_curves_episodes", "fig3_training_curves_frames", "fig5_scenario_n_ou",
                 "fig10_summary_radar", "fig11_sensitivity_actor_lr", "fig12_sensitivity_r8"):
        for ext in ("png", "pdf"):
            assert (out / f"{stem}.{ext}").stat().st_size > 1000, stem
    # regenerated from the same runs: the same bytes (a PDF carries no creation date)
    time.sleep(1.1)
    again = report.build(root, tmp_path / "again")
    assert sorted(again["figures"]) == sorted(res["figures"])
    for name in res["figures"]:
        assert (out / name).read_bytes() == (tmp_path / "again" / name).read_bytes(), name
    md = (out / "report.md").read_text()
    assert "learning-aid world" in md and "| ddpg |" in md and "train/ppo/seed1`: unfinished" in md
    assert "0.700 [0.203, 1.197]" in md and "torch | 2.13.0+cpu" in md
    # 15 train runs record their machine; the 6 evaluations (their records made without one) do not
    assert "Machine(s): Test CPU, 2 cores; not recorded for 6 of 21 runs" in md
    runs_csv = (out / "runs.csv").read_text()
    assert "python -m uavlae.train +exp=sac seed=0" in runs_csv and "abcdef1234" in runs_csv
    # train and evaluation runs name their commit alike, cut to 10 characters
    assert "abcdef1234," in runs_csv and "1234567890," in runs_csv and "abcdef12345" not in runs_csv
    assert final["sac"]["advisor_calls"] == "7"

    # more seeds and a new method, then aggregated again without touching the rest
    _train_dir(root, "sac", 3, _metrics(0.7, 0.7))
    _train_dir(root, "cpo", 0, _metrics(0.3, 0.3))
    t2 = report.build(root, tmp_path / "out")["tables"]
    final2 = {r["method"]: r for r in t2["train_final"]}
    assert final2["sac"]["n_seeds"] == 4 and final2["sac"]["DCR"] == pytest.approx(0.7)
    assert final2["cpo"]["n_seeds"] == 1 and final2["cpo"]["DCR"] == pytest.approx(0.3)


def test_records_keep_what_the_report_reads_with_relative_paths(tmp_path):
    from uavlae.experiments.records import write_records

    root = tmp_path / "quick"
    _synthetic(root)
    d = root / "train" / "sac" / "seed0"
    (d / "checkpoints").mkdir()
    (d / "checkpoints" / "last.pt").write_bytes(b"state")
    (d / "wandb").mkdir()
    (d / "wandb" / "run.wandb").write_text("x")
    (d / "trajectory_0.png").write_bytes(b"png")
    (d / "logs" / "scalars" / "train" / "loss_actor.csv").write_text("1,2\n")
    cfg = json.loads((d / "config.json").read_text())
    cfg["run_dir"] = str(d)  # a resumed run saves its folder resolved
    (d / "config.json").write_text(json.dumps(cfg))
    meta = json.loads((d / "meta.json").read_text())
    (d / "meta.json").write_text(json.dumps({**meta, "argv": [str(tmp_path / "uavlae" / "train.py")], "pid": 7}))
    sweep = root / ".multirun" / "train" / "2026-01-01_00-00-00"
    sweep.mkdir(parents=True)
    (sweep / "multirun.yaml").write_text(f"hydra:\n  runtime:\n    cwd: {tmp_path}\n  job:\n    name: train\n"
                                         f"  overrides:\n    task: [+sweep=train, experiment.root={root}]\n")
    files = write_records(root, tmp_path / "records", base=tmp_path)
    rec = tmp_path / "records" / "train" / "sac" / "seed0"
    kept = sorted(str(p.relative_to(rec)) for p in rec.rglob("*") if p.is_file())
    assert kept == ["config.json", "final_metrics.json", "logs/scalars/episode/mean_return.csv",
                    "logs/scalars/override/advisor/calls.csv",
                    "logs/scalars/train/episodes.csv", "meta.json"]
    assert json.loads((rec / "config.json").read_text())["run_dir"] == "quick/train/sac/seed0"
    assert set(json.loads((rec / "meta.json").read_text())) == {"git", "packages", "machine", "command"}
    assert (tmp_path / "records" / ".multirun" / "train" / "2026-01-01_00-00-00" / "multirun.yaml").read_text() == (
        "hydra:\n  job:\n    name: train\n  overrides:\n    task:\n    - +sweep=train\n    - experiment.root=quick\n")
    assert not any(str(tmp_path) in (tmp_path / "records" / f).read_text() for f in files)
    # what the report reads is all there: the same tables from the records as from the runs
    assert report.build(tmp_path / "records", tmp_path / "a")["tables"] == report.build(root, tmp_path / "b")["tables"]
    # a path the records cannot make relative is an error naming the file and the key
    cfg["trainer"] = {**cfg.get("trainer", {}), "eval_set": "/elsewhere/sets/eval.json"}
    (d / "config.json").write_text(json.dumps(cfg))
    with pytest.raises(ValueError, match=r"train/sac/seed0/config.json.trainer.eval_set: /elsewhere/sets/eval.json"):
        write_records(root, tmp_path / "records", base=tmp_path)
    assert (tmp_path / "records" / "train" / "sac" / "seed0" / "config.json").is_file()  # the old records stay


@pytest.mark.parametrize("profile", ["quick", "long", "budget"])
def test_the_committed_report_regenerates_from_the_committed_records(profile, tmp_path, monkeypatch):
    """Every table, the report and its list of figures, byte for byte, from ``results/<profile>/records``."""
    import matplotlib

    matplotlib.use("Agg")
    monkeypatch.chdir(REPO_ROOT)  # the report names its folders relative to where it runs
    committed = REPO_ROOT / "results" / profile
    written_by = next(ln for ln in (committed / "report.md").read_text().splitlines() if ln.startswith("Written by: "))
    command = written_by.split("`")[1]
    assert command == f"python -m uavlae.experiments.report results/{profile}/records --out results/{profile}"
    res = report.build(Path("results") / profile / "records", tmp_path, command)
    assert res["skipped"] == []
    for f in sorted(tmp_path.iterdir()):
        if f.suffix in (".csv", ".md", ".json"):
            assert f.read_bytes() == (committed / f.name).read_bytes(), f.name
    figures = {f.name for f in tmp_path.iterdir() if f.suffix in (".png", ".pdf")}
    assert figures == set(res["figures"]) and figures <= {f.name for f in committed.iterdir()}


def test_report_cli_names_a_missing_dir(tmp_path):
    res = subprocess.run([sys.executable, "-m", "uavlae.experiments.report", str(tmp_path / "nope")], cwd=REPO_ROOT,
                         capture_output=True, text=True, timeout=120)
    assert res.returncode != 0 and "is not a directory" in res.stderr


# ---------------------------------------------------------------------------- train / evaluate


def test_config_differences_by_hand():
    from uavlae.lifecycle import config_differences

    want = {"env": {"t_max": 5, "maps": {"n": 2}}, "seed": 0, "lr": 1e-3}
    have = {"env": {"t_max": 7}, "seed": 0, "old": 1}
    # env.maps.n: only this run has it (added since); env.t_max: another value; old: since removed
    changed, added = config_differences(want, have)
    assert added == ["env.maps.n", "lr"] and changed == ["env.t_max", "old"]
    assert config_differences(want, want) == ([], [])
    # a value that became a section: the saved scalar's key is gone from this run, so changed
    assert config_differences({"a": {"b": 1}}, {"a": 1}) == (["a"], ["a.b"])


def test_a_run_is_dirty_when_its_code_differs_not_when_results_were_regenerated(tmp_path, monkeypatch):
    from uavlae import runlog

    def git(*args: str) -> str:
        return subprocess.run(["git", "-c", "user.name=t", "-c", "user.email=t@t", *args], cwd=tmp_path, check=True,
                              capture_output=True, text=True).stdout.strip()

    (tmp_path / "results").mkdir()
    (tmp_path / "results" / "report.md").write_text("old\n")
    (tmp_path / "code.py").write_text("x = 1\n")
    git("init", "-q")
    git("add", ".")
    git("commit", "-qm", "first")
    monkeypatch.setattr(runlog, "REPO_ROOT", tmp_path)
    assert runlog.git_info() == {"commit": git("rev-parse", "HEAD"), "dirty": False}
    (tmp_path / "results" / "report.md").write_text("regenerated\n")
    (tmp_path / "notes.txt").write_text("untracked\n")
    assert runlog.git_info()["dirty"] is False
    (tmp_path / "code.py").write_text("x = 2\n")
    assert runlog.git_info()["dirty"] is True


def test_reuse_skips_finished_and_resumes_unfinished_runs(tmp_path, monkeypatch):
    from uavlae.checkpoint import LAST, PREV, checkpoint_dir, load_checkpoint
    from uavlae.train import run

    monkeypatch.chdir(tmp_path)  # a relative run_dir, as the sweeps give it
    run_dir = tmp_path / "r"
    args = ["+exp=sac", "run_dir=r", "experiment.reuse=true", *TINY]
    first = run(_cfg(*args))
    assert first["frames"] == 128 and first["episodes"] >= 0
    stamp = (run_dir / "final_metrics.json").stat().st_mtime_ns
    assert run(_cfg(*args)) == first and (run_dir / "final_metrics.json").stat().st_mtime_ns == stamp
    # killed after 64 frames: the checkpoint of 64 frames is the last one, no final file
    ckpts = checkpoint_dir(run_dir)
    shutil.copy(ckpts / PREV, ckpts / LAST)
    (run_dir / "final_metrics.json").unlink()
    assert load_checkpoint(run_dir)[0]["counters"]["frames"] == 64
    resumed = run(_cfg(*args))
    assert resumed["frames"] == 128 and resumed["eval/DCR"] == pytest.approx(first["eval/DCR"])
    assert resumed["actor_param_sum"] == pytest.approx(first["actor_param_sum"], rel=1e-6)
    assert run(_cfg(*args)) == resumed  # finished now: kept as it is
    # a larger frame budget extends the run from its final checkpoint (it kept its buffer)
    extended = run(_cfg(*args[:-len(TINY)], *TINY[1:], "trainer.total_frames=256"))
    assert extended["frames"] == 256 and extended["updates"] > resumed["updates"]
    with pytest.raises(ValueError, match=r"holds a run of another config.*algo.actor_lr: recorded 0.0001, asked 0.001"):
        run(_cfg(*args, "algo.actor_lr=1e-3"))


def test_reuse_keeps_a_run_made_before_a_setting_existed(tmp_path, monkeypatch):
    from uavlae.train import run

    monkeypatch.chdir(tmp_path)
    args = ["+exp=sac", "run_dir=r", "experiment.reuse=true", *TINY]
    first = run(_cfg(*args))
    saved = json.loads((tmp_path / "r" / "config.json").read_text())
    del saved["env"]["maps"]  # as written by the code before env.maps existed
    (tmp_path / "r" / "config.json").write_text(json.dumps(saved))
    assert run(_cfg(*args)) == first  # finished: kept, not refused
    saved["env"]["t_max"] = 7  # a setting the saved run did have, with another value: refused
    (tmp_path / "r" / "config.json").write_text(json.dumps(saved))
    with pytest.raises(ValueError, match=r"holds a run of another config.*env.t_max: recorded 7, asked 1000"):
        run(_cfg(*args))


def test_episode_budget_stops_training(tmp_path):
    from uavlae.train import run

    # 10-step episodes (t_max) on 4 rows: 4 episodes end every 10 frames-per-row -> 8 episodes by 80 frames
    final = run(_cfg("+exp=sac", f"run_dir={tmp_path / 'e'}", *TINY, "env.t_max=10", "trainer.total_frames=100000",
                     "trainer.total_episodes=8", "trainer.frames_per_batch=8", "trainer.init_random_frames=8"))
    assert final["episodes"] >= 8 and final["frames"] < 200


def test_evaluate_honours_env_overrides(tmp_path):
    from uavlae.envs.scenario import load_scenarios
    from uavlae.evaluate import evaluate_checkpoint
    from uavlae.train import run

    run_dir = tmp_path / "sac"
    run(_cfg("+exp=sac", f"run_dir={run_dir}", *TINY, "trainer.eval_episodes=4"))
    over = ["env.ou.count.min=3", "env.ou.count.max=3", "env.ge.count.min=15", "env.ge.count.max=15"]
    out = tmp_path / "ev"
    agg = evaluate_checkpoint(_cfg(f"checkpoint={run_dir}", *over, f"experiment.eval_dir={out}", "trainer.eval_max_steps=10",
                                   "trainer.eval_episodes=4"), over)
    rec = json.loads((out / "evaluation.json").read_text())
    assert rec["spec"]["env_overrides"] == {"ou.count.min": 3, "ou.count.max": 3, "ge.count.min": 15, "ge.count.max": 15}
    assert rec["env"]["ou"]["count"] == {"min": 3, "max": 3, "pad": 7}  # the training padding kept
    assert rec["env"]["ge"]["count"] == {"min": 15, "max": 15, "pad": 15}
    scen = load_scenarios(out / "eval_set.json")
    assert len(scen) == 4 and rec["metrics"] == pytest.approx(agg)
    for sc in scen:
        d = sc.to_dict()
        assert len(d["ou_pos"]) == 3 and len(d["ge_pos"]) == 15
    # without overrides: the run's own world and evaluation set
    evaluate_checkpoint(_cfg(f"checkpoint={run_dir}", f"experiment.eval_dir={tmp_path / 'plain'}", "trainer.eval_max_steps=10",
                             "trainer.eval_episodes=4"))
    plain = json.loads((tmp_path / "plain" / "evaluation.json").read_text())
    assert plain["spec"]["env_overrides"] == {} and plain["eval_set_file"] == str(run_dir / "eval_set.json")
    assert plain["env"]["ou"]["count"] == {"min": 3, "max": 7, "pad": None}
    # a controller (no checkpoint) flies the command line's world itself
    ctrl = tmp_path / "random"
    evaluate_checkpoint(_cfg("+exp=random", "env.ou.count.min=5", "env.ou.count.max=5", f"experiment.eval_dir={ctrl}",
                             "trainer.eval_max_steps=10", "trainer.eval_episodes=2"), ["env.ou.count.min=5", "env.ou.count.max=5"])
    rec = json.loads((ctrl / "evaluation.json").read_text())
    assert rec["spec"]["checkpoint"] is None and rec["spec"]["method"] == "random" and rec["n_scenarios"] == 2
    assert [len(sc.to_dict()["ou_pos"]) for sc in load_scenarios(ctrl / "eval_set.json")] == [5, 5]
    with pytest.raises(ValueError, match="exceeds its padding maximum pad=7"):
        evaluate_checkpoint(_cfg(f"checkpoint={run_dir}", "env.ou.count.max=8", f"experiment.eval_dir={tmp_path / 'x'}"),
                            ["env.ou.count.max=8"])


# ---------------------------------------------------------------------------- multirun


def _sweep(*args: str, timeout: int = 400, wandb: str = "disabled") -> subprocess.CompletedProcess:
    # without WANDB_SERVICE: each job starts its own wandb service, not this test session's (tests/test_package.py)
    env = {k: v for k, v in os.environ.items() if k != "WANDB_SERVICE"}
    env.update(OMP_NUM_THREADS="1", UAVLAE_NUM_THREADS="1", WANDB_MODE=wandb, WANDB_SILENT="true")
    res = subprocess.run([sys.executable, *args], cwd=REPO_ROOT, env=env, capture_output=True, text=True, timeout=timeout)
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-3000:]
    return res


def test_joblib_sweeps_train_evaluate_report_and_log_their_dashboards_offline(tmp_path):
    from wandb_records import read_offline_run

    root = tmp_path / "exp"
    tiny = [t for t in TINY if not t.startswith("logger.")]
    campaign = ["experiment.profile=quick", f"experiment.root={root}", "logger.wandb.mode=offline"]
    _sweep("-m", "uavlae.train", "-m", "+sweep=train", "+exp=sac", "seed=0,1", *campaign, *tiny, wandb="offline")
    finals = {s: json.loads((root / "train" / "sac" / f"seed{s}" / "final_metrics.json").read_text()) for s in (0, 1)}
    assert all(f["frames"] == 128 for f in finals.values())
    meta = json.loads((root / "train" / "sac" / "seed0" / "meta.json").read_text())
    assert meta["command"].startswith("python -m uavlae.train ") and "+exp=sac" in meta["command"]
    assert meta["machine"]["logical_cores"] == os.cpu_count() and meta["machine"]["torch"] == torch.__version__
    _sweep("-m", "uavlae.evaluate", "-m", "+sweep=scenario_n_ou", "+exp=sac", "seed=0", "env.ou.count.max=3,7",
           *campaign, "trainer.eval_episodes=2", "trainer.eval_max_steps=10", "trainer.eval_plots=1", wandb="offline")
    for k in (3, 7):
        scen = json.loads((root / "eval_sets" / f"n_ou_{k}.json").read_text())
        assert [len(s["ou_pos"]) for s in scen] == [k, k]
        rec = json.loads((root / "scenario_n_ou" / f"n_ou={k}" / "sac" / "seed0" / "evaluation.json").read_text())
        assert rec["env"]["ou"]["count"] == {"min": k, "max": k, "pad": 7}
    _sweep("-m", "uavlae.experiments.report", str(root))
    md = (root / "report" / "report.md").read_text()
    assert "python -m uavlae.train -m +sweep=train +exp=sac seed=0,1" in md
    assert f"Machine(s): {meta['machine']['cpu']}, {os.cpu_count()} cores\n" in md  # every run records it: no "not recorded"
    assert "Fig. 5: metrics against N_OU" in md and (root / "report" / "fig5_scenario_n_ou.pdf").is_file()
    rows = (root / "report" / "runs.csv").read_text().splitlines()
    assert len(rows) == 1 + 2 + 2

    # the dashboards: one group for the invocation, runs named by method and seed, filterable tags,
    # the final and baseline metrics in the summary, the per-episode records as tables
    group = f"quick:{root}"
    for seed, final in finals.items():
        run_dir = root / "train" / "sac" / f"seed{seed}"
        (offline,) = (run_dir / "wandb").glob("offline-run-*")
        run = read_offline_run(offline)
        assert (run["group"], run["name"], run["job_type"]) == (group, f"sac seed{seed}", "train")
        assert set(run["tags"]) == {"method:sac", f"seed:{seed}", "sweep:train", "point:default", "profile:quick",
                                    "kind:train"}
        for key in ("eval/DCR", "eval/CR", "eval/SLR", "baseline/heuristic/DCR", "baseline/random/SLR", "wall_s"):
            assert run["summary"][key] == pytest.approx(final[key]), key
        with open(run_dir / "eval" / "frames_000000128" / "episodes.csv", newline="") as fh:
            episodes = list(csv.reader(fh))
        table = run["tables"]["eval/episodes"]
        assert table["columns"] == episodes[0] and len(table["data"]) == 2  # trainer.eval_episodes
        col = episodes[0].index("data_collected")
        assert [r[col] for r in table["data"]] == pytest.approx([float(r[col]) for r in episodes[1:]])
        assert {"baseline/heuristic/episodes", "baseline/random/episodes"} <= set(run["tables"])
    for k in (3, 7):
        out = root / "scenario_n_ou" / f"n_ou={k}" / "sac" / "seed0"
        (offline,) = (out / "wandb").glob("offline-run-*")
        run = read_offline_run(offline)
        assert (run["group"], run["name"], run["job_type"]) == (group, f"sac seed0 n_ou={k}", "evaluate")
        assert {"method:sac", "seed:0", "sweep:scenario_n_ou", f"point:n_ou={k}", "kind:evaluate"} <= set(run["tags"])
        metrics = json.loads((out / "evaluation.json").read_text())["metrics"]
        assert run["summary"]["eval/DCR"] == pytest.approx(metrics["DCR"]) and run["summary"]["frames"] == 128
        assert len(run["tables"]["eval/episodes"]["data"]) == 2


def test_ray_sweep_on_a_local_instance(tmp_path):
    pytest.importorskip("hydra_plugins.hydra_ray_launcher")
    root = tmp_path / "exp"
    # address null: the launcher starts a local Ray instance of 2 CPUs for the sweep and stops it
    res = _sweep("-m", "uavlae.train", "-m", "+sweep=train", "+exp=random", "seed=0,1", "hydra/launcher=ray_local",
                 f"experiment.root={root}", "trainer.eval_episodes=2", "trainer.eval_max_steps=10", "trainer.eval_plots=0")
    assert "Ray Launcher is launching 2 jobs" in res.stdout + res.stderr
    finals = [json.loads((root / "train" / "random" / f"seed{s}" / "final_metrics.json").read_text()) for s in (0, 1)]
    assert all(f["frames"] == 0 and 0 <= f["eval/DCR"] <= 1 for f in finals)
    pids = {json.loads((root / "train" / "random" / f"seed{s}" / "meta.json").read_text())["pid"] for s in (0, 1)}
    assert len(pids) == 2 and os.getpid() not in pids  # two Ray workers, not this process


def test_submitit_local_sweep_runs_the_slurm_path_on_this_machine(tmp_path):
    pytest.importorskip("hydra_plugins.hydra_submitit_launcher")
    root = tmp_path / "exp"
    res = _sweep("-m", "uavlae.train", "-m", "+sweep=train", "+exp=random", "seed=0,1", "hydra/launcher=slurm_local",
                 f"experiment.root={root}", "trainer.eval_episodes=2", "trainer.eval_max_steps=10", "trainer.eval_plots=0")
    assert "Submitit 'local' sweep output dir" in res.stdout + res.stderr
    finals = [json.loads((root / "train" / "random" / f"seed{s}" / "final_metrics.json").read_text()) for s in (0, 1)]
    assert all(f["frames"] == 0 and 0 <= f["eval/DCR"] <= 1 for f in finals)
    pids = {json.loads((root / "train" / "random" / f"seed{s}" / "meta.json").read_text())["pid"] for s in (0, 1)}
    assert len(pids) == 2 and os.getpid() not in pids  # two submitit jobs, not this process
    # submitit's own records of each job: its pickled result beside its logs
    assert len(list(root.glob(".multirun/train/*/.submitit/*/*_result.pkl"))) == 2


def test_wandb_group_name_and_tags_by_hand():
    from types import SimpleNamespace

    from uavlae.runlog import wandb_group, wandb_name, wandb_tags

    def ex(**kw):
        base = {"sweep": "train", "profile": "quick", "root": "runs/quick", "point": "default", "method": "sac", "tags": ()}
        return SimpleNamespace(**{**base, **kw})

    # make quick and make baselines-budget: the same profile and sweep, two campaigns, two groups
    assert wandb_group(None, ex()) == "quick:runs/quick"
    assert wandb_group(None, ex(root="runs/budget/")) == "quick:runs/budget"
    assert wandb_group(None, ex(profile=None)) == "runs/quick"
    assert wandb_group(None, ex(sweep=None)) is None and wandb_group("mine", ex()) == "mine"
    assert wandb_name("sac", 2, ex()) == "sac seed2"
    assert wandb_name("ppo", 0, ex(sweep="scenario_n_ou", point="n_ou=3")) == "ppo seed0 n_ou=3"
    assert wandb_name("sac", 0, ex(sweep=None, point="x")) == "sac seed0"
    assert wandb_tags(["a" * 70], ex(sweep="scenario_n_ou", point="n_ou=3"), 1, kind="evaluate", method="ppo") == [
        "a" * 64, "method:ppo", "seed:1", "sweep:scenario_n_ou", "point:n_ou=3", "profile:quick", "kind:evaluate"]


def test_wandb_runs_are_grouped_by_invocation_named_and_tagged_with_trajectory_images(tmp_path, monkeypatch):
    from uavlae.factories import make_logger

    cfg = _cfg("+sweep=train", "+profile=quick", "+exp=sac", "seed=1", "logger.wandb.mode=offline")
    monkeypatch.chdir(tmp_path)
    # a relative run folder (the default runs/<name>/<time>) reaches wandb resolved: a wandb service
    # shared with another process would resolve it against that process's working directory
    logger = make_logger(cfg, Path("."), "sac-test", {"name": "sac"})
    try:
        run = logger.loggers["wandb"].experiment
        assert Path(run.dir).is_absolute() and Path(run.dir).is_relative_to(tmp_path.resolve())
        assert run.group == "quick:runs/quick" and run.name == "sac seed1"  # the profile and its sweeps' root
        assert set(run.tags) == {"method:sac", "seed:1", "sweep:train", "point:default", "profile:quick", "kind:train"}
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        plt.plot([0, 1], [0, 1])
        plt.savefig(tmp_path / "trajectory_0.png")
        plt.close()
        logger.log_metrics({"eval/DCR": 0.5}, step=64)
        logger.log_images({"eval/trajectory_0": tmp_path / "trajectory_0.png"}, step=64)
    finally:
        logger.close()
    assert list((tmp_path / "wandb").glob("offline-run-*/files/media/images/eval/trajectory_0_*.png"))


def test_the_committed_heuristics_table_regenerates_from_its_record():
    """``results/heuristics_table.md``, byte for byte, from the ``heuristics_table.json`` beside it."""
    from uavlae.experiments.heuristics_table import markdown

    record = json.loads((REPO_ROOT / "results" / "heuristics_table.json").read_text())
    seed = int(record["runs"][0]["command"].split("trainer.eval_seed=")[1].split()[0])
    assert markdown(record, seed).encode() == (REPO_ROOT / "results" / "heuristics_table.md").read_bytes()


def test_every_report_helper_is_written_once_in_the_toolkit():
    """Reading JSON or CSV, writing CSV and saving a figure happen in uavlae/experiments/reporting.py
    only; every report writer goes through it."""
    import ast

    import uavlae.experiments

    def does_io(node: ast.Call) -> str | None:
        f = node.func
        if isinstance(f, ast.Attribute) and isinstance(f.value, ast.Name) and f.value.id == "csv":
            return f"csv.{f.attr}"
        if isinstance(f, ast.Attribute) and f.attr == "savefig":
            return "savefig"
        if (isinstance(f, ast.Attribute) and f.attr == "loads" and node.args and isinstance(node.args[0], ast.Call)
                and isinstance(node.args[0].func, ast.Attribute) and node.args[0].func.attr == "read_text"):
            return "json.loads(read_text)"
        return None

    found = []
    for path in sorted(Path(uavlae.experiments.__file__).parent.glob("*.py")):
        if path.name == "reporting.py":
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Call) and (what := does_io(node)):
                found.append(f"{path.name}:{node.lineno} {what}")
    assert found == []


def test_a_flag_cell_reads_as_the_records_and_other_tables_write_it():
    from uavlae.experiments.reporting import cell_true

    assert [cell_true(v) for v in ("True", "true", " TRUE ", "1", "1.0", 1, True)] == [True] * 7
    assert [cell_true(v) for v in ("False", "false", "0", "0.0", "", "yes", 0, False)] == [False] * 8
