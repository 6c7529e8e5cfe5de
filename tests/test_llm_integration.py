"""The real local model (SmolLM2-135M via xllamacpp on 127.0.0.1): prompts built from states,
validated actions back. One server for the session, always stopped by its fixture."""

from __future__ import annotations

import math
import os
import tempfile
from pathlib import Path

import httpx
import pytest
import torch

from uavlae.llm import Advice, LLMAdvisor, WorldLimits, advisor_states_from_tensordict, make_llm_config
from uavlae.llm.server import local_server

pytestmark = [pytest.mark.integration, pytest.mark.timeout(300)]

LIM = WorldLimits(x_size=500.0, y_size=500.0, v_max=10.0, v_limit=5.0, perception_radius=20.0,
                  landing=(475.0, 0.0, 500.0, 25.0), e_limit=8e5)
SHORT = dict(max_tokens=96, reasoning_max_chars=40)  # the tests check plumbing, not eloquence


def test_server_is_healthy_and_local(llm_server):
    assert llm_server.base_url.startswith("http://127.0.0.1:")
    assert httpx.get(llm_server.base_url.removesuffix("/v1") + "/health", timeout=5).status_code == 200
    # a process group of its own: a stop sent to the trainer's group leaves it answering
    assert os.getpgid(llm_server.pid) == llm_server.pid != os.getpgid(0)


def test_real_states_give_validated_actions(llm_server, tmp_path):
    from test_llm_unit import _contract_td  # a TensorDict that follows the env contract

    states = advisor_states_from_tensordict(_contract_td(), [0, 1], LIM)
    cfg = make_llm_config("local", cache_path=str(tmp_path / "c.sqlite"), **SHORT)
    with LLMAdvisor(cfg, base_url=llm_server.base_url) as adv:
        res = adv.advise_sync(states, timeout=240)
        for r in res:
            assert isinstance(r, Advice), r
            assert math.hypot(r.vx, r.vy) <= LIM.v_max + 1e-6 and math.isfinite(r.confidence)
            assert r.action(LIM.v_max)[0] == pytest.approx(r.vx / LIM.v_max)
        again = adv.advise_sync(states, timeout=60)
        snap = adv.stats.snapshot()
    assert [a.source for a in again] == ["cache", "cache"]
    assert [(a.vx, a.vy) for a in again] == [(r.vx, r.vy) for r in res]
    assert snap["cache_hits"] == 2 and snap["prompt_tokens"] > 0 and snap["completion_tokens"] > 0
    # the action fits the env's action tensor
    act = torch.tensor([r.action(LIM.v_max) for r in res])
    assert act.shape == (2, 2) and act.abs().max() <= 1


def test_grammar_mode_works_on_llama_cpp(llm_server):
    from uavlae.llm import example_states

    cfg = make_llm_config("local", cache_mode="off", response_format="grammar", **SHORT)
    with LLMAdvisor(cfg, base_url=llm_server.base_url) as adv:
        (r,) = adv.advise_sync(example_states(1, LIM, seed=3), timeout=240)
    assert isinstance(r, Advice), r


def test_autostart_owns_and_stops_its_server(tmp_path):
    from uavlae.llm import example_states

    adv = LLMAdvisor(make_llm_config("local", cache_mode="off", **SHORT))
    (r,) = adv.advise_sync(example_states(1, LIM, seed=4), timeout=240)
    pid = adv.local_server.pid  # the child this advisor started
    adv.close()
    assert isinstance(r, Advice)
    with pytest.raises(ProcessLookupError):
        os.kill(pid, 0)


def test_slot_affinity_keeps_each_episodes_prefix_cached():
    """Episodes A, B, then A again one slot later: with affinity A's second call finds its map
    and GEs cached in its own slot; B's first call finds the system prompt copied into its slot
    (not evaluated again). Without affinity the one most similar slot serves everyone."""
    import dataclasses

    from uavlae.llm import example_states

    a, b = example_states(2, LIM, seed=11)
    a2 = dataclasses.replace(a, position=(a.position[0] + 3.0, a.position[1] - 2.0))
    reused = {}
    with local_server(n_threads=1, n_parallel=2, ctx_per_slot=2048) as srv:
        for affinity in (False, True):  # without first: a fresh server, no leftover prompts
            calls = []
            # the paper's example: SmolLM2's first answers are valid, one call per state
            cfg = make_llm_config("local", cache_mode="off", slot_affinity=affinity, example="paper")
            with LLMAdvisor(cfg, base_url=srv.base_url) as adv:
                adv.on_call = calls.append
                for s in (a, b, a2):
                    (r,) = adv.advise_sync([s], timeout=240)
                    assert isinstance(r, Advice), r
            reused[affinity] = [c.timings["cache_n"] for c in calls]
        # the copy of the system prompt lies inside the server's own slot folder ...
        saved = Path(srv.slots_dir) / f"uavlae-prefix-{os.getpid()}.bin"
        assert saved.is_file() and saved.stat().st_size > 0
    # ... and goes with it: nothing is left in the temp folder
    assert not Path(srv.slots_dir).exists()
    assert not list(Path(tempfile.gettempdir()).glob(f"*uavlae-prefix-{os.getpid()}.bin"))
    on, off = reused[True], reused[False]
    assert on[1] >= 400  # the ~480-token system prompt, restored into slot 1, not evaluated
    assert on[2] >= on[1] + 100  # A's zones and GEs (11+ GEs of 8+ tokens each) came back too
    assert off[2] < on[2] - 100  # without affinity B's call had overwritten A's prefix


@pytest.mark.parametrize("fmt", ["grammar", "json_schema"])
def test_reasoning_first_answers_open_with_the_reasoning(llm_server, fmt):
    from uavlae.llm import example_states

    texts = []
    cfg = make_llm_config("local", cache_mode="off", response_format=fmt, reasoning_first=True,
                          example="placeholder", **SHORT)
    with LLMAdvisor(cfg, base_url=llm_server.base_url) as adv:
        adv.on_call = lambda res: texts.append(res.text)
        (r,) = adv.advise_sync(example_states(1, LIM, seed=5), timeout=240)
    assert isinstance(r, Advice), r
    assert texts[0].lstrip("{ \n").startswith('"Reasoning"'), texts[0]
    assert len(r.reasoning) <= SHORT["reasoning_max_chars"]


@pytest.mark.parametrize("kw", [{"example": "placeholder"}, {"example": "none", "reasoning_first": True}])
def test_the_whole_system_message_is_reused_by_the_next_state(llm_server, kw):
    """States of two different maps on the one slot: the second call finds every token of the
    system message cached, so nothing in it depends on the state or the call."""
    from uavlae.llm import example_states

    a, b = example_states(2, LIM, seed=21)
    calls = []
    cfg = make_llm_config("local", cache_mode="off", **kw, **SHORT)
    with LLMAdvisor(cfg, base_url=llm_server.base_url) as adv:
        adv.on_call = calls.append
        for s in (a, b):
            (r,) = adv.advise_sync([s], timeout=240)
            assert isinstance(r, Advice), r
        system = adv._messages(a)[0]["content"]
    assert system == adv._messages(b)[0]["content"]
    root = llm_server.base_url.removesuffix("/v1")
    n_system = len(httpx.post(root + "/tokenize", json={"content": system}, timeout=30).json()["tokens"])
    assert n_system > 300
    assert calls[1].timings["cache_n"] >= n_system  # the chat template's role tokens come on top
