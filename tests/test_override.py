"""The override module: who acts per row, what reaches the advisor, and the fallbacks."""

from __future__ import annotations

import concurrent.futures
import copy
import math
import pickle

import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule
from torch import nn

from uavlae.policies.override import (
    FALLBACK,
    HEURISTIC,
    LLM,
    POLICY,
    Advisor,
    Handle,
    HeuristicAdvisor,
    LLMAdvisorAdapter,
    OverridePolicy,
)

INF = math.inf


def answered(value):
    """A future that holds ``value`` already: what an LLM's ``submit`` returns once it has answered."""
    future = concurrent.futures.Future()
    future.set_result(value)
    return future


class ConstActor(nn.Module):
    """action = (0.25, -0.25) in every row: easy to tell from the advisor's."""

    def forward(self, obs):
        return torch.tensor([0.25, -0.25]).expand(obs.shape[0], 2).clone()


def const_actor():
    return TensorDictModule(ConstActor(), in_keys=["observation"], out_keys=["action"])


class RecordingAdvisor(Advisor):
    """Records what it was given; answers action = (row / 10, 0.5), ok where ``fail`` says not."""

    source = LLM

    def __init__(self, fail_rows=()):
        self.fail_rows = set(fail_rows)
        self.calls = []

    def advise(self, td_rows, rows):
        self.calls.append((rows.clone(), td_rows.clone()))
        actions = torch.stack([rows.float() / 10, torch.full((rows.numel(),), 0.5)], dim=-1)
        ok = torch.tensor([int(r) not in self.fail_rows for r in rows], dtype=torch.bool)
        return actions, ok


class FakeHeuristic:
    """Stands in for HeuristicPolicy.act: action = (-0.9, 0.9), records the rows' positions."""

    def __init__(self):
        self.seen = []

    def act(self, state):
        self.seen.append(state["position"].clone())
        return torch.tensor([-0.9, 0.9]).expand(state["position"].shape[0], 2).clone()


def batch(d_bz, d_nfz, d_rz, d_ou):
    """A hand-made [B] root tensordict: observation and the env's distances (+ a row tag)."""
    B = len(d_bz)
    state = {k: torch.tensor(v, dtype=torch.float32) for k, v in
             dict(d_bz=d_bz, d_nfz=d_nfz, d_rz=d_rz, d_ou=d_ou).items()}
    state["position"] = torch.arange(B, dtype=torch.float32).unsqueeze(-1).expand(B, 2).clone()
    return TensorDict({"observation": torch.zeros(B, 3), "state": TensorDict(state, [B])}, [B])


# rows 1 (BZ at 3 m), 3 (OU exactly at d_th) and 4 (inside an RZ: 0 m) are within 15 m
D = dict(
    d_bz=[INF, 3.0, 40.0, 20.0, INF, 15.5],
    d_nfz=[100.0, 60.0, INF, INF, INF, INF],
    d_rz=[INF, 50.0, 30.0, 16.0, 0.0, INF],
    d_ou=[INF, INF, 22.0, 15.0, INF, 100.0],
)
TRIGGERED = [1, 3, 4]


def test_only_triggered_rows_reach_the_advisor_and_actions_merge():
    adv = RecordingAdvisor()
    pol = OverridePolicy(const_actor(), adv, mode="proximity", d_th=15.0)
    out = pol(batch(**D))
    (rows, td_rows), = adv.calls
    assert rows.tolist() == TRIGGERED
    # the advisor saw exactly those rows' data (positions tag the rows)
    assert td_rows.batch_size == torch.Size([3])
    assert td_rows["state", "position"][:, 0].tolist() == [1.0, 3.0, 4.0]
    assert td_rows["state", "d_bz"].tolist() == [3.0, 20.0, INF]
    expect = torch.tensor([[0.25, -0.25]] * 6)
    for r in TRIGGERED:
        expect[r] = torch.tensor([r / 10, 0.5])
    torch.testing.assert_close(out["action"], expect)
    assert out["action_source"].dtype == torch.int64
    assert out["action_source"].tolist() == [POLICY, LLM, POLICY, LLM, LLM, POLICY]
    assert not out["override_abort"].any()


def test_no_triggered_row_means_no_call():
    adv = RecordingAdvisor()
    pol = OverridePolicy(const_actor(), adv, mode="proximity", d_th=15.0)
    far = [16.0, INF, 30.0, 100.0, INF, 15.01]
    out = pol(batch(far, far, far, far))
    assert adv.calls == [] and out["action_source"].tolist() == [POLICY] * 6


@pytest.mark.parametrize("mode,expected", [("always", list(range(6))), ("never", [])])
def test_always_and_never(mode, expected):
    adv = RecordingAdvisor()
    out = OverridePolicy(const_actor(), adv, mode=mode)(batch(**D))
    assert (adv.calls[0][0].tolist() if adv.calls else []) == expected
    assert (out["action_source"] == LLM).nonzero().squeeze(-1).tolist() == expected


def test_fixed_prob_rate_is_fp_and_seeded():
    n, fp = 20_000, 0.3
    far = [INF] * n
    td = batch(far, far, far, far)
    trig = OverridePolicy(const_actor(), RecordingAdvisor(), mode="fixed_prob", fp=fp, seed=7).trigger(td)
    rate = trig.float().mean().item()
    assert abs(rate - fp) < 4 * math.sqrt(fp * (1 - fp) / n)  # ~0.013
    again = OverridePolicy(const_actor(), RecordingAdvisor(), mode="fixed_prob", fp=fp, seed=7).trigger(td)
    other = OverridePolicy(const_actor(), RecordingAdvisor(), mode="fixed_prob", fp=fp, seed=8).trigger(td)
    assert torch.equal(trig, again) and not torch.equal(trig, other)
    # whatever the surroundings: the trigger ignores the distances
    adv = RecordingAdvisor()
    out = OverridePolicy(const_actor(), adv, mode="fixed_prob", fp=fp, seed=7)(td)
    assert torch.equal(out["action_source"] == LLM, trig)
    assert adv.calls[0][0].tolist() == trig.nonzero().squeeze(-1).tolist()


def test_fallback_policy_keeps_the_actor_action():
    adv = RecordingAdvisor(fail_rows={3})
    out = OverridePolicy(const_actor(), adv, mode="proximity", fallback="policy")(batch(**D))
    assert out["action_source"].tolist() == [POLICY, LLM, POLICY, FALLBACK, LLM, POLICY]
    torch.testing.assert_close(out["action"][3], torch.tensor([0.25, -0.25]))
    torch.testing.assert_close(out["action"][1], torch.tensor([0.1, 0.5]))
    assert not out["override_abort"].any()


def test_fallback_heuristic_acts_on_the_failed_rows_only():
    h = FakeHeuristic()
    adv = RecordingAdvisor(fail_rows={1, 4})
    out = OverridePolicy(const_actor(), adv, fallback="heuristic", heuristic=h)(batch(**D))
    assert out["action_source"].tolist() == [POLICY, FALLBACK, POLICY, LLM, FALLBACK, POLICY]
    (pos,) = h.seen
    assert pos[:, 0].tolist() == [1.0, 4.0]
    torch.testing.assert_close(out["action"][[1, 4]], torch.tensor([[-0.9, 0.9], [-0.9, 0.9]]))
    torch.testing.assert_close(out["action"][3], torch.tensor([0.3, 0.5]))
    with pytest.raises(ValueError, match="heuristic"):
        OverridePolicy(const_actor(), adv, fallback="heuristic")


def test_fallback_end_episode_flags_the_row():
    adv = RecordingAdvisor(fail_rows={4})
    pol = OverridePolicy(const_actor(), adv, fallback="end_episode")
    out = pol(batch(**D))
    assert out["override_abort"].tolist() == [False, False, False, False, True, False]
    assert out["action_source"][4] == FALLBACK
    torch.testing.assert_close(out["action"][4], torch.tensor([0.25, -0.25]))
    snap = pol.snapshot()
    assert snap["aborts"] == 1 and snap["source/fallback"] == 1 and snap["triggered"] == 3


def test_fallback_none_takes_the_advisors_setting():
    adv = RecordingAdvisor()
    adv.fallback = "end_episode"
    assert OverridePolicy(const_actor(), adv, fallback=None).fallback == "end_episode"
    assert OverridePolicy(const_actor(), RecordingAdvisor(), fallback=None).fallback == "policy"
    with pytest.raises(ValueError, match="fallback"):
        OverridePolicy(const_actor(), adv, fallback="nope")
    with pytest.raises(ValueError, match="mode"):
        OverridePolicy(const_actor(), adv, mode="sometimes")


def test_actor_only_in_evaluation():
    adv = RecordingAdvisor()
    pol = OverridePolicy(const_actor(), adv, mode="always")
    with pol.actor_only():
        out = pol(batch(**D))
    assert adv.calls == [] and out["action_source"].tolist() == [POLICY] * 6
    assert pol.snapshot()["frames"] == 0  # evaluation frames are not counted
    pol.deterministic = True
    pol(batch(**D))
    assert adv.calls == []


def test_deterministic_actor_is_the_mean():
    from uavlae.envs import UAVEnv
    from uavlae.policies.networks import make_sac_actor

    env = UAVEnv(batch_size=[3], seed=0)
    torch.manual_seed(0)
    pol = OverridePolicy(make_sac_actor(env.layout.size, env.action_spec), RecordingAdvisor(), mode="always")
    td = env.reset()
    pol.deterministic = True
    a1 = pol(td.clone())["action"]
    a2 = pol(td.clone())["action"]
    torch.testing.assert_close(a1, a2)
    torch.testing.assert_close(a1, torch.tanh(pol(td.clone())["loc"]))


def test_counters_and_rates():
    adv = RecordingAdvisor(fail_rows={3})
    pol = OverridePolicy(const_actor(), adv)
    pol(batch(**D))
    pol(batch(**D))
    s = pol.snapshot(reset=True)
    assert s["frames"] == 12 and s["triggered"] == 6
    assert s["source/policy"] == 6 and s["source/llm"] == 4 and s["source/fallback"] == 2
    assert s["trigger_rate"] == 0.5 and s["override_rate"] == pytest.approx(4 / 12)
    assert s["advice_fail_rate"] == pytest.approx(2 / 6)
    assert pol.snapshot()["frames"] == 0


def test_extra_state_round_trip_and_no_deepcopy():
    pol = OverridePolicy(const_actor(), RecordingAdvisor(), mode="fixed_prob", fp=0.5, seed=3)
    far = [INF] * 64
    pol(batch(far, far, far, far))
    sd = pol.state_dict()
    nxt = pol.trigger(batch(far, far, far, far))
    other = OverridePolicy(const_actor(), RecordingAdvisor(), mode="fixed_prob", fp=0.5, seed=99)
    other.load_state_dict(sd)
    assert torch.equal(other.trigger(batch(far, far, far, far)), nxt)
    assert other.counts == pol.counts
    with pytest.raises(TypeError, match="actor"):
        copy.deepcopy(pol)
    copy.deepcopy(pol.actor)  # a target network copies the actor, which is fine


class FakeLLM:
    """Mimics LLMAdvisor.submit (what LLMAdvisorAdapter asks of its LLM): answers per state, in order."""

    def __init__(self, answers):
        from uavlae.llm import make_llm_config

        self.cfg = make_llm_config("local", cache_mode="off")
        self.answers = answers
        self.got = []

    def submit(self, states):
        self.got.append(states)
        return answered(self.answers[: len(states)])


def _env_rows():
    from uavlae.envs import UAVEnv

    env = UAVEnv(batch_size=[3], seed=1)
    return env, env.reset()


def test_llm_adapter_converts_velocity_and_failures():
    from uavlae.llm import Advice, AdviceFailure, FailureKind

    env, td = _env_rows()
    fake = FakeLLM([Advice(vx=5.0, vy=-10.0, confidence=0.9, reasoning="r"),
                    AdviceFailure(kind=FailureKind.OVER_SPEED, detail="x", attempts=10)])
    ad = LLMAdvisorAdapter(fake, env.cfg)
    actions, ok = ad.advise(td[torch.tensor([0, 2])], torch.tensor([0, 2]))
    v_max = env.cfg.motion.v_max
    torch.testing.assert_close(actions[0], torch.tensor([5.0 / v_max, -10.0 / v_max]))
    assert ok.tolist() == [True, False]
    (states,) = fake.got  # both rows in one call: sent concurrently by the advisor
    pos = td["state", "position"]
    assert [s.position for s in states] == [tuple(pos[0].tolist()), tuple(pos[2].tolist())]
    assert states[0].limits.v_max == v_max
    assert ad.fallback is None  # one fallback setting: the override's (advisor.fallback)


def test_pickled_policy_carries_no_http_client(tmp_path):
    from uavlae.llm import LLMAdvisor, make_llm_config

    env, td = _env_rows()
    llm = LLMAdvisor(make_llm_config("local", cache_mode="off"), base_url="http://127.0.0.1:9/v1")
    pol = OverridePolicy(const_actor(), LLMAdvisorAdapter(llm, env.cfg), fallback=None)
    llm._client = object()  # as if a client were open
    blob = pickle.dumps(pol)
    back = pickle.loads(blob)
    assert back.advisor.llm._client is None and back.fallback == "policy"  # the override's own default
    assert back.advisor.llm.base_url_or_none == "http://127.0.0.1:9/v1"
    llm._client = None
    llm.close()


def test_heuristic_advisor_on_env_rows():
    from uavlae.policies.heuristic import HeuristicPolicy

    env, td = _env_rows()
    h = HeuristicPolicy(env.cfg)
    adv = HeuristicAdvisor(h)
    out = OverridePolicy(const_actor(), adv, mode="always")(td.clone())
    assert out["action_source"].tolist() == [HEURISTIC] * 3
    torch.testing.assert_close(out["action"], h.act(td["state"]))
    assert out["action"].abs().max() <= 1


# ---------------------------------------------------------------------------- fewer calls


class CountingAdvisor(Advisor):
    """Answers action = (k / 10, row / 10) on its k-th call (k = 1, 2, ...): a held answer is
    told from a fresh one by its first column. ``fail_rows`` fail on every call."""

    source = LLM

    def __init__(self, fail_rows=()):
        self.fail_rows = set(fail_rows)
        self.rows = []

    def advise(self, td_rows, rows):
        self.rows.append(rows.tolist())
        k = len(self.rows)
        actions = torch.stack([torch.full((rows.numel(),), k / 10), rows.float() / 10], dim=-1)
        return actions, torch.tensor([int(r) not in self.fail_rows for r in rows], dtype=torch.bool)


def stepped(d, step):
    """``batch(**d)`` with the episode's slot ``("state", "step")`` of every row."""
    td = batch(**d)
    td["state", "step"] = torch.as_tensor(step, dtype=torch.int64)
    return td


NEAR, FAR = 3.0, INF


def rows_d(near):
    """Four rows, row i triggered (a BZ at 3 m) where ``near[i]``."""
    d = [NEAR if n else FAR for n in near]
    return dict(d_bz=d, d_nfz=[FAR] * 4, d_rz=[FAR] * 4, d_ou=[FAR] * 4)


def test_hold_steps_executes_an_answer_k_slots_while_the_row_stays_triggered():
    adv = CountingAdvisor(fail_rows={3})
    pol = OverridePolicy(const_actor(), adv, hold_steps=3)
    # row 0: triggered throughout; row 1: leaves the trigger at slot 2; row 2: a new episode at
    # slot 2 (its step goes back to 0); row 3: its answers fail, so it asks every slot
    plan = [
        ([1, 1, 1, 1], [0, 0, 0, 0]),
        ([1, 1, 1, 1], [1, 1, 1, 1]),
        ([1, 0, 1, 1], [2, 2, 0, 2]),
        ([1, 1, 1, 1], [3, 3, 1, 3]),
        ([1, 1, 1, 1], [4, 4, 2, 4]),
    ]
    actions, sources = [], []
    for near, step in plan:
        out = pol(stepped(rows_d(near), step))
        actions.append(out["action"][:, 0].tolist())
        sources.append(out["action_source"].tolist())
    # who was asked at each call: slot 0 all; slot 1 the failed row; slot 2 the new episode and the
    # failed row; slot 3 row 0 (its 3 slots are used), row 1 (back in the trigger) and row 3
    assert adv.rows == [[0, 1, 2, 3], [3], [2, 3], [0, 1, 3], [3]]
    # column 0 = the call that answered: row 0 runs call 1 for 3 slots, then call 4 (the 4th call)
    assert [a[0] for a in actions] == pytest.approx([0.1, 0.1, 0.1, 0.4, 0.4])
    assert [a[1] for a in actions] == pytest.approx([0.1, 0.1, 0.25, 0.4, 0.4])  # slot 2: the actor's 0.25
    assert [a[2] for a in actions] == pytest.approx([0.1, 0.1, 0.3, 0.3, 0.3])
    assert [s[3] for s in sources] == [FALLBACK] * 5
    assert [s[1] for s in sources] == [LLM, LLM, POLICY, LLM, LLM]
    s = pol.snapshot()
    # 19 triggered rows: 11 asked (4 + 1 + 2 + 3 + 1), the other 8 executed a held answer
    assert s["triggered"] == 19 and s["advised"] == 11 and s["held"] == 8
    assert s["source/llm"] == 14 and s["source/fallback"] == 5 and s["hold_steps"] == 3


def test_hold_steps_one_asks_every_slot():
    adv = CountingAdvisor()
    pol = OverridePolicy(const_actor(), adv)
    for step in range(3):
        pol(stepped(rows_d([1, 1, 0, 0]), [step] * 4))
    assert adv.rows == [[0, 1]] * 3 and pol.snapshot()["held"] == 0


def test_max_calls_is_a_budget_of_rows_then_the_actor_acts():
    adv = CountingAdvisor()
    pol = OverridePolicy(const_actor(), adv, max_calls=5)
    outs = [pol(stepped(rows_d([1, 1, 1, 1]), [t] * 4)) for t in range(3)]
    assert adv.rows == [[0, 1, 2, 3], [0]]  # the 5th row is the first triggered one in batch order
    assert outs[1]["action_source"].tolist() == [LLM, POLICY, POLICY, POLICY]
    assert outs[1]["action"][1].tolist() == [0.25, -0.25]  # the actor's action
    assert outs[2]["action_source"].tolist() == [POLICY] * 4
    s = pol.snapshot()
    assert s["advised"] == 5 and s["calls_used"] == 5 and s["max_calls"] == 5
    assert s["budget_skipped"] == 7 and s["triggered"] == 12
    # zero: never asked
    adv0 = CountingAdvisor()
    assert OverridePolicy(const_actor(), adv0, max_calls=0)(stepped(rows_d([1] * 4), [0] * 4))["action_source"].tolist() == [POLICY] * 4
    assert adv0.rows == []


def test_held_answers_and_the_budget_survive_a_checkpoint():
    def make():
        return OverridePolicy(const_actor(), CountingAdvisor(), hold_steps=3, max_calls=6)

    a = make()
    a(stepped(rows_d([1, 1, 0, 0]), [0] * 4))
    sd = a.state_dict()
    b = make()
    b.load_state_dict(sd)
    # slot 1: rows 0 and 1 run their held answers (no call), rows 2 and 3 ask (4 of 6 rows used)
    outs = [p(stepped(rows_d([1, 1, 1, 1]), [1] * 4)) for p in (a, b)]
    torch.testing.assert_close(outs[0]["action"][:2], outs[1]["action"][:2])
    assert b.advisor.rows == [[2, 3]] and b.calls_used == 4
    assert b.snapshot()["held"] == 2 and b.run_totals()["triggered"] == 6


def test_bad_hold_and_budget_settings_are_errors():
    with pytest.raises(ValueError, match="hold_steps"):
        OverridePolicy(const_actor(), CountingAdvisor(), hold_steps=0)
    with pytest.raises(ValueError, match="max_calls"):
        OverridePolicy(const_actor(), CountingAdvisor(), max_calls=-1)


class DelayedAdvisor(CountingAdvisor):
    """``start`` returns a handle at once; its answer is only computed when asked for."""

    def __init__(self):
        super().__init__()
        self.started = []

    def start(self, td_rows, rows):
        self.started.append(rows.tolist())
        parent = self

        class Later(Handle):
            def result(self):
                return parent.advise(td_rows, rows)

        return Later()


def test_begin_sends_the_advice_and_the_actor_acts_in_finish():
    adv = DelayedAdvisor()
    actor = const_actor()
    pol = OverridePolicy(actor, adv)
    td = stepped(rows_d([1, 0, 0, 1]), [0] * 4)
    pending = pol.begin(td)
    assert adv.started == [[0, 3]] and adv.rows == [] and pending.rows.tolist() == [0, 3]
    # what runs between the halves (the learner's updates) reaches the actor that acts
    actor.module.forward = lambda obs: torch.full((obs.shape[0], 2), -0.5)
    out = pol.finish(td, pending)
    assert adv.rows == [[0, 3]]
    assert out["action"][:, 0].tolist() == pytest.approx([0.1, -0.5, -0.5, 0.1])
    assert out["action_source"].tolist() == [LLM, POLICY, POLICY, LLM]


def test_ous_beyond_the_perception_radius_do_not_trigger():
    """With d_th above the perception radius, an OU at 22 m (unseen) triggers nothing, one at
    18 m (seen) does; buildings still trigger at any distance up to d_th."""
    d = dict(d_bz=[INF, INF, 24.0], d_nfz=[INF] * 3, d_rz=[INF] * 3, d_ou=[22.0, 18.0, INF])
    blind = OverridePolicy(const_actor(), RecordingAdvisor(), mode="proximity", d_th=25.0)
    seeing = OverridePolicy(const_actor(), RecordingAdvisor(), mode="proximity", d_th=25.0,
                            perception_radius=20.0)
    assert blind.trigger(batch(**d)).tolist() == [True, True, True]
    assert seeing.trigger(batch(**d)).tolist() == [False, True, True]


def test_a_rejected_key_stops_the_policy_with_one_message(monkeypatch):
    import httpx

    from uavlae.llm import EndpointError, LLMAdvisor, make_llm_config

    monkeypatch.setenv("UAVLAE_TEST_KEY", "sk-never-shown")
    env, td = _env_rows()
    sent = []

    def refuse(request):
        sent.append(request)
        return httpx.Response(401, text="invalid api key")

    llm = LLMAdvisor(make_llm_config("openai_compatible", base_url="http://10.0.0.1:8000/v1", cache_mode="off",
                                     api_key_env="UAVLAE_TEST_KEY", max_concurrency=4),
                     transport=httpx.MockTransport(refuse))
    pol = OverridePolicy(const_actor(), LLMAdvisorAdapter(llm, env.cfg), mode="always", fallback="policy")
    with pytest.raises(EndpointError, match=r"http://10\.0\.0\.1:8000/v1.*UAVLAE_TEST_KEY") as info:
        pol(td)
    assert "sk-never-shown" not in str(info.value) and len(sent) <= 4
    llm.close()


# ---------------------------------------------------------------------------- the advisor contract


class AdviseOnly(Advisor):
    """An advisor that writes ``advise`` alone: every other hook is the contract's default."""

    def advise(self, td_rows, rows):
        return torch.full((rows.numel(), 2), 0.5), torch.ones(rows.numel(), dtype=torch.bool)


def test_the_contracts_defaults_fly_checkpoint_and_cost_nothing():
    adv = AdviseOnly()
    pol = OverridePolicy(const_actor(), adv, mode="always", fallback=None)
    assert pol.fallback == "policy"
    pending = pol.begin(batch(**D))
    assert pending.done_at is not None and list(pending.handle.failures) == []  # answered when asked
    out = pol.finish(batch(**D), pending)
    assert out["action_source"].tolist() == [LLM] * 6  # the default source
    assert not any(k.startswith("advisor/") for k in pol.snapshot())  # no counters of its own
    assert "advisor/latency_p50_s" not in pol.run_totals()  # it times no calls
    assert pol.cost() == {} and pol.currency() is None  # it asks no LLM
    state = pol.get_extra_state()
    assert state["advisor"] is None
    pol.set_extra_state(state)
    pol.close()


def test_an_object_outside_the_contract_is_refused():
    class Duck:
        def advise(self, td_rows, rows):
            return torch.zeros(rows.numel(), 2), torch.ones(rows.numel(), dtype=torch.bool)

    with pytest.raises(TypeError, match="uavlae.policies.advisor.Advisor"):
        OverridePolicy(const_actor(), Duck())


def test_no_module_of_policies_probes_an_advisor_or_its_llm():
    """The override calls the contract's hooks directly: no getattr or hasattr aimed at an
    advisor, its handle or its LLM anywhere in uavlae/policies/."""
    import ast
    from pathlib import Path

    import uavlae.policies

    found = []
    for f in sorted(Path(uavlae.policies.__file__).parent.glob("*.py")):
        for node in ast.walk(ast.parse(f.read_text())):
            if isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and node.func.id in ("getattr", "hasattr"):
                target = ast.unparse(node.args[0]).lower()
                if any(w in target for w in ("advisor", "llm", "handle", "adv")):
                    found.append(f"{f.name}:{node.lineno} {ast.unparse(node)}")
    assert found == []
