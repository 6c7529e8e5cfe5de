"""The real local model (SmolLM2-135M via xllamacpp on 127.0.0.1): prompts built from states,
validated actions back. One server for the session, always stopped by its fixture."""

from __future__ import annotations

import math
import os

import httpx
import pytest
import torch

from uavlae.llm import Advice, LLMAdvisor, WorldLimits, advisor_states_from_tensordict, make_llm_config
from uavlae.llm.server import local_server

pytestmark = [pytest.mark.integration, pytest.mark.timeout(300)]

LIM = WorldLimits(x_size=500.0, y_size=500.0, v_max=10.0, v_limit=5.0, perception_radius=20.0,
                  landing=(475.0, 0.0, 500.0, 25.0), e_limit=8e5)
SHORT = dict(max_tokens=96, reasoning_max_chars=40)  # the tests check plumbing, not eloquence


@pytest.fixture(scope="session")
def llm_server():
    with local_server(n_threads=1, n_parallel=1) as srv:
        yield srv
    # the context manager stopped exactly its child
    with pytest.raises(ProcessLookupError):
        os.kill(srv.pid, 0)


def test_server_is_healthy_and_local(llm_server):
    assert llm_server.base_url.startswith("http://127.0.0.1:")
    assert httpx.get(llm_server.base_url.removesuffix("/v1") + "/health", timeout=5).status_code == 200


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
