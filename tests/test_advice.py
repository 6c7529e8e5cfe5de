"""Advice the actor can learn from, and what the override's dependence counters measure.

- The greedy advisor keeps its memory per env row: under the proximity trigger and under a
  random row mask, every triggered row's answer is the action of a ``GreedyPolicy`` flown on the
  whole batch every slot (the triggered set changes from slot to slot; acting on the triggered
  rows alone, as before, gives other actions, which the test shows too).
- The cloning term (``algo.clone_weight``): its value by hand, its gradient in the fused path
  against autograd, finite at |a| = 1, zero without advised rows, its decay.
- The phase-out, the scripted advisors, the agreement counters and the advised evaluation.
"""

from __future__ import annotations

import math

import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule
from torch import nn
from torchrl.data import Bounded

from uavlae.algos.sac import clone_loss, make_sac
from uavlae.envs import UAVEnv
from uavlae.policies.greedy import GreedyPolicy
from uavlae.policies.override import (
    ADVICE_SOURCES,
    FALLBACK,
    HEURISTIC,
    LLM,
    POLICY,
    SCRIPTED,
    STUDENT,
    Advisor,
    HeuristicAdvisor,
    OverridePolicy,
    ScriptedAdvisor,
)

from tests.test_sac_fused import random_batch


class DriftActor(nn.Module):
    """South-east at 0.6 v_max with a seeded wobble: rows cross zones, so the trigger set changes."""

    def __init__(self, seed: int):
        super().__init__()
        self.g = torch.Generator().manual_seed(seed)

    def forward(self, obs):
        wobble = torch.rand(obs.shape[0], 2, generator=self.g) * 1.2 - 0.6
        return (torch.tensor([0.6, -0.6]) + wobble).clamp(-1, 1)


def _fly(mode: str, observe: bool, steps: int = 120) -> tuple[int, int]:
    """Fly the override with a greedy advisor beside a reference greedy policy stepped on the
    whole batch every slot; returns (triggered rows compared, rows whose action differed)."""
    env = UAVEnv(batch_size=[12], seed=5)
    reference = GreedyPolicy(env.cfg)
    advisor = HeuristicAdvisor(GreedyPolicy(env.cfg))
    if not observe:
        advisor.observe = lambda td: None  # the contract's default: it sees only the rows asked this slot
    actor = TensorDictModule(DriftActor(1), in_keys=["observation"], out_keys=["action"])
    policy = OverridePolicy(actor, advisor, mode=mode, d_th=15.0, fp=0.3, seed=2,
                            perception_radius=env.cfg.safety.perception_radius)
    td = env.reset()
    compared = differed = 0
    for _ in range(steps):
        ref = reference.act(td.get("state"))
        td = policy(td)
        trig = td.get("action_source") == HEURISTIC
        compared += int(trig.sum())
        differed += int((td.get("action")[trig] - ref[trig]).abs().amax(-1).gt(1e-6).sum())
        _, td = env.step_and_maybe_reset(td)
    return compared, differed


@pytest.mark.parametrize("mode", ["proximity", "fixed_prob"])
def test_greedy_advisor_answers_as_if_flying_every_row_every_slot(mode):
    compared, differed = _fly(mode, observe=True)
    assert compared > 100  # the trigger fired on many rows, over a changing set
    assert differed == 0
    # acting on the triggered rows alone forgets each row's memory whenever the set changes
    _, differed_old = _fly(mode, observe=False)
    assert differed_old > 0


def test_always_on_trigger_proves_nothing_about_memory():
    """With every row sent every slot both ways agree: why the test above masks rows."""
    env = UAVEnv(batch_size=[6], seed=5)
    ref, adv = GreedyPolicy(env.cfg), HeuristicAdvisor(GreedyPolicy(env.cfg))
    adv.observe = lambda td: None  # the contract's default: no memory followed
    actor = TensorDictModule(DriftActor(1), in_keys=["observation"], out_keys=["action"])
    policy = OverridePolicy(actor, adv, mode="always")
    td = env.reset()
    for _ in range(30):
        r = ref.act(td.get("state"))
        td = policy(td)
        torch.testing.assert_close(td.get("action"), r)
        _, td = env.step_and_maybe_reset(td)


# ---------------------------------------------------------------------------- the cloning term


def _advised_batch(n: int, obs_dim: int, seed: int) -> TensorDict:
    b = random_batch(n, obs_dim, seed=seed)
    g = torch.Generator().manual_seed(seed + 1)
    b["action_source"] = torch.randint(0, 6, (n,), generator=g)
    b["action"][:6] = torch.tensor([[1.0, -1.0], [-1.0, 1.0], [1.0, 1.0], [1.0, 0.0], [-1.0, -1.0], [0.0, 1.0]])
    b["action_source"][:6] = torch.tensor([HEURISTIC, LLM, STUDENT, SCRIPTED, FALLBACK, POLICY])
    return b


def test_clone_sources_are_the_advisors_own_answers():
    assert set(ADVICE_SOURCES) == {LLM, HEURISTIC, STUDENT, SCRIPTED}
    assert POLICY not in ADVICE_SOURCES and FALLBACK not in ADVICE_SOURCES


def test_clone_loss_by_hand():
    """The actor's output weights zeroed and its loc bias set to (atanh 0.5, 0): the
    deterministic action is (0.5, 0) in every row. Rows: (1, -1) heuristic, (0, 0) the actor's,
    (0.5, 0.5) LLM, (-1, 1) fallback. Only rows 0 and 2 count: w / 4 * ((0.5 - 1)^2 + (0 + 1)^2
    + 0 + (0 - 0.5)^2) = w * 1.5 / 4, so 0.75 at w = 2."""
    sac = make_sac({"clone_weight": 2.0, "clone_scale": "none"}, 3, Bounded(-1.0, 1.0, shape=(2,)))
    w_out, b_out = sac._fused.actor_layers[-1]
    with torch.no_grad():
        w_out.zero_()
        b_out[:2] = torch.tensor([math.atanh(0.5), 0.0])
    obs = torch.randn(4, 3)
    action = torch.tensor([[1.0, -1.0], [0.0, 0.0], [0.5, 0.5], [-1.0, 1.0]])
    source = torch.tensor([HEURISTIC, POLICY, LLM, FALLBACK])
    mask = torch.isin(source, torch.tensor(ADVICE_SOURCES))
    with torch.no_grad():
        assert float(clone_loss(sac.actor, obs, action, mask, 2.0)) == pytest.approx(0.75, rel=1e-6)
    batch = random_batch(4, 3, seed=0)
    batch["observation"], batch["action"], batch["action_source"] = obs, action, source
    torch.manual_seed(0)
    out, grads = sac._fused.grads(batch, 2.0, sac._clone_mask(batch), False)
    assert float(out["loss_clone"]) == pytest.approx(0.75, rel=1e-6)
    # d/dloc: 2 w / N (det - a)(1 - det^2) summed over rows 0 and 2, on top of SAC's own gradient
    torch.manual_seed(0)
    _, plain = sac._fused.grads(batch)
    extra = grads[5][:2] - plain[5][:2]  # the output bias rows of loc
    by_hand = 2 * 2.0 / 4 * torch.tensor([(0.5 - 1.0) * 0.75 + 0.0, (0.0 + 1.0) * 1.0 + (0.0 - 0.5) * 1.0])
    torch.testing.assert_close(extra, by_hand, rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("scale", ["actor_loss", "none"])
def test_clone_gradient_fused_matches_autograd(scale):
    from tests.test_sac_fused import perturb_targets

    torch.manual_seed(0)
    sac = make_sac({"clone_weight": 0.7, "clone_scale": scale}, 9, Bounded(-1.0, 1.0, shape=(2,)))
    perturb_targets(sac)
    batch = _advised_batch(64, 9, seed=3)
    mask = sac._clone_mask(batch)
    assert int(mask.sum()) > 6
    params = sac._fused.params
    for p in params:
        p.grad = None
    torch.manual_seed(5)
    out = sac.loss(batch.select(*sac.loss.in_keys).clone())
    w = 0.7 * (max(abs(float(out["loss_actor"].detach())), 1.0) if scale == "actor_loss" else 1.0)
    cl = clone_loss(sac.actor, batch["observation"], batch["action"], mask, w)
    (out["loss_actor"] + out["loss_qvalue"] + out["loss_alpha"] + cl).backward()
    ref = [p.grad.clone() for p in params]
    torch.manual_seed(5)
    logs, grads = sac._fused.grads(batch, 0.7, mask, scale == "actor_loss")
    cl = float(cl.detach())
    assert float(logs["loss_clone"]) == pytest.approx(cl, rel=1e-5)
    assert cl > 0 and all(torch.isfinite(g).all() for g in grads)
    for p, g, r in zip(params, grads, ref):
        assert float((g - r).abs().max()) / (float(r.abs().max()) + 1e-12) < 1e-5, tuple(p.shape)


def test_clone_whole_updates_match_between_the_two_paths():
    batch = _advised_batch(128, 11, seed=4)
    states = {}
    for impl in ("torchrl", "fused"):
        torch.manual_seed(0)
        sac = make_sac({"loss_impl": impl, "clone_weight": 0.5}, 11, Bounded(-1.0, 1.0, shape=(2,)))
        for i in range(4):
            torch.manual_seed(200 + i)
            logs = sac.update(batch.clone())
        assert logs["loss_clone"] > 0
        states[impl] = sac.state_dict()
    for key, value in states["torchrl"]["loss"].items():
        if value.is_floating_point():
            assert torch.allclose(value, states["fused"]["loss"][key], rtol=1e-4, atol=1e-6), key


def test_clone_off_or_without_advice_leaves_sac_unchanged():
    batch = _advised_batch(64, 7, seed=6)
    no_advice = batch.clone()
    no_advice["action_source"] = torch.where(torch.isin(batch["action_source"], torch.tensor(ADVICE_SOURCES)),
                                             torch.tensor(POLICY), batch["action_source"])
    results = []
    for cfg, b in (({}, batch), ({"clone_weight": 3.0}, no_advice)):
        torch.manual_seed(0)
        sac = make_sac(cfg, 7, Bounded(-1.0, 1.0, shape=(2,)))
        torch.manual_seed(1)
        logs = sac.update(b.clone())
        assert logs["loss_clone"] == 0
        results.append(sac.state_dict()["loss"])
    for key, value in results[0].items():
        assert torch.equal(value, results[1][key]), key


def test_clone_weight_decays_linearly_to_zero():
    sac = make_sac({"clone_weight": 2.0, "clone_decay_frames": 1000}, 5, Bounded(-1.0, 1.0, shape=(2,)))
    got = []
    for frames in (0, 250, 1000, 5000):
        sac.anneal(frames)
        got.append(sac.clone_now)
    assert got == pytest.approx([2.0, 1.5, 0.0, 0.0])
    batch = _advised_batch(32, 5, seed=1)
    sac.anneal(1000)
    assert sac._clone_mask(batch) is None  # weight 0: no cloning work at all


@pytest.mark.parametrize("impl", ["fused", "torchrl"])
def test_clone_toward_teacher_labels_by_hand(impl):
    """Every row is the actor's own (no advice executed) but carries the teacher's label: the
    deterministic action is (0.5, 0) everywhere; labels (1, -1), (0, 0), (0.5, 0.5), (-1, 1), the
    second not labelled (advice_ok False). w / 4 * ((0.25 + 1) + 0.25 + (2.25 + 1)) = w * 4.75 / 4,
    so 2.375 at w = 2; the replayed actions (all zero) play no part."""
    sac = make_sac({"clone_weight": 2.0, "clone_scale": "none", "loss_impl": impl}, 3, Bounded(-1.0, 1.0, shape=(2,)))
    last = sac._fused.actor_layers[-1] if impl == "fused" else None
    with torch.no_grad():
        if last is None:
            last = [m for m in sac.actor.modules() if isinstance(m, nn.Linear)][-1]
            w_out, b_out = last.weight, last.bias
        else:
            w_out, b_out = last
        w_out.zero_()
        b_out[:2] = torch.tensor([math.atanh(0.5), 0.0])
    batch = random_batch(4, 3, seed=0)
    batch["action"] = torch.zeros(4, 2)
    batch["action_source"] = torch.full((4,), POLICY)
    batch["advice"] = torch.tensor([[1.0, -1.0], [0.0, 0.0], [0.5, 0.5], [-1.0, 1.0]])
    batch["advice_ok"] = torch.tensor([True, False, True, True])
    logs = sac.update(batch)
    assert logs["loss_clone"] == pytest.approx(2.375, rel=1e-5)


def test_teacher_labels_every_row_with_the_heuristics_answer():
    """Under fixed_prob 0.5 with label_all, every row carries the greedy heuristic's answer as
    if it flew that row every slot (a reference greedy stepped on the whole batch beside it); the
    rows the advisor acted on executed exactly that label, the others the actor's action. In
    evaluation nothing is labelled; an advisor that cannot label is refused."""
    env = UAVEnv(batch_size=[8], seed=5)
    reference = GreedyPolicy(env.cfg)
    actor = TensorDictModule(ConstActor(), in_keys=["observation"], out_keys=["action"])
    policy = OverridePolicy(actor, HeuristicAdvisor(GreedyPolicy(env.cfg)), mode="fixed_prob", fp=0.5, seed=3,
                            label_all=True)
    td = env.reset()
    advised = own = 0
    gap_sum = 0.0  # the actor's own (0.25, -0.25) against the label, on the rows it flew
    for _ in range(40):
        ref = reference.act(td.get("state")).clamp(-1, 1)
        td = policy(td)
        torch.testing.assert_close(td.get("advice"), ref)
        assert bool(td.get("advice_ok").all())
        by_advisor = td.get("action_source") == HEURISTIC
        torch.testing.assert_close(td.get("action")[by_advisor], ref[by_advisor])
        torch.testing.assert_close(td.get("action")[~by_advisor], torch.tensor([0.25, -0.25]).expand(int((~by_advisor).sum()), 2))
        advised, own = advised + int(by_advisor.sum()), own + int((~by_advisor).sum())
        gap_sum += float(torch.linalg.vector_norm(ref[~by_advisor] - torch.tensor([0.25, -0.25]), dim=-1).sum())
        _, td = env.step_and_maybe_reset(td)
    assert advised > 60 and own > 60
    snap = policy.snapshot()
    assert snap["label_rows"] == own and snap["label_gap"] == pytest.approx(gap_sum / own, rel=1e-5)
    with policy.actor_only():
        assert "advice" not in policy(td.exclude("advice", "advice_ok")).keys()
    with pytest.raises(ValueError, match="label_all"):
        OverridePolicy(actor, FixedAdvisor([1.0, 1.0]), mode="always", label_all=True)


def test_clone_needs_an_advisor_and_action_source():
    from uavlae.algos.sac import make_sac_config

    with pytest.raises(ValueError, match="clone_weight"):
        make_sac_config({"clone_weight": -1.0})
    sac = make_sac({"clone_weight": 1.0}, 5, Bounded(-1.0, 1.0, shape=(2,)))
    with pytest.raises(KeyError, match="action_source"):
        sac.update(random_batch(8, 5))


# ---------------------------------------------------------------------------- the override's side


class ConstActor(nn.Module):
    def forward(self, obs):
        return torch.tensor([0.25, -0.25]).expand(obs.shape[0], 2).clone()


class LocActor(nn.Module):
    """Writes a sampled action far from its mean, and loc = atanh(0.2, 0.2): agreement must read
    the deterministic action tanh(loc) = (0.2, 0.2), not the sample."""

    def forward(self, obs):
        n = obs.shape[0]
        return torch.full((n, 2), -0.9), torch.full((n, 2), math.atanh(0.2))


def _rows(d, n_extra=0):
    B = len(d)
    state = {"d_bz": torch.tensor(d, dtype=torch.float32), "d_nfz": torch.full((B,), math.inf),
             "d_rz": torch.full((B,), math.inf), "d_ou": torch.full((B,), math.inf),
             "step": torch.arange(B)}
    return TensorDict({"observation": torch.zeros(B, 3), "state": TensorDict(state, [B])}, [B])


class FixedAdvisor(Advisor):
    source = HEURISTIC

    def __init__(self, action):
        self.action = torch.tensor(action)

    def advise(self, td_rows, rows):
        return self.action.expand(rows.numel(), 2).clone(), torch.ones(rows.numel(), dtype=torch.bool)


def test_phase_out_anneals_d_th_to_nothing():
    """d_th 20 m, phase-out over 8 frames, 4 rows a step at 2, 8, 14, 19 m. Frames acted on
    before each step: 0, 4, 8: scale 1, 0.5, 0 -> d_th 20, 10, 0 -> 4, 2, 0 rows triggered."""
    actor = TensorDictModule(ConstActor(), in_keys=["observation"], out_keys=["action"])
    pol = OverridePolicy(actor, FixedAdvisor([1.0, 1.0]), mode="proximity", d_th=20.0, phase_out_frames=8)
    counts = []
    for _ in range(3):
        out = pol(_rows([2.0, 8.0, 14.0, 19.0]))
        counts.append(int((out["action_source"] == HEURISTIC).sum()))
    assert counts == [4, 2, 0]
    assert pol.snapshot()["phase"] == 0.0
    with pol.advised():  # the evaluation with the advisor: the paper's trigger, no phase-out
        assert int((pol(_rows([2.0, 8.0, 14.0, 19.0]))["action_source"] == HEURISTIC).sum()) == 4
    assert pol.phase() == 0.0 and pol.totals["frames"] == 12  # training state put back


def test_phase_out_of_fixed_prob_scales_fp():
    actor = TensorDictModule(ConstActor(), in_keys=["observation"], out_keys=["action"])
    pol = OverridePolicy(actor, FixedAdvisor([1.0, 1.0]), mode="fixed_prob", fp=0.8, phase_out_frames=40_000, seed=0)
    first = pol(_rows([50.0] * 20_000))  # at scale 1: rate 0.8
    second = pol(_rows([50.0] * 10_000))  # after 20k of 40k frames: fp 0.4
    third = pol(_rows([50.0] * 10_000))  # 30k: fp 0.2
    rates = [float((o["action_source"] == HEURISTIC).float().mean()) for o in (first, second, third)]
    assert rates == pytest.approx([0.8, 0.4, 0.2], abs=0.02)
    with pytest.raises(ValueError, match="phase_out_frames"):
        OverridePolicy(actor, FixedAdvisor([1.0, 1.0]), mode="always", phase_out_frames=10)


def test_agreement_reads_the_actors_deterministic_action():
    """Advice (0.2, 0.2) on rows 0, 1 (within 15 m), and (1, 1) after a reset of the advisor:
    the actor's deterministic action is (0.2, 0.2) while its sample is (-0.9, -0.9). Gap 0 on
    the first step (both rows agree), sqrt(2) * 0.8 on the second (neither)."""
    actor = TensorDictModule(LocActor(), in_keys=["observation"], out_keys=["action", "loc"])
    adv = FixedAdvisor([0.2, 0.2])
    pol = OverridePolicy(actor, adv, mode="proximity", d_th=15.0, agree_tol=0.1)
    pol(_rows([3.0, 10.0, 30.0]))
    s = pol.snapshot(reset=True)
    assert s["actor_gap"] == pytest.approx(0.0, abs=1e-6) and s["actor_agree"] == 1.0
    assert s["advised_fraction"] == pytest.approx(2 / 3)
    adv.action = torch.tensor([1.0, 1.0])
    pol(_rows([3.0, 10.0, 30.0]))
    s = pol.snapshot(reset=True)
    assert s["actor_gap"] == pytest.approx(math.sqrt(2) * 0.8, rel=1e-5) and s["actor_agree"] == 0.0
    t = pol.run_totals()
    assert t["actor_gap"] == pytest.approx(math.sqrt(2) * 0.8 / 2, rel=1e-5) and t["actor_agree"] == 0.5
    assert t["advised_fraction"] == pytest.approx(4 / 6)


def test_scripted_advisors():
    hover = ScriptedAdvisor("hover")
    a, ok = hover.advise(None, torch.tensor([3, 5]))
    assert a.tolist() == [[0.0, 0.0], [0.0, 0.0]] and ok.all()
    r1, r2 = ScriptedAdvisor("random", seed=4), ScriptedAdvisor("random", seed=4)
    x, _ = r1.advise(None, torch.arange(1000))
    torch.testing.assert_close(x, r2.advise(None, torch.arange(1000))[0])
    assert float(x.min()) >= -1 and float(x.max()) <= 1 and abs(float(x.mean())) < 0.05
    state = r1.state_dict()
    nxt = r1.advise(None, torch.arange(3))[0]
    r2.load_state_dict(state)
    torch.testing.assert_close(r2.advise(None, torch.arange(3))[0], nxt)
    with pytest.raises(ValueError, match="hover"):
        ScriptedAdvisor("teleport")
    actor = TensorDictModule(ConstActor(), in_keys=["observation"], out_keys=["action"])
    out = OverridePolicy(actor, hover, mode="always")(_rows([1.0, 1.0]))
    assert out["action_source"].tolist() == [SCRIPTED, SCRIPTED] and out["action"].abs().sum() == 0
