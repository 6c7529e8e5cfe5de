"""The student advisor (advisor.amortize): what it reads, whom it asks, what it learns, and
that its state resumes exactly. The LLM here is a stand-in answering a fixed rule (the real
local model is in tests/test_train.py); the student itself, the override and the env are real."""

from __future__ import annotations

import concurrent.futures
import io
import math

import pytest
import torch
from tensordict.nn import TensorDictModule
from torch import nn

from uavlae.llm import Advice, AdviceFailure, AdvisorState, EndpointError, FailureKind, GroundEquipment, OtherUAV, WorldLimits
from uavlae.policies.override import FALLBACK, LLM, STUDENT, Advisor, LLMAdvisorAdapter, OverridePolicy
from uavlae.policies.student import (
    N_CELLS, N_DCU, N_ENTITY, AmortizedAdvisor, Student, StudentConfig, encode, make_student_config, shown_state,
)

LIM = WorldLimits(x_size=500.0, y_size=500.0, v_max=10.0, v_limit=5.0, perception_radius=20.0,
                  landing=(475.0, 0.0, 500.0, 25.0), e_limit=8e5)


def state(**kw) -> AdvisorState:
    base = dict(position=(100.0, 200.0), velocity=(3.04, -1.96), energy_left=5e5, limits=LIM,
                ges=(GroundEquipment(100.0, 260.0, 2.04),), bz=((110.0, 190.0, 130.0, 230.0),))
    base.update(kw)
    return AdvisorState(**base)


# ---------------------------------------------------------------------------- what it reads


def test_features_are_the_prompts_numbers_worked_by_hand():
    cfg = StudentConfig()
    dcu, ents, cells = encode([state()], cfg)
    # DCU (100, 200) m of 500 x 500, velocity (3.0, -2.0) m/s as the prompt rounds it, of v_max 10;
    # the landing area's centre (487.5, 12.5) is (+387.5, -187.5) m away
    torch.testing.assert_close(dcu[0], torch.tensor([0.2, 0.4, 0.3, -0.2, 0.0, 0.775, -0.375, 0.0]))
    bz, ge = ents[0]
    # the building's nearest point (110, 200): 10 m east; centre (120, 210); half sizes (10, 20)
    torch.testing.assert_close(bz, torch.tensor([1, 0, 0, 0, 0, 1.0, 0.0, 10 / 500, math.exp(-1.0), 0.0,
                                                 20 / 500, 10 / 500, 10 / 500, 20 / 500, 0.0, 0.0, 0.0]))
    # the GE 60 m north with 2.0 data units (the prompt writes one decimal)
    torch.testing.assert_close(ge, torch.tensor([0, 0, 0, 1, 0, 0.0, 1.0, 60 / 500, math.exp(-6.0), 0.0,
                                                 0.0, 60 / 500, 0.0, 0.0, 2.0, 0.0, 0.0]))
    # situation: nearest obstacle the building (kind 0) at bearing 0, the target (the GE) at 90
    # degrees: relative bearing 270 -> sector 6 of 8; 10 m > close_m 5 -> band 2; 3.6 m/s <= 5: slow
    assert cells.tolist() == [((0 * 8 + 6) * 3 + 2) * 2 + 0] and N_CELLS == 240
    assert dcu.shape == (1, N_DCU) and bz.shape == (N_ENTITY,)


def test_the_student_reads_no_more_than_the_prompt_shows():
    """Numbers the compact prompt does not write (energy, the env's distances, an OU beyond the
    perception radius, decimals below its rounding) change nothing it reads."""
    cfg = StudentConfig()
    a = encode([state()], cfg)
    far_ou = OtherUAV(150.0, 200.0, 1.0, 1.0, 50.0)  # 50 m away: the prompt does not list it
    b = encode([state(energy_left=1.0, d_bz=3.0, d_ou=50.0, ous=(far_ou,), position=(100.2, 199.9),
                      velocity=(3.01, -1.99))], cfg)
    assert torch.equal(a[0], b[0]) and all(torch.equal(x, y) for x, y in zip(a[1], b[1])) and torch.equal(a[2], b[2])
    near_ou = OtherUAV(105.0, 200.0, 1.0, 1.0, 5.0)  # a visible one is read
    c = encode([state(ous=(near_ou,))], cfg)
    assert c[1][0].shape[0] == 3 and c[2].item() != a[2].item()
    assert shown_state(state(), "verbose").position == (100.0, 200.0)


def test_config_refuses_a_cap_below_the_warm_up():
    with pytest.raises(ValueError, match="max_llm_rows=10 is below min_answers=64"):
        make_student_config({"max_llm_rows": 10})


# ---------------------------------------------------------------------------- what it learns


def toward_ge(s: AdvisorState) -> tuple[float, float]:
    """The stand-in LLM's rule: 6 m/s toward the nearest GE with data, hover without one."""
    if not s.ges:
        return 0.0, 0.0
    g = min(s.ges, key=lambda g: math.hypot(g.x - s.position[0], g.y - s.position[1]))
    dx, dy = g.x - s.position[0], g.y - s.position[1]
    d = math.hypot(dx, dy) or 1.0
    return 6.0 * dx / d, 6.0 * dy / d


def test_the_student_learns_a_rule_deterministically():
    from uavlae.llm import example_states

    cfg = StudentConfig(hidden=32, batch_size=32, updates_per_answer=2.0, lr=3e-3)
    train, test = example_states(300, LIM, seed=1), example_states(100, LIM, seed=2)
    target = lambda ss: torch.tensor([toward_ge(s) for s in ss]) / LIM.v_max  # noqa: E731
    dcu, ents, cells = encode(train, cfg)
    tdcu, tents, _ = encode(test, cfg)
    a, b = Student(cfg, seed=3), Student(cfg, seed=3)
    before, _ = a.predict(tdcu, tents)
    for st in (a, b):
        st.learn(dcu[:20], ents[:20], cells[:20], target(train[:20]))
    for x, y in zip(a.net.parameters(), b.net.parameters()):
        assert torch.equal(x, y)  # the same answers, the same seed: the same student
    for k in range(20, 300, 20):  # answers arrive a step at a time
        a.learn(dcu[k:k + 20], ents[k:k + 20], cells[k:k + 20], target(train[k:k + 20]))
    assert a.updates == 600 and a.answers == 300 and int(a.cell_counts.sum()) == 300
    err = lambda pred, ss: float((pred - target(ss)).norm(dim=-1).mean()) * LIM.v_max  # noqa: E731
    after, _ = a.predict(tdcu, tents)
    # m/s; answers are 6 m/s: it learned the rule on states it saw, and half of it on new ones
    assert err(a.predict(dcu, ents)[0], train) < 1.5 and err(after, test) < 0.5 * err(before, test)


# ---------------------------------------------------------------------------- whom it asks


class RuleLLM:
    """Stands in for LLMAdvisor: answers toward_ge for every state it is asked (and fails on
    the states ``fail`` picks), records what it was asked; down, it raises the EndpointError
    a real LLM's future raises."""

    def __init__(self, fail=lambda s: False, down=False):
        from uavlae.llm import make_llm_config

        self.cfg = make_llm_config("local", cache_mode="off")
        self.asked: list[AdvisorState] = []
        self.fail, self.down = fail, down

    def submit(self, states):
        future = concurrent.futures.Future()
        if self.down:
            future.set_exception(EndpointError("LLM endpoint http://x/v1/chat/completions left 3 rows in a row "
                                               "unanswered"))
            return future
        self.asked += states
        future.set_result([AdviceFailure(kind=FailureKind.OVER_SPEED, detail="x", attempts=10) if self.fail(s)
                           else Advice(*toward_ge(s), confidence=1.0, reasoning="r") for s in states])
        return future

    class stats:  # noqa: N801  (what LLMAdvisorAdapter.snapshot reads)
        latencies: list = []

        @staticmethod
        def snapshot(reset=False):
            return {"requests": 0}


class Zero(nn.Module):
    def forward(self, obs):
        return torch.zeros(obs.shape[0], 2)


def policy(cfg: dict, fail=lambda s: False, seed=0, B=8):
    from uavlae.envs import UAVEnv

    env = UAVEnv(batch_size=[B], seed=seed)
    llm = RuleLLM(fail)
    adv = AmortizedAdvisor(LLMAdvisorAdapter(llm, env.cfg), make_student_config(cfg), seed=seed)
    actor = TensorDictModule(Zero(), in_keys=["observation"], out_keys=["action"])
    return env, llm, adv, OverridePolicy(actor, adv, mode="always", fallback="policy", seed=seed)


def fly(env, pol, steps):
    """Every row advised every slot; the executed actions fly the env. Returns sources, actions."""
    td = env.reset()
    src, act = [], []
    for _ in range(steps):
        td = pol(td)
        src.append(td["action_source"].clone())
        act.append(td["action"].clone())
        td = env.step_and_maybe_reset(td)[1]
    return torch.stack(src), torch.stack(act)


def test_the_llm_answers_the_warm_up_then_the_student_answers_where_it_is_sure():
    """8 rows a slot; min_answers 16: the LLM answers the first two slots (16 rows), then a
    student that is never unsure (threshold 10) and never audits answers every row alone."""
    env, llm, adv, pol = policy({"min_answers": 16, "unsure": 10.0, "novel_min": 0, "audit_fraction": 0.0})
    src, act = fly(env, pol, 5)
    assert (src[:2] == LLM).all() and (src[2:] == STUDENT).all() and len(llm.asked) == 16
    snap = pol.snapshot()
    assert snap["source/llm"] == 16 and snap["source/student"] == 24 and snap["advised_fraction"] == 1.0
    assert snap["advisor/student/asked_warmup"] == 16 and snap["advisor/student/llm_rows"] == 16
    # the student's actions are velocities inside the disc |v| <= v_max
    assert (act[2:].norm(dim=-1) <= 1.0).all()


def test_audits_unsure_rows_and_novel_situations_go_to_the_llm():
    env, llm, adv, pol = policy({"min_answers": 8, "unsure": 10.0, "novel_min": 0, "audit_fraction": 1.0})
    src, _ = fly(env, pol, 3)
    assert (src == LLM).all() and pol.snapshot()["advisor/student/asked_audit"] == 16  # after the warm-up slot
    env, llm, adv, pol = policy({"min_answers": 8, "unsure": 1e-9, "novel_min": 0, "audit_fraction": 0.0})
    src, _ = fly(env, pol, 3)
    assert (src == LLM).all() and pol.snapshot()["advisor/student/asked_unsure"] == 16  # an ensemble never agrees to 1e-9
    env, llm, adv, pol = policy({"min_answers": 8, "unsure": 10.0, "novel_min": 10**6, "audit_fraction": 0.0})
    src, _ = fly(env, pol, 3)
    assert (src == LLM).all() and pol.snapshot()["advisor/student/asked_novel"] == 16


def test_max_llm_rows_caps_the_llm_and_the_student_answers_the_rest():
    env, llm, adv, pol = policy({"min_answers": 8, "unsure": 1e-9, "max_llm_rows": 12, "audit_fraction": 0.0})
    src, _ = fly(env, pol, 4)
    # slot 1: 8 rows (warm-up); slot 2: the first 4 in batch order; then none
    assert len(llm.asked) == 12 and (src[0] == LLM).all()
    assert src[1].tolist() == [LLM] * 4 + [STUDENT] * 4 and (src[2:] == STUDENT).all()


def test_max_llm_share_spends_a_credit_earned_per_triggered_row_on_the_least_sure_rows():
    """A student never sure (threshold 1e-9), a share of 1/4: after the 8-row warm-up each slot
    of 8 rows earns 2 rows of credit, and the LLM answers exactly the 2 rows whose members
    disagree most."""
    env, llm, adv, pol = policy({"min_answers": 8, "unsure": 1e-9, "novel_min": 0, "audit_fraction": 0.0,
                                 "max_llm_share": 0.25})
    td = env.reset()
    for slot in range(5):
        spread = None
        if slot:
            states = adv.llm.states(td)
            _, spread = adv.student.predict(*encode(states, adv.cfg)[:2])
        td = pol(td)
        src = td["action_source"]
        if slot == 0:
            assert (src == LLM).all()
        else:
            assert (src == LLM).nonzero().squeeze(-1).tolist() == sorted(spread.topk(2).indices.tolist())
        td = env.step_and_maybe_reset(td)[1]
    assert len(llm.asked) == 8 + 4 * 2 and adv.credit == 0.0


def test_share_allowance_is_spent_first_then_the_share_accrues():
    """A share of 1/4 with 4 rows of allowance, a student never sure, 8 rows a slot: after the
    8-row warm-up, slot 2 has 4 + 8/4 = 6 rows of credit, then each slot earns and spends 2.
    With 16 rows a slot, an allowance of 20 above a burst of 16 earns nothing until spent below
    it: slot 2 asks 16 (4 left), slot 3 has 4 + 16/4 = 8, slot 4 has 0 + 4."""
    never_sure = {"min_answers": 8, "unsure": 1e-9, "novel_min": 0, "audit_fraction": 0.0, "max_llm_share": 0.25}
    env, llm, adv, pol = policy({**never_sure, "share_allowance": 4})
    src, _ = fly(env, pol, 4)
    assert (src == LLM).sum(-1).tolist() == [8, 6, 2, 2] and adv.credit == 0.0
    env, llm, adv, pol = policy({**never_sure, "share_allowance": 20, "share_burst": 16}, B=16)
    src, _ = fly(env, pol, 4)
    assert (src == LLM).sum(-1).tolist() == [16, 16, 8, 4] and adv.credit == 0.0


def test_a_failed_llm_row_takes_the_fallback_and_an_outage_stops_the_step():
    env, llm, adv, pol = policy({"min_answers": 8})
    td = env.reset()
    x = td["state", "ge_pos"][:, 0, 0]  # every row starts at the take-off point; their maps differ
    cut = float(x.median())
    llm.fail = lambda s: s.ges[0].x < cut  # the rows whose first GE lies in the west
    failed = x < cut
    src = pol(td)["action_source"]
    assert failed.any() and (~failed).any()
    assert (src[failed] == FALLBACK).all() and (src[~failed] == LLM).all()
    assert len(adv.student) == int((~failed).sum())  # it learns from validated answers only
    llm.down = True
    with pytest.raises(EndpointError, match="unanswered"):
        pol(env.reset())


def test_the_student_resumes_exactly_from_a_checkpoint():
    """Six slots straight, against three, the override's state through torch.save and
    torch.load(weights_only=True) into a new policy, and three more: the same actions, sources
    and LLM questions (the student, its answers, optimiser and generators all travel)."""
    cfg = {"min_answers": 8, "unsure": 0.05, "novel_min": 1, "audit_fraction": 0.2, "updates_per_answer": 2.0}
    env, llm, adv, pol = policy(cfg)
    src, act = fly(env, pol, 6)
    assert (src == STUDENT).any() and (src[1:] == LLM).any()  # both answer, after the warm-up too

    env1, llm1, _, pol1 = policy(cfg)
    td = env1.reset()
    out_src, out_act = [], []
    for _ in range(3):
        td = pol1(td)
        out_src.append(td["action_source"].clone()), out_act.append(td["action"].clone())
        td = env1.step_and_maybe_reset(td)[1]
    buf = io.BytesIO()
    torch.save({"policy": pol1.get_extra_state(), "env": env1.sampler_state(), "td": td.to_dict()}, buf)
    buf.seek(0)
    saved = torch.load(buf, weights_only=True)
    env2, llm2, _, pol2 = policy(cfg)
    env2.load_sampler_state(saved["env"])
    pol2.set_extra_state(saved["policy"])
    td = td.__class__(saved["td"], batch_size=td.batch_size)
    for _ in range(3):
        td = pol2(td)
        out_src.append(td["action_source"].clone()), out_act.append(td["action"].clone())
        td = env2.step_and_maybe_reset(td)[1]
    assert torch.equal(torch.stack(out_src), src) and torch.equal(torch.stack(out_act), act)
    assert len(llm1.asked) + len(llm2.asked) == len(llm.asked)


def test_the_advised_evaluation_leaves_the_student_as_it_was():
    cfg = {"min_answers": 8, "unsure": 0.05, "audit_fraction": 0.2}
    env, llm, adv, pol = policy(cfg)
    fly(env, pol, 2)
    before = {k: v.clone() for k, v in adv.student.net.state_dict().items()}
    n = len(adv.student)
    with pol.advised():
        fly(env, pol, 3)
        assert len(adv.student) > n  # it learned meanwhile
    assert len(adv.student) == n
    assert all(torch.equal(v, adv.student.net.state_dict()[k]) for k, v in before.items())


def test_cost_counts_rows_tokens_and_money_by_hand():
    class Priced(Advisor):
        source = LLM
        asks_llm = True

        def advise(self, td_rows, rows):
            return torch.zeros(rows.numel(), 2), torch.ones(rows.numel(), dtype=torch.bool)

        def snapshot(self, reset=False):
            return {"requests": 3, "calls": 4, "prompt_tokens": 1000, "cached_prompt_tokens": 400,
                    "completion_tokens": 200, "call_s": 2.5}

        def price(self):
            return 0.5, 0.1, 2.0, "USD"

    from uavlae.envs import UAVEnv

    env = UAVEnv(batch_size=[3], seed=0)
    actor = TensorDictModule(Zero(), in_keys=["observation"], out_keys=["action"])
    pol = OverridePolicy(actor, Priced(), mode="always")
    pol(env.reset())
    c = pol.cost()
    assert (c["triggered"], c["rows_llm"], c["rows_student"], c["llm_calls"], c["tokens_in"], c["tokens_out"]) == \
        (3, 3, 0, 4, 1000, 200)
    # (600 computed x 0.5 + 400 cached x 0.1 + 200 out x 2.0) / 1e6
    assert c["money"] == pytest.approx(7.4e-4) and c["llm_s"] == 2.5 and pol.currency() == "USD"
    assert OverridePolicy(actor, None, mode="never").cost() == {}  # no LLM, no cost
