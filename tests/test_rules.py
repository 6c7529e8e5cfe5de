"""The rules of meaning (uavlae.rules, docs/model.md "Rules a run's config must meet"), each at its
edge worked out by hand, and check_run naming every broken rule in one message."""

from __future__ import annotations

import pytest

from tests.test_train import TINY, _cfg
from uavlae.envs import make_env_config
from uavlae.errors import ConfigError
from uavlae.rules import run_problems, world_problems


def test_the_default_world_breaks_no_rule():
    assert world_problems(make_env_config()) == []


def test_a_world_without_ges_names_the_key():
    (line,) = world_problems(make_env_config(ge={"count": {"min": 0, "max": 4}}))
    assert line.startswith("env.ge.count.min=0: a scenario without GEs has no data to collect")


def test_the_snr_of_a_ge_straight_below_must_reach_the_threshold():
    # SPEC §3 at d = H = 10 m: SNR = TP * alpha / H^2 / N = 0.01 * 0.36 / 100 / 1e-6 = 36
    assert world_problems(make_env_config(channel={"snr_threshold": 36.0})) == []
    (line,) = world_problems(make_env_config(channel={"snr_threshold": 36.5}))
    assert line.startswith("env.channel.snr_threshold=36.5 is above the SNR of a GE straight below the DCU (36 from")
    # at H = 32 m: 0.0036 / 1024 / 1e-6 = 3.52 < 3.6, the default threshold
    assert "env.area.altitude=32" in world_problems(make_env_config(area={"altitude": 32.0}))[0]


def test_the_energy_limit_must_pay_the_straight_flight_to_the_landing_area():
    # start (12.5, 487.5), LA [475, 500] x [0, 25]: d = hypot(462.5, 462.5) = 654.07 m, 66 slots of
    # P(10) + P(0) = 126.03 + 168.48 = 294.51 J (SPEC §4): E_min = 19,437.7 J
    assert world_problems(make_env_config(energy={"e_limit": 19500.0})) == []
    (line,) = world_problems(make_env_config(energy={"e_limit": 19400.0}))
    assert line.startswith("env.energy.e_limit=19400 J does not pay the straight flight") and "(19438 J)" in line


def test_a_start_inside_the_landing_area_names_both():
    (line,) = world_problems(make_env_config(area={"start": (480.0, 10.0)}))
    assert line == ("env.area.start=[480.0, 10.0] lies in the landing area env.area.landing=[475.0, 0.0, 500.0, 25.0]: "
                    "the first slot at rest would land; move one of them")


def test_an_advisor_that_is_never_asked():
    cfg = _cfg("+exp=sac_llm_fp", "advisor.fp=0.0")
    (line,) = run_problems(cfg, make_env_config(cfg.env))
    assert line.startswith("advisor.mode=fixed_prob with advisor.fp=0: the llm advisor would never be asked")
    assert run_problems(_cfg("+exp=sac_llm_fp"), make_env_config()) == []


def test_check_run_names_every_broken_rule_in_one_message(tmp_path):
    from uavlae.train import run

    with pytest.raises(ConfigError) as err:
        run(_cfg("+exp=sac", f"run_dir={tmp_path / 'r'}", *TINY, "env.ge.count.min=0", "env.ge.count.max=0",
                 "env.energy.e_limit=1000", "trainer.total_frames=16"))
    lines = str(err.value).splitlines()
    assert lines[0] == "the config breaks 4 rules:"  # 16 frames: below a batch of 32 and the warm-up of 32
    assert [ln.split("=", 1)[0].strip() for ln in lines[1:]] == [
        "env.ge.count.min", "env.energy.e_limit", "trainer.total_frames", "trainer.total_frames"]
    assert not (tmp_path / "r").exists()


def test_a_rule_between_two_keys_does_not_quote_their_section():
    with pytest.raises(ConfigError) as err:
        make_env_config(motion={"v_limit": 20.0})
    assert str(err.value) == ("invalid environment config:\n"
                              "  env.motion: motion.v_limit=20.0 must be < motion.v_max=10.0")


def test_the_filters_training_options_need_the_filter_in_training_and_the_cost_a_learner_that_reads_it():
    cfg = _cfg("+exp=sac", "safety_filter.mode=deploy", "safety_filter.penalty=1.0", "safety_filter.learn_from=proposed")
    (line,) = run_problems(cfg, make_env_config(cfg.env))
    assert line.startswith("safety_filter.penalty=1.0 safety_filter.learn_from=proposed with safety_filter.mode=deploy: "
                           "nothing is filtered in training")
    cfg = _cfg("+exp=sac", "safety_filter.mode=train_and_deploy", "safety_filter.cost=1.0")
    (line,) = run_problems(cfg, make_env_config(cfg.env))
    assert line.startswith("safety_filter.cost=1 with algo=sac: that learner reads no cost")
    cfg = _cfg("+exp=sac_lag", "safety_filter.mode=train_and_deploy", "safety_filter.cost=1.0",
               "safety_filter.learn_from=proposed")
    assert run_problems(cfg, make_env_config(cfg.env)) == []


def test_an_on_policy_learner_through_the_filter_stores_its_wish():
    cfg = _cfg("+exp=ppo", "safety_filter.mode=train_and_deploy")
    (line,) = run_problems(cfg, make_env_config(cfg.env))
    assert line.startswith("safety_filter.mode=train_and_deploy with algo=ppo and safety_filter.learn_from=executed: ")
    cfg = _cfg("+exp=ppo", "safety_filter.mode=train_and_deploy", "safety_filter.learn_from=proposed")
    assert run_problems(cfg, make_env_config(cfg.env)) == []


def test_a_deterministic_actor_cannot_fly_by_draws():
    cfg = _cfg("+exp=ddpg", "trainer.eval_actor=sample")
    (line,) = run_problems(cfg, make_env_config(cfg.env))
    assert line == ("trainer.eval_actor=sample with algo=ddpg: its actor is deterministic, there is no policy to "
                    "draw from; use trainer.eval_actor=mean")
    for exp in ("sac", "crossq", "ppo"):
        cfg = _cfg(f"+exp={exp}", "trainer.eval_actor=sample")
        assert run_problems(cfg, make_env_config(cfg.env)) == []
