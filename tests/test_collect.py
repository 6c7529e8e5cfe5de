"""The collector on a real UAVEnv, the episode end on failed advice, resume, the replay buffer;
and one run against the real local LLM server."""

from __future__ import annotations

import io

import pytest
import torch
from tensordict.nn import TensorDictModule
from torch import nn

from uavlae.collect import TRANSITION_KEYS, UAVCollector, make_replay_buffer
from uavlae.envs import UAVEnv
from uavlae.policies.override import FALLBACK, LLM, POLICY, Advisor, OverridePolicy

B = 4


class TanhObs(nn.Module):
    """A deterministic stand-in actor: action = tanh(3 * observation[:2])."""

    def forward(self, obs):
        return torch.tanh(3 * obs[..., :2])


def det_actor():
    return TensorDictModule(TanhObs(), in_keys=["observation"], out_keys=["action"])


class RowAdvisor(Advisor):
    """Always advises (0, 0.5); fails on the rows in ``fail_rows``."""

    source = LLM

    def __init__(self, fail_rows=()):
        self.fail_rows = set(fail_rows)
        self.rows = []

    def advise(self, td_rows, rows):
        self.rows.append(rows.tolist())
        ok = torch.tensor([int(r) not in self.fail_rows for r in rows], dtype=torch.bool)
        return torch.tensor([[0.0, 0.5]]).expand(rows.numel(), 2).clone(), ok


def test_batches_have_the_right_shapes_and_frame_counts():
    env = UAVEnv(batch_size=[B], seed=0)
    col = UAVCollector(env, det_actor(), frames_per_batch=42, total_frames=100)
    assert col.T == 10 and col.frames_per_batch == 40 and len(col) == 3
    batches = list(col)
    assert len(batches) == 3 and col.frames == 120
    b = batches[0]
    assert b.batch_size == torch.Size([B, 10])
    assert b["action"].shape == (B, 10, 2) and b["action_source"].shape == (B, 10)
    assert (b["action_source"] == POLICY).all()
    for key in ["reward", "done", "terminated", "truncated", "cost"]:
        assert b["next", key].shape == (B, 10, 1), key
    assert b["next", "events", "bz_collision"].shape == (B, 10, 1)
    assert b["next", "state", "position"].shape == (B, 10, 2)
    # time runs along dim 1: the slot counter goes up by one per step of a running episode
    steps = b["next", "state", "step"]
    assert torch.equal(steps[:, 1:] - steps[:, :-1], torch.ones(B, 9, dtype=steps.dtype))
    # consecutive: the next observation of step t is the observation of step t + 1
    torch.testing.assert_close(b["next", "observation"][:, :-1], b["observation"][:, 1:])
    torch.testing.assert_close(batches[1]["observation"][:, 0], b["next", "observation"][:, -1])


def test_keep_keys_drops_the_raw_state_and_random_frames():
    env = UAVEnv(batch_size=[B], seed=0)
    col = UAVCollector(env, det_actor(), 20, 40, init_random_frames=20, keep_keys=TRANSITION_KEYS, seed=5)
    first, second = list(col)
    keys = first.keys(True, True)
    assert ("next", "state", "position") not in keys and ("state", "position") not in keys
    assert {"observation", "action", "action_source", ("next", "reward"), ("next", "cost"),
            ("next", "events", "landed")} <= set(keys)
    # warm-up: uniform random actions, not the actor's
    actor_act = torch.tanh(3 * first["observation"][..., :2])
    assert not torch.allclose(first["action"], actor_act)
    torch.testing.assert_close(second["action"], torch.tanh(3 * second["observation"][..., :2]))
    assert first["action"].abs().max() <= 1


def test_override_abort_ends_exactly_that_rows_episode():
    env = UAVEnv(batch_size=[B], seed=0)
    pol = OverridePolicy(det_actor(), RowAdvisor(fail_rows={2}), mode="always", fallback="end_episode")
    col = UAVCollector(env, pol, frames_per_batch=B * 3, total_frames=B * 3)
    (b,) = list(col)
    src = b["action_source"]
    assert (src[2] == FALLBACK).all() and (src[[0, 1, 3]] == LLM).all()
    done, trunc, term = b["next", "done"][..., 0], b["next", "truncated"][..., 0], b["next", "terminated"][..., 0]
    assert done[2].all() and trunc[2].all() and not term[2].any()
    assert not done[[0, 1, 3]].any()
    # row 2 restarts every step; the others keep counting; the stored last slot is not overwritten
    assert b["next", "state", "step"][2].tolist() == [1, 1, 1]
    assert b["next", "state", "step"][0].tolist() == [1, 2, 3]
    assert b["state", "step"][2].tolist() == [0, 0, 0]
    records, agg = col.episode_metrics()
    assert records["row"].tolist() == [2, 2, 2] and records["length"].tolist() == [1, 1, 1]
    assert records["truncated"].all() and agg["n_episodes"] == 3
    assert col.episode_metrics()[1]["n_episodes"] == 0  # cleared by the previous call
    stats = col.override_stats()
    assert stats["aborts"] == 3 and stats["source/llm"] == 9 and stats["frames"] == 12


def _resume_pair():
    def make(env_seed):
        env = UAVEnv(batch_size=[B], seed=env_seed)
        pol = OverridePolicy(det_actor(), RowAdvisor(fail_rows={1}), mode="fixed_prob", fp=0.5,
                             fallback="end_episode", seed=3)
        return UAVCollector(env, pol, frames_per_batch=2 * B, init_random_frames=2 * B, seed=11)

    return make(0), make(123)


def test_state_dict_resumes_exactly():
    a, b = _resume_pair()
    it = iter(a)
    next(it), next(it)
    buf = io.BytesIO()
    torch.save(a.state_dict(), buf)
    buf.seek(0)
    b.load_state_dict(torch.load(buf, weights_only=True))
    assert b.frames == a.frames == 4 * B
    for _ in range(2):
        xa, xb = next(it), b.rollout_batch()
        assert (xa == xb).all(), "resumed collector diverged"
    assert a.override_stats()["triggered"] == b.override_stats()["triggered"]
    ra, rb = a.episode_metrics()[0], b.episode_metrics()[0]
    assert torch.equal(ra["length"], rb["length"]) and torch.equal(ra["row"], rb["row"])


def test_replay_buffer_extend_sample_state_dict():
    env = UAVEnv(batch_size=[B], seed=0)
    col = UAVCollector(env, det_actor(), 40, 40, keep_keys=TRANSITION_KEYS)
    (batch,) = list(col)
    rb = make_replay_buffer(capacity=100, batch_size=16, seed=1)
    rb.extend(batch.reshape(-1))
    assert len(rb) == 40
    s = rb.sample()
    assert s.batch_size == torch.Size([16]) and s["action"].shape == (16, 2)
    assert s["next", "reward"].shape == (16, 1) and s["action_source"].dtype == torch.int64
    sd = rb.state_dict()
    buf = io.BytesIO()
    torch.save(sd, buf)
    buf.seek(0)
    rb2 = make_replay_buffer(capacity=100, batch_size=16, seed=999)
    rb2.load_state_dict(torch.load(buf, weights_only=False))
    assert len(rb2) == 40
    assert (rb2[:40] == rb[:40]).all()
    x1, x2 = rb.sample(), rb2.sample()
    assert torch.equal(x1["index"], x2["index"]), "the sampling generator is restored"
    # capacity wraps around
    rb2.extend(batch.reshape(-1))
    rb2.extend(batch.reshape(-1))
    assert len(rb2) == 100
    with pytest.raises(ValueError, match="storage"):
        make_replay_buffer(10, 2, storage="list")


def test_fast_sample_equals_torchrl_sample():
    """UniformReplayBuffer.sample gathers leaf by leaf; torchrl's TensorDictReplayBuffer.sample
    of the same data with the same generator must give the same TensorDict, bit for bit, before
    and after the storage wraps around, and the fast path must really be the one taken."""
    from torchrl.data import TensorDictReplayBuffer

    from uavlae.collect import UniformReplayBuffer

    env = UAVEnv(batch_size=[B], seed=0)
    col = UAVCollector(env, det_actor(), 40, 80, keep_keys=TRANSITION_KEYS)
    batches = [b.reshape(-1) for b in col]
    fast = make_replay_buffer(capacity=60, batch_size=16, seed=3)
    stock = make_replay_buffer(capacity=60, batch_size=16, seed=3)
    assert isinstance(fast, UniformReplayBuffer)
    for data in batches:  # 40 then 80 transitions: the second extend wraps the 60-slot storage
        fast.extend(data)
        stock.extend(data)
        assert fast._gather_ok()
        for _ in range(5):
            a = fast.sample()
            b = TensorDictReplayBuffer.sample(stock)  # the stock path on the twin buffer
            assert set(a.keys(True, True)) == set(b.keys(True, True))
            for k in b.keys(True, True):
                assert a[k].dtype == b[k].dtype and torch.equal(a[k], b[k]), k
            assert a.batch_size == b.batch_size == torch.Size([16])
            assert int(a["index"].max()) < len(fast)
    # rows really come from the storage: the sampled observation is the stored one at "index"
    s = fast.sample()
    assert torch.equal(s["observation"], fast[s["index"]]["observation"])
    # outside the fast path's conditions (another batch size) the stock sample answers
    with pytest.warns(UserWarning, match="conflicting batch_sizes"):
        assert fast.sample(8).batch_size == torch.Size([8])


# ---------------------------------------------------------------------------- real LLM


@pytest.mark.integration
@pytest.mark.timeout(300)
def test_llm_override_with_the_real_local_server(llm_server, tmp_path):
    from uavlae.envs.scenario import Scenario
    from uavlae.llm import LLMAdvisor, make_llm_config
    from uavlae.policies.override import LLMAdvisorAdapter

    near = Scenario(  # a building 7.5 m south of the start: within d_th = 15 m
        nfz=[(300.0, 300.0, 360.0, 360.0)], rz=[(200.0, 100.0, 260.0, 160.0)],
        bz=[(0.0, 420.0, 60.0, 480.0)], ge_pos=[(100.0, 400.0), (420.0, 300.0)], ge_data=[1.5, 2.0],
        ou_pos=[(250.0, 250.0)], ou_vel=[(1.0, 0.0)], start=(12.5, 487.5),
    )
    far = Scenario(nfz=[], rz=[], bz=[], ge_pos=[(250.0, 250.0)], ge_data=[3.0], ou_pos=[], ou_vel=[],
                   start=(12.5, 487.5))
    env = UAVEnv(batch_size=[2], seed=0, scenarios=[near, far])
    cfg = make_llm_config("local", cache_path=str(tmp_path / "c.sqlite"), max_tokens=96,
                          reasoning_max_chars=40)
    llm = LLMAdvisor(cfg, base_url=llm_server.base_url)
    pol = OverridePolicy(det_actor(), LLMAdvisorAdapter(llm, env.cfg, timeout=240), mode="proximity",
                         d_th=15.0, fallback=None)
    col = UAVCollector(env, pol, frames_per_batch=4, total_frames=4)
    try:
        (b,) = list(col)
    finally:
        col.shutdown()
    d = torch.stack([b["state", k] for k in ("d_bz", "d_nfz", "d_rz", "d_ou")], -1).amin(-1)
    trig = d <= 15.0
    assert trig[0, 0] and not trig[1].any()
    src = b["action_source"]
    assert ((src == LLM) | (src == FALLBACK))[trig].all() and (src[~trig] == POLICY).all()
    assert b["action"].abs().max() <= 1
    # an LLM action is a validated velocity / v_max: inside the disc of radius 1
    assert (b["action"][src == LLM].norm(dim=-1) <= 1 + 1e-5).all()
    stats = col.override_stats()
    assert stats["triggered"] == int(trig.sum()) and stats["advisor/requests"] == int(trig.sum())
    assert stats["advisor/calls"] >= 1
