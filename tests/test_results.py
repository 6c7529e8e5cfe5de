"""What a run's results say, numbers by hand: strict JSON (no NaN), the LLM's calls as one count
with its parts, the line that says the with-advisor budget bit, a summary read back from strict
JSON, and the pictures: each GE at the data it held when the episode ended, the outcome in the
title."""

from __future__ import annotations

import json
import math

import pytest
import torch
from tensordict import TensorDict

from uavlae.envs import make_env_config
from uavlae.envs.render import draw_scenario, episode_outcome
from uavlae.envs.scenario import load_scenarios
from uavlae.evaluate import EpisodeEnds
from uavlae.factories import REPO_ROOT
from uavlae.files import dump_json
from uavlae.summary import format_summary


def test_json_files_are_strict_a_nan_is_null(tmp_path):
    path = dump_json(tmp_path / "s.json", {"money": math.nan, "xs": (math.inf, 1.5, -math.inf), "n": {"k": 2}})
    text = path.read_text()
    assert "NaN" not in text and "Infinity" not in text
    assert json.loads(text) == {"money": None, "xs": [None, 1.5, None], "n": {"k": 2}}
    with pytest.raises(ValueError):  # a file whose numbers must all be finite refuses one
        dump_json(tmp_path / "t.json", [math.nan], allow_nan=False)


OVERRIDE = {  # an advised run's counters as summary.json holds them (strict JSON: no value is null)
    "triggered": 300, "frames": 1000, "advised": 30, "held": 0, "hold_steps": 1, "budget_skipped": 0, "max_calls": -1,
    "source/fallback": 2, "advised_fraction": 0.03, "actor_gap": None, "actor_agree": None, "agree_tol": 0.1,
    "advisor/calls": 45, "advisor/requests": 30, "advisor/cache_hits": 4, "advisor/ask_again": 15,
    "advisor/retries": 4, "advisor/latency_p50_s": None, "advisor/latency_p95_s": 2.5, "advisor/prompt_tokens": 9000,
    "advisor/completion_tokens": 900, "advice_wait_s": 12.0,
}


def _summary(**more) -> dict:
    base = {"name": "sac_llm", "controller": "learner", "run_dir": "runs/x", "frames": 1000,
            "full_run_frames": 1000000, "updates": 744, "train_s": 50.0, "fps": 20.0, "eval_episodes": 8,
            "metrics": {"sac_llm (trained actor)": {"DCR": 0.5, "CR": None, "SLR": 0.0, "RVR": 0.25, "ECR": 0.1}},
            "advisor_kind": "llm", "override": OVERRIDE, "pictures": []}
    return json.loads(json.dumps({**base, **more}))


def test_the_llm_line_is_one_count_with_its_parts():
    text = format_summary(_summary())
    (line,) = [ln for ln in text.splitlines() if ln.startswith("  LLM in training: ")]
    # 45 calls = 26 first calls (45 - 15 - 4) + 15 asked again + 4 retries; 45 per 1000 frames; 9000 / 45 = 200
    assert line.startswith("  LLM in training: 45 HTTP calls (45.0 per 1000 frames) = 26 first calls for the 30 rows asked "
                           "(4 answered from the cache, rows with the same prompt sharing one call) + 15 asked again "
                           "after an answer it could not use + 4 transport retries; per call p50 nan s, p95 2.50 s, "
                           "200 prompt + 20 completion tokens")
    assert "sac_llm (trained actor)     0.500     nan   0.000" in text  # a null metric reads nan, no crash


def test_the_summary_says_when_the_with_advisor_budget_left_rows_to_the_actor():
    bit = format_summary(_summary(advised_eval={"max_calls": 64, "triggered": 410, "advised": 64,
                                                "budget_skipped": 346}))
    assert ("  The actor with its advisor: trainer.eval_advisor_max_calls=64 rows were asked, then the actor flew "
            "346 of the 410 triggered rows itself") in bit
    unbitten = format_summary(_summary(advised_eval={"max_calls": 64, "triggered": 40, "advised": 40,
                                                     "budget_skipped": 0, "llm_requests": 40, "llm_calls": 52}))
    assert "eval_advisor_max_calls" not in unbitten
    # its own LLM calls, apart from training's 45
    assert ("  The actor with its advisor asked the LLM for 40 rows in 52 HTTP calls (not counted in the LLM line "
            "of training below).") in unbitten


def test_the_cost_line_reads_a_null_price_as_none():
    cost = {"triggered": 30, "rows_llm": 26, "rows_student": 0, "rows_held": 0, "rows_fallback": 2, "tokens_in": 9000,
            "tokens_in_cached": 100, "tokens_out": 900, "llm_s": 30.0, "wait_s": 12.0, "money": math.nan,
            "currency": None}
    text = format_summary(_summary(cost=dump_json_roundtrip(cost)))
    assert "; no price in the llm config." in text


def dump_json_roundtrip(obj):
    from uavlae.files import finite

    return json.loads(json.dumps(finite(obj), allow_nan=False))


def test_episode_outcome_by_hand():
    t, f = torch.tensor(True), torch.tensor(False)
    landed = {"landed": t, "bz_collision": f, "rz_speeding": t, "boundary_exit": f,
              "data_collected": torch.tensor(5.0), "data_total": torch.tensor(6.0)}
    assert episode_outcome(landed) == "landed, DCR 0.83, sped in an RZ"
    crashed = {"bz_collision": True, "landed": False, "data_collected": 0.0, "data_total": 4.0}
    assert episode_outcome(crashed) == "crashed into a building, DCR 0.00"
    late = {"truncated": True, "boundary_exit": True, "data_collected": 1.0, "data_total": 2.0}
    assert episode_outcome(late) == "out of time, DCR 0.50, left the area"


def _next(left) -> TensorDict:
    return TensorDict({"state": {"ge_remaining": torch.tensor(left)}}, batch_size=[2])


def test_episode_ends_keeps_each_rows_ge_data_from_the_step_that_ended_it():
    seen = []
    ends = EpisodeEnds(lambda step, finished, nxt: seen.append(step))
    ends(1, torch.tensor([False, False]), _next([[2.0, 1.0], [3.0, 3.0]]))
    ends(2, torch.tensor([True, False]), _next([[0.0, 1.0], [3.0, 2.0]]))  # row 0 ends here
    ends(3, torch.tensor([True, True]), _next([[5.0, 5.0], [0.0, 2.0]]))  # row 0 flies on, ignored
    assert ends.ge_left.tolist() == [[0.0, 1.0], [0.0, 2.0]] and seen == [1, 2, 3]


def test_a_picture_draws_each_ge_at_its_end_state():
    scenario = load_scenarios(REPO_ROOT / "results" / "eval_set_32.json")[0]

    def labels(fig) -> set[str]:
        return {t.get_text() for t in fig.axes[0].get_legend().get_texts()}

    assert "GE (size: data left)" in labels(draw_scenario(scenario)) and "GE collected" not in labels(
        draw_scenario(scenario))
    padded = make_env_config().ge.count.padded  # the state's layout, as the evaluator keeps it
    emptied = labels(draw_scenario(scenario, ge_left=torch.zeros(padded)))
    assert "GE collected" in emptied and "GE (size: data left)" not in emptied
