"""The env config: SPEC defaults, the YAML mirror, and errors that name the field."""

import json

import pytest
import yaml

from uavlae.envs import UAVEnv
from uavlae.envs.config import EnvConfig, make_env_config
from uavlae.factories import CONF_DIR

CONF = CONF_DIR / "env" / "default.yaml"


def test_yaml_mirrors_the_model_defaults():
    from_yaml = make_env_config(yaml.safe_load(CONF.read_text()))
    assert from_yaml == EnvConfig()
    assert json.loads(from_yaml.model_dump_json()) == json.loads(EnvConfig().model_dump_json())


def test_spec_constants():
    c = EnvConfig()
    assert c.energy.p0 == pytest.approx(79.86, abs=0.005)  # (δ/8) ρ s A Ω³ R³
    assert c.energy.pi == pytest.approx(88.63, abs=0.005)  # (1+k) W^1.5 / sqrt(2 ρ A)
    assert c.area.start_xy == (12.5, 487.5)  # centre of TA


@pytest.mark.parametrize(
    "bad, field",
    [
        ({"area": {"x_size": -1}}, "area.x_size"),
        ({"zones": {"side_min": 120, "side_max": 60}}, "side_min"),
        ({"zones": {"side_max": 900}}, "zones.side_max"),
        ({"motion": {"v_max": float("nan")}}, "motion.v_max"),
        ({"ge": {"count": {"min": 5, "max": 20, "pad": 15}}}, "ge.count"),
        ({"ou": {"count": {"min": 6, "max": 3}}}, "ou.count"),
        ({"colour": "red"}, "colour"),
        ({"reward": {"r7_variant": "sometimes"}}, "reward.r7_variant"),
        ({"energy": {"e_limit": 2e6}}, "energy"),
    ],
)
def test_bad_input_names_the_field(bad, field):
    with pytest.raises(ValueError) as e:
        make_env_config(bad)
    assert field in str(e.value)
    with pytest.raises(ValueError):
        UAVEnv(bad)


def test_fixed_counts_are_respected():
    cfg = {"ge": {"count": {"min": 12, "max": 12}}, "ou": {"count": {"min": 4, "max": 4, "pad": 6}}}
    env = UAVEnv(cfg, batch_size=[16], seed=0)
    td = env.reset()
    assert (td["state", "ge_mask"].sum(-1) == 12).all()
    assert td["state", "ou_mask"].shape == (16, 6)
    assert (td["state", "ou_mask"].sum(-1) == 4).all()
