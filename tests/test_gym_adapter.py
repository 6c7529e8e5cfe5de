"""UAVGymEnv: the gymnasium API checker, registration, and step-for-step equality with UAVEnv."""

import gymnasium
import numpy as np
import pytest
import torch
from gymnasium.utils.env_checker import check_env

from uavlae.envs.config import EnvConfig
from uavlae.envs.gym_adapter import GYM_ID, UAVGymEnv
from uavlae.envs.scenario import Scenario
from uavlae.envs.uav_env import UAVEnv

CFG = EnvConfig()
SC = Scenario(
    nfz=[(100.0, 100.0, 160.0, 160.0)], rz=[(300.0, 300.0, 360.0, 380.0)], bz=[(200.0, 50.0, 260.0, 120.0)],
    ge_pos=[(50.0, 400.0), (40.0, 470.0), (420.0, 420.0)], ge_data=[1.5, 2.5, 2.0],
    ou_pos=[(30.0, 440.0), (250.0, 250.0), (400.0, 100.0)], ou_vel=[(1.0, 0.0), (-2.0, 3.0), (0.0, 5.0)],
    start=(12.5, 487.5),
)


# Unbounded observation bounds are deliberate: hand-made scenarios may exceed the sampled ranges.
@pytest.mark.filterwarnings("ignore:.*Box observation space m.*:UserWarning")
@pytest.mark.parametrize("render_mode", [None, "rgb_array"])
def test_check_env(render_mode):
    # through gymnasium.make so that the checker also sees the registered spec
    env = gymnasium.make(GYM_ID, cfg=CFG, render_mode=render_mode).unwrapped
    assert isinstance(env, UAVGymEnv)
    check_env(env, skip_render_check=render_mode is None)


def test_registered_and_spaces():
    env = gymnasium.make(GYM_ID, scenario=SC)
    obs, info = env.reset(seed=0)
    assert env.observation_space.shape == obs.shape and obs.dtype == np.float32
    assert env.action_space.shape == (2,) and env.action_space.low.min() == -1.0
    obs, reward, terminated, truncated, info = env.step(np.zeros(2, np.float32))
    assert isinstance(reward, float) and set(info) >= {"events", "reward_terms", "cost", "state"}
    assert info["state"]["position"].shape == (2,)
    assert sum(info["reward_terms"].values()) == pytest.approx(reward, abs=1e-5)


def _compare(genv, env, obs0, td, actions):
    np.testing.assert_array_equal(obs0, td["observation"][0].numpy())
    for a in actions:
        obs, reward, term, trunc, info = genv.step(a)
        td["action"] = torch.as_tensor(a).reshape(1, 2)
        td = env.step(td)
        nxt = td["next"]
        np.testing.assert_array_equal(obs, nxt["observation"][0].numpy())
        np.testing.assert_array_equal(info["state"]["position"], nxt["state", "position"][0].numpy())
        np.testing.assert_array_equal(info["state"]["ou_pos"], nxt["state", "ou_pos"][0].numpy())
        assert reward == float(nxt["reward"][0, 0])
        assert term == bool(nxt["terminated"][0, 0]) and trunc == bool(nxt["truncated"][0, 0])
        for k, v in info["events"].items():
            assert v == bool(nxt["events", k][0, 0])
        if term or trunc:
            break
        from torchrl.envs.utils import step_mdp

        td = step_mdp(td)
    return td


def _actions(n, seed):
    g = np.random.default_rng(seed)
    return [g.uniform(-1, 1, 2).astype(np.float32) for _ in range(n)]


def test_same_trajectory_as_uavenv_fixed_scenario():
    genv = UAVGymEnv(CFG)
    obs0, _ = genv.reset(seed=7, options={"scenario": SC})
    env = UAVEnv(CFG, batch_size=[1], seed=7, scenarios=[SC])
    # toward the GEs near the start (data collected), then wandering: OUs turn at random
    acts = [np.array([0.3, -0.6], np.float32)] * 6 + _actions(60, 0)
    _compare(genv, env, obs0, env.reset(), acts)


@pytest.mark.parametrize("pool_size", [0, 3])
def test_same_trajectories_as_uavenv_sampled_scenarios(pool_size):
    # seeded once, then episode after episode: the same scenarios (pool included) and OU moves
    cfg = CFG.model_copy(update={"sampling": CFG.sampling.model_copy(update={"pool_size": pool_size})})
    genv = UAVGymEnv(cfg)
    env = UAVEnv(cfg, batch_size=[1], seed=11)
    for episode in range(5):
        obs0, info = genv.reset(seed=11 if episode == 0 else None)
        td = env.reset()
        np.testing.assert_array_equal(info["state"]["ge_pos"], td["state", "ge_pos"][0].numpy())
        _compare(genv, env, obs0, td, _actions(15, episode))


def test_same_seed_same_episode_and_crash_terminates():
    crash = Scenario(bz=[(110.0, 200.0, 150.0, 300.0)], ge_pos=[(250.0, 250.0)], ge_data=[2.0], start=(95.0, 250.0))
    env = UAVGymEnv(CFG, scenario=crash)
    env.reset(seed=0)
    _, _, term, _, info = env.step(np.array([1.0, 0.0], np.float32))
    assert not term
    _, reward, term, _, info = env.step(np.array([1.0, 0.0], np.float32))
    assert term and info["events"]["bz_collision"] and info["cost"] == 1.0
    assert info["reward_terms"]["crash"] == -CFG.reward.crash_penalty
