"""UAVEnv through the TorchRL API: specs, contract, resets, seeding and invariants."""

import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from torchrl.envs.utils import check_env_specs

from uavlae.envs import UAVEnv
from uavlae.envs.scenario import Scenario
from uavlae.envs.world import EVENT_KEYS, REWARD_KEYS, STATE_KEYS


@pytest.mark.parametrize("b", [1, 64])
def test_check_env_specs(b):
    env = UAVEnv(batch_size=[b], seed=0)
    check_env_specs(env, seed=0)


def test_defaults_and_output_contract():
    env = UAVEnv(batch_size=[4], seed=1)
    td = env.rollout(3, break_when_any_done=False)
    assert td.batch_size == torch.Size([4, 3])
    nxt = td["next"]
    assert nxt["observation"].shape == (4, 3, env.layout.size)
    assert torch.isfinite(nxt["observation"]).all()
    for k in REWARD_KEYS:
        assert nxt["reward_terms", k].shape == (4, 3, 1)
    total = sum(nxt["reward_terms", k] for k in REWARD_KEYS)
    torch.testing.assert_close(total, nxt["reward"])
    for k in EVENT_KEYS:
        assert nxt["events", k].dtype == torch.bool
    for k in STATE_KEYS:
        assert ("state", k) in nxt.keys(True)
    assert nxt["cost"].shape == (4, 3, 1)
    # energy_left is E_limit minus what was used
    torch.testing.assert_close(
        nxt["state", "energy_left"], env.cfg.energy.e_limit - nxt["state", "energy_used"]
    )


def test_hover_slot_energy_and_no_motion():
    # A zero action hovers: the DCU stays put and one slot costs P(0) (t_fly + t_hover) = 336.97 J.
    env = UAVEnv(batch_size=[2], seed=3)
    td = env.reset()
    td["action"] = torch.zeros(2, 2)
    out = env.step(td)["next"]
    torch.testing.assert_close(out["state", "position"], td["state", "position"])
    torch.testing.assert_close(out["state", "energy_used"], torch.full((2,), 336.97), atol=0.01, rtol=0)


def test_same_seed_same_rollout_and_different_seed_differs():
    def roll(seed):
        env = UAVEnv(batch_size=[8], seed=seed)
        torch.manual_seed(0)  # the random policy draws from the global generator
        return env.rollout(20, break_when_any_done=False)

    a, b, c = roll(5), roll(5), roll(6)
    for key in [("next", "state", "position"), ("next", "reward"), ("next", "state", "ou_pos")]:
        torch.testing.assert_close(a[key], b[key])
    assert not torch.equal(a["state", "ge_pos"], c["state", "ge_pos"])


def test_partial_reset_changes_only_masked_rows():
    env = UAVEnv(batch_size=[6], seed=2)
    td = env.reset()
    td["action"] = torch.full((6, 2), 0.3)
    td = env.step(td)
    from torchrl.envs.utils import step_mdp

    td = step_mdp(td)
    before = td.clone()
    mask = torch.tensor([True, False, True, False, False, False]).unsqueeze(-1)
    td["_reset"] = mask
    after = env.reset(td)
    keep = ~mask.squeeze(-1)
    for key in [("state", "position"), ("state", "ge_pos"), ("state", "step"), "observation"]:
        torch.testing.assert_close(after[key][keep], before[key][keep])
    assert (after["state", "step"][~keep] == 0).all()
    assert not torch.equal(after["state", "ge_pos"][~keep], before["state", "ge_pos"][~keep])


def test_fixed_scenarios_cycle_over_batch():
    s0 = Scenario(
        nfz=[(100.0, 100.0, 160.0, 160.0)], rz=[(300.0, 300.0, 360.0, 380.0)],
        bz=[(200.0, 50.0, 260.0, 120.0)], ge_pos=[(50.0, 400.0), (420.0, 420.0)],
        ge_data=[1.5, 2.0], ou_pos=[(250.0, 250.0)], ou_vel=[(1.0, 0.0)], start=(12.5, 487.5),
    )
    s1 = Scenario(
        nfz=[], rz=[], bz=[], ge_pos=[(250.0, 250.0)], ge_data=[3.0], ou_pos=[], ou_vel=[],
        start=(12.5, 487.5),
    )
    env = UAVEnv(batch_size=[5], seed=0, scenarios=[s0, s1])
    td = env.reset()
    assert td["state", "ge_mask"].sum(-1).tolist() == [2, 1, 2, 1, 2]
    torch.testing.assert_close(td["state", "data_total"], torch.tensor([3.5, 3.0, 3.5, 3.0, 3.5]))


@settings(max_examples=8, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(seed=st.integers(0, 2**31 - 1))
def test_invariants_over_random_rollouts(seed):
    env = UAVEnv(batch_size=[16], seed=seed)
    torch.manual_seed(seed)
    td = env.rollout(40, break_when_any_done=False)
    s, s0 = td["next", "state"], td["state"]
    # within every slot: energy used grows by a positive slot energy, remaining data never grows
    assert (s["energy_used"] > s0["energy_used"]).all()
    assert (s["ge_remaining"] <= s0["ge_remaining"] + 1e-6).all()
    assert (s["data_collected"] >= s0["data_collected"]).all()
    pos = s["position"]
    assert (pos[..., 0] >= 0).all() and (pos[..., 0] <= env.cfg.area.x_size).all()
    assert (pos[..., 1] >= 0).all() and (pos[..., 1] <= env.cfg.area.y_size).all()
    assert (s["data_collected"] <= s["data_total"] + 1e-4).all()


def test_bad_batch_size_is_a_clear_error():
    with pytest.raises(ValueError, match="batch_size"):
        UAVEnv(batch_size=[2, 3])


def test_stepping_a_root_without_its_state_names_the_missing_entries():
    env = UAVEnv(batch_size=[2], seed=0)
    td = env.reset().set("action", torch.zeros(2, 2))
    del td["state", "position"], td["state", "energy_used"]
    with pytest.raises(KeyError, match=r"no \('state', key\) for \['position', 'energy_used'\]"):
        env._step(td)


def test_env_contract_lists_the_state_table():
    """docs/env_contract.md shows the raw state exactly as STATE_TABLE (which the specs use) has it."""
    from pathlib import Path

    from uavlae.envs.world import state_table_markdown

    doc = (Path(__file__).resolve().parents[1] / "docs" / "env_contract.md").read_text()
    assert state_table_markdown() in doc
    env = UAVEnv(batch_size=[2], seed=0)
    assert set(env.observation_spec["state"].keys()) == set(env.raw_state_keys)
    assert env.observation_spec["state", "served_ge"].dtype == torch.int64
    assert env.observation_spec["state", "ge_pos"].shape == (2, env.cfg.ge.count.padded, 2)
