"""benchmarks/llm_call_breakdown.py's answer agreement, on calls written by hand."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))

from llm_call_breakdown import answer_agreement  # noqa: E402


def _calls(*answers):
    return [{"answer": a} for a in answers]


def test_answer_agreement_counts_whole_answers_and_velocities_over_every_stream():
    default = [_calls([1.0, 2.0, 0.5, "a"], [3.0, 4.0, 0.5, "b"]), _calls([0.0, 1.0, 0.9, "c"])]
    other = [_calls([1.0, 2.0, 0.5, "a"],   # the same answer
                    [3.0, 4.0, 0.7, "x"]),  # the same velocity, another confidence and reasoning
             _calls([0.0, 5.0, 0.9, "c"])]  # another velocity
    got = answer_agreement(other, default)
    assert got["same_answer_as_default"] == pytest.approx(1 / 3)
    assert got["same_velocity_as_default"] == pytest.approx(2 / 3)


def test_a_failed_call_agrees_only_with_another_failure_and_never_on_velocity():
    default = [_calls(None, [1.0, 1.0, 0.5, "a"])]
    other = [_calls(None, None)]
    got = answer_agreement(other, default)
    assert got["same_answer_as_default"] == pytest.approx(1 / 2)  # None == None
    assert got["same_velocity_as_default"] == 0.0
