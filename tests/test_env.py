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


@pytest.mark.parametrize("mode", ["pool", "no_pool", "fixed"])
def test_maybe_reset_row_path_equals_torchrl_generic_path(mode):
    """UAVEnv.maybe_reset (index_put on the done rows) gives exactly what EnvBase.maybe_reset
    (reset of the done rows, then a where per entry) gives, on a hand-made done mask, and leaves
    the transition's "next" entries untouched."""
    from torchrl.envs import EnvBase

    from uavlae.envs.scenario import sample_scenarios

    B = 6

    def make():
        if mode == "fixed":
            source = UAVEnv(batch_size=[1], seed=3)
            return UAVEnv(batch_size=[B], seed=0, scenarios=sample_scenarios(source.cfg, 4, source.rng))
        cfg = {"sampling": {"pool_size": 0}} if mode == "no_pool" else None
        return UAVEnv(cfg, batch_size=[B], seed=0)

    fast, slow = make(), make()
    td_fast, td_slow = fast.reset(), slow.reset()
    action = torch.tensor([[0.3, -0.2]]).expand(B, 2)
    for mask in ([1, 0, 0, 1, 0, 0], [0, 0, 0, 0, 0, 1], [0, 1, 1, 1, 1, 1]):
        done = torch.tensor(mask, dtype=torch.bool).unsqueeze(-1)
        td_fast = fast.step(td_fast.set("action", action.clone()))
        td_slow = slow.step(td_slow.set("action", action.clone()))
        for td in (td_fast, td_slow):  # the hand-made mask in place of the world's own
            td["next", "done"] = done.clone()
        terminal = td_fast["next"].clone()
        root_fast = fast.maybe_reset(fast._step_mdp(td_fast))
        root_slow = EnvBase.maybe_reset(slow, slow._step_mdp(td_slow))
        assert set(root_fast.keys(True, True)) == set(root_slow.keys(True, True))
        for key in root_slow.keys(True, True):
            assert torch.equal(root_fast[key], root_slow[key]), key
        assert (td_fast["next"] == terminal).all()  # the transition keeps its terminal data
        keep = ~done.squeeze(-1)
        assert torch.equal(root_fast["state", "position"][keep], terminal["state", "position"][keep])
        assert (root_fast["state", "step"][~keep] == 0).all() and not root_fast["done"].any()
        td_fast, td_slow = root_fast, root_slow


def test_maybe_reset_of_a_deeper_root_takes_the_generic_path():
    """A root with an entry three levels deep is not the env's flat layout: UAVEnv.maybe_reset
    hands it to EnvBase.maybe_reset, which keeps the entry (zeroed in the reset rows)."""
    env = UAVEnv(batch_size=[4], seed=0)
    td = env.step(env.reset().set("action", torch.zeros(4, 2)))
    td["next", "done"] = torch.tensor([[True], [False], [False], [False]])
    root = env._step_mdp(td)
    root["extra", "deep", "x"] = torch.ones(4, 3)
    out = env.maybe_reset(root)
    assert out["extra", "deep", "x"].sum(-1).tolist() == [0.0, 3.0, 3.0, 3.0]
    assert out["state", "step"].tolist() == [0, 1, 1, 1]


def _same_entries(a, b, path=""):
    """The same keys in the same order, batch sizes, devices, and the very same tensors."""
    assert type(a) is type(b) and list(a.keys()) == list(b.keys()), path
    assert a.batch_size == b.batch_size and a.device == b.device, path
    for k in a.keys():
        x, y = a.get(k), b.get(k)
        if isinstance(x, torch.Tensor):
            assert x is y, f"{path}/{k}"
        else:
            _same_entries(x, y, f"{path}/{k}")


def test_flat_step_mdp_gives_torchrl_s_root():
    """UAVEnv._step_mdp (the root for the next step, without TorchRL's per-entry dispatch) gives
    what TorchRL's generic _StepMDP gives: the same tensors under the same keys, the policy's own
    entries kept (a nested one too, and an extra leaf in "state"), "next", the reward and
    "_reset" dropped; a root it does not handle (a lazy stack) goes to the generic object."""
    from tensordict import LazyStackedTensorDict, TensorDict

    env = UAVEnv(batch_size=[3], seed=0)
    flat = env._step_mdp
    assert flat is env._step_mdp and flat.flat  # built once; the env's key trees are two levels deep
    td = env.reset().set("action", torch.zeros(3, 2)).set("loc", torch.ones(3, 2))
    td["policy"] = TensorDict({"h": torch.zeros(3, 4)}, batch_size=[3])
    td["state", "extra_leaf"] = torch.arange(3.0)
    td["_reset"] = torch.zeros(3, 1, dtype=torch.bool)
    out = env.step(td)
    root = flat(out)
    _same_entries(root, flat.generic(out))
    assert "next" not in root.keys() and "reward" not in root.keys() and "_reset" not in root.keys()
    assert root["state", "position"] is out["next", "state", "position"] and root["loc"] is out["loc"]
    assert root["state", "extra_leaf"] is out["state", "extra_leaf"]
    lazy = LazyStackedTensorDict.lazy_stack([out[:2], out[2:]], 0)
    assert flat._build(lazy) is None and type(flat(lazy)) is LazyStackedTensorDict


def test_stepping_a_root_without_its_state_names_the_missing_entries():
    env = UAVEnv(batch_size=[2], seed=0)
    td = env.reset().set("action", torch.zeros(2, 2))
    del td["state", "position"], td["state", "energy_used"]
    with pytest.raises(KeyError, match=r"no \('state', key\) for \['position', 'energy_used'\]"):
        env._step(td)
