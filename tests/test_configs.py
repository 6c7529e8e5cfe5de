"""Every `+exp` composes and validates; struct mode and the pydantic models reject bad keys."""

from __future__ import annotations

import pytest
from hydra import compose, initialize_config_dir
from hydra.errors import ConfigCompositionException
from omegaconf import OmegaConf

from uavlae.factories import CONF_DIR, validate_config

EXPS = sorted(p.stem for p in (CONF_DIR / "exp").glob("*.yaml"))


@pytest.fixture(scope="module")
def hydra_ctx():
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        yield


def _compose(*overrides: str):
    return compose("config", overrides=list(overrides))


def test_all_paper_exps_exist():
    assert set(EXPS) >= {"sac_llm", "sac_llm_fp", "sac_heuristic", "sac", "ppo", "ddpg", "cpo", "heuristic", "llm"}


@pytest.mark.parametrize("exp", EXPS)
def test_exp_composes_and_validates(hydra_ctx, exp):
    cfg = _compose(f"+exp={exp}")
    assert OmegaConf.is_struct(cfg)
    assert cfg.name == exp
    validate_config(OmegaConf.create(OmegaConf.to_container(cfg, resolve=True)))
    if exp in ("heuristic", "llm", "random", "heuristic_planner"):
        assert cfg.controller == exp.removesuffix("_planner") and "algo" not in cfg
    else:
        assert cfg.controller == "learner"
    # the paper's greedy heuristic wherever one acts, the planner only under its own names
    assert cfg.heuristic_kind == ("planner" if exp.endswith("_planner") or exp.startswith("pilot") else "greedy")
    expected_advisor = {
        "sac_llm": "llm", "sac_llm_amortized": "llm", "sac_llm_fp": "llm", "sac_heuristic": "heuristic", "sac_heuristic_planner": "heuristic", "pilot": "heuristic", "pilot_drawn": "heuristic", "pilot_mean": "heuristic", "pilot_cruise": "heuristic", "llm": "llm",
        "sac_hover": "hover", "sac_random_advice": "random",
    }
    assert cfg.advisor.kind == expected_advisor.get(exp, "none")
    assert cfg.advisor.get("amortize", False) == (exp == "sac_llm_amortized")
    # the resolved config never holds an API key, only the variable's name
    assert set(cfg.llm.keys()) & {"api_key"} == set()


def test_paper_values(hydra_ctx):
    cfg = _compose("+exp=sac_llm")
    assert cfg.advisor.mode == "proximity" and cfg.advisor.d_th == 15.0
    assert cfg.algo.actor_lr == 1e-4 and cfg.algo.critic_lr == 3e-4 and list(cfg.algo.hidden) == [64, 64]
    assert _compose("+exp=sac_llm_fp").advisor.fp == 0.3
    assert _compose("+exp=ppo").algo.clip_epsilon == 0.2
    assert _compose("+exp=cpo").algo.cost_limit == 0.05 and _compose("+exp=cpo").algo.target_kl == 0.01
    # the trainer reads the algo's numbers unless told otherwise
    cfg = _compose("+exp=sac", "algo.utd_ratio=2.0")
    assert cfg.trainer.utd_ratio == 2.0 and cfg.trainer.batch_size == 256
    assert _compose("+exp=ppo").trainer.frames_per_batch == 2048


@pytest.mark.parametrize("override", ["trainer.no_such_key=1", "env.area.no_such=1", "advisor.nope=1", "nope=1"])
def test_unknown_keys_error(hydra_ctx, override):
    with pytest.raises(ConfigCompositionException):
        _compose("+exp=sac", override)


@pytest.mark.parametrize(
    "override, field",
    [
        ("+trainer.no_such_key=1", "trainer.no_such_key"),
        ("+algo.no_such_key=1", "algo.no_such_key"),
        ("+env.no_such_key=1", "env.no_such_key"),
        ("trainer.env_batch_size=0", "trainer.env_batch_size"),
        ("trainer.frames_per_batch=100", "frames_per_batch"),
        ("advisor.fp=1.5", "advisor.fp"),
        ("algo.gamma=2.0", "algo.gamma"),
        ("env.motion.v_max=-1.0", "env.motion"),
        ("logger.wandb.mode=sometimes", "logger.wandb.mode"),
    ],
)
def test_bad_values_are_rejected_by_name(hydra_ctx, override, field):
    cfg = _compose("+exp=sac", override)
    with pytest.raises(ValueError, match=field.replace(".", r"\.")):
        validate_config(OmegaConf.create(OmegaConf.to_container(cfg, resolve=True)))


def test_stronger_learners_compose(hydra_ctx):
    """Beyond the paper: `algo=sac_ln` swaps SAC's networks for LayerNorm 2x256 under any SAC exp,
    and `+exp=crossq` hands the loop CrossQ's numbers; both are off-policy, so advice may go with them."""
    cfg = _compose("+exp=sac", "algo=sac_ln")
    assert cfg.name == "sac" and cfg.algo.layer_norm and list(cfg.algo.hidden) == [256, 256]
    assert cfg.algo.loss_impl == "torchrl" and cfg.algo.actor_lr == 1e-4 and cfg.trainer.batch_size == 256
    validate_config(OmegaConf.create(OmegaConf.to_container(cfg, resolve=True)))
    cfg = _compose("+exp=crossq", "advisor=heuristic_override")
    assert cfg.algo.policy_delay == 3 and cfg.trainer.utd_ratio == 1.0 and cfg.trainer.init_random_frames == 5000
    validate_config(OmegaConf.create(OmegaConf.to_container(cfg, resolve=True)))
    cfg = _compose("+exp=sac", "algo.layer_norm=true")  # with the default fused update
    with pytest.raises(ValueError, match=r"algo\.layer_norm needs algo\.loss_impl=torchrl"):
        validate_config(OmegaConf.create(OmegaConf.to_container(cfg, resolve=True)))


@pytest.mark.parametrize("overrides, problem", [
    (("+exp=sac_llm", "advisor.label_all=true", "algo.clone_weight=0.4"), "only the heuristic"),
    (("+exp=sac_heuristic_planner", "advisor.label_all=true"), r"algo\.clone_weight is 0"),
])
def test_teacher_labels_need_the_heuristic_and_a_cloning_term(hydra_ctx, overrides, problem):
    cfg = _compose(*overrides)
    with pytest.raises(ValueError, match=problem):
        validate_config(OmegaConf.create(OmegaConf.to_container(cfg, resolve=True)))
    good = _compose("+exp=pilot", "advisor.label_all=true")
    validate_config(OmegaConf.create(OmegaConf.to_container(good, resolve=True)))


def test_advisor_on_an_on_policy_learner_is_rejected(hydra_ctx):
    cfg = _compose("+exp=ppo", "advisor=heuristic_override")
    with pytest.raises(ValueError, match="on-policy"):
        validate_config(OmegaConf.create(OmegaConf.to_container(cfg, resolve=True)))


def test_resolved_config_never_holds_the_api_key(hydra_ctx, monkeypatch):
    from uavlae.factories import redact_secrets

    monkeypatch.setenv("DEEPSEEK_API_KEY", "sk-test-secret-123")
    cfg = _compose("+exp=sac_llm", "llm=deepseek")
    resolved = OmegaConf.to_container(cfg, resolve=True)
    assert resolved["llm"]["api_key_env"] == "DEEPSEEK_API_KEY"
    assert "sk-test-secret-123" not in repr(resolved)
    # a key pasted into any field by mistake is not written to the run's files
    resolved["llm"]["model"] = "model-sk-test-secret-123"
    assert "sk-test-secret-123" not in repr(redact_secrets(resolved))


def _makefile_rungs() -> dict[str, list[str]]:
    """The pilot study's rungs as the Makefile defines them (``RUNG_X = keys``, where the keys may
    name an earlier rung as ``$(RUNG_Y)``), each expanded to its override list."""
    from pathlib import Path

    text = (Path(__file__).resolve().parents[1] / "Makefile").read_text().replace("\\\n", " ")
    raw = {}
    for line in text.splitlines():
        name, sep, value = line.partition(" = ")
        if sep and name.startswith("RUNG_"):
            raw[name] = value.split()

    def expand(name: str) -> list[str]:
        return [k for key in raw[name] for k in (expand(key[2:-1]) if key.startswith("$(RUNG_") else [key])]

    return {name: [k.strip("'") for k in expand(name)] for name in raw}


def test_every_pilot_rung_composes_and_keeps_the_rules(hydra_ctx):
    """Every rung of the ladder, composed as `make pilot-screen-*` composes it, validates and breaks
    no rule of uavlae/rules.py, and every rung of the report's ladder has a Makefile target."""
    from pathlib import Path

    from uavlae.envs import make_env_config
    from uavlae.experiments.pilot import LADDER, RECIPES
    from uavlae.rules import run_problems

    rungs = _makefile_rungs()
    assert {"RUNG_TEACH_ALL", "RUNG_WISH_TEACH_ALL", "RUNG_LAG"} <= set(rungs)
    for name, keys in rungs.items():
        cfg = _compose("+sweep=pilot", "+profile=quick", "env=default", *keys)
        validate_config(OmegaConf.create(OmegaConf.to_container(cfg, resolve=True)))
        assert run_problems(cfg, make_env_config(cfg.env)) == [], name
    assert rungs["RUNG_WISH_TEACH_ALL"][-1] == "safety_filter.learn_from=proposed"
    makefile = (Path(__file__).resolve().parents[1] / "Makefile").read_text()
    assert all(f"experiment.method={rung}" in makefile for rung in LADDER if rung not in RECIPES)
    # the verdict's recipes: a config each, run under their own name
    assert "+exp=$(PILOT_RECIPE)" in makefile and "experiment.method=$(PILOT_RECIPE)" in makefile
    for recipe in RECIPES:
        cfg = _compose("+sweep=pilot", "+profile=quick", "env=default", f"+exp={recipe}")
        validate_config(OmegaConf.create(OmegaConf.to_container(cfg, resolve=True)))
        assert run_problems(cfg, make_env_config(cfg.env)) == [] and cfg.name == recipe


def test_the_committed_pilots_recipe_is_the_second_recipe_under_its_own_name(hydra_ctx):
    """+exp=pilot composes +exp=pilot_drawn (the recipe its verdict chose): the two configs differ
    in the name and what follows from it (the run folder, the method) and nowhere else."""
    def flat(cfg, prefix=""):
        out = {}
        for k, v in cfg.items():
            out.update(flat(v, f"{prefix}{k}.") if isinstance(v, dict) else {f"{prefix}{k}": v})
        return out

    pilot, drawn = (flat(OmegaConf.to_container(_compose(f"+exp={e}"), resolve=True)) for e in ("pilot", "pilot_drawn"))
    assert {k for k in pilot.keys() | drawn.keys() if pilot.get(k) != drawn.get(k)} == {"name", "run_dir", "experiment.method"}
    assert pilot["trainer.eval_actor"] == "sample" and pilot["safety_filter.learn_from"] == "proposed"
