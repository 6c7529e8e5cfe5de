"""Extractor (paper §5.3.2): a completion's text -> a validated velocity, or ExtractionError.

Tolerates a reasoning model's ``<think>`` block, code fences and prose around the JSON; takes
the last top-level JSON object that carries vx and vy (objects nested inside it, e.g. text in
"Reasoning" that imitates an answer, are never candidates). Rejects NaN/Infinity, missing keys,
and |v| > v_max. Numbers in the Reasoning text are never read as an action.
"""

from __future__ import annotations

import json
import math
import re

from pydantic import ValidationError

from .schema import ActionSchema, Advice, ExtractionError, FailureKind

_THINK = re.compile(r"<think>.*?</think>", re.DOTALL | re.IGNORECASE)
_CANON = {"vx": "vx", "vy": "vy", "confidence": "Confidence", "reasoning": "Reasoning"}
_decoder = json.JSONDecoder(parse_constant=lambda c: _reject_constant(c))


class _NonFinite(ValueError):
    pass


def _reject_constant(c: str) -> float:
    raise _NonFinite(c)


def _strip(text: str) -> str:
    text = _THINK.sub("", text)
    low = text.lower()
    if "<think>" in low:  # an unclosed block: everything after it is still thinking
        text = text[: low.index("<think>")]
    return text


def _candidates(text: str) -> tuple[list[dict], FailureKind | None, str]:
    """Top-level JSON objects in ``text``; and the first decoding problem met, if any."""
    found: list[dict] = []
    problem: FailureKind | None = None
    detail = ""
    i = text.find("{")
    while i != -1:
        try:
            obj, end = _decoder.raw_decode(text, i)
        except _NonFinite as e:
            problem, detail = problem or FailureKind.NON_FINITE, detail or f"non-finite number {e}"
            i = text.find("{", i + 1)
            continue
        except ValueError as e:
            problem, detail = problem or FailureKind.INVALID_JSON, detail or f"invalid JSON ({e.msg})"
            i = text.find("{", i + 1)
            continue
        if isinstance(obj, dict):
            found.append(obj)
        i = text.find("{", end)
    return found, problem, detail


def extract_action(text: str | None, v_max: float, *, max_chars: int = 1_000_000,
                   speed_tol: float = 1e-6) -> Advice:
    """Parse and validate one completion. Raises :class:`ExtractionError` with a kind."""
    if text is None or not text.strip():
        raise ExtractionError(FailureKind.EMPTY, "empty answer")
    if len(text) > max_chars:
        raise ExtractionError(FailureKind.TOO_LARGE, f"answer of {len(text)} chars > {max_chars}")
    body = _strip(text)
    if "{" not in body:
        raise ExtractionError(FailureKind.NO_JSON, "no JSON object in the answer")
    objs, problem, detail = _candidates(body)
    keyed = [{_CANON.get(str(k).lower(), k): v for k, v in o.items()} for o in objs]
    with_v = [o for o in keyed if "vx" in o and "vy" in o]
    if not with_v:
        if problem is not None:
            raise ExtractionError(problem, detail)
        if keyed:
            raise ExtractionError(FailureKind.MISSING_KEYS, "no object with both vx and vy")
        raise ExtractionError(FailureKind.NO_JSON, "no JSON object in the answer")
    obj = with_v[-1]
    missing = [k for k in ("vx", "vy", "Confidence", "Reasoning") if k not in obj]
    if missing:
        raise ExtractionError(FailureKind.MISSING_KEYS, f"missing keys {missing}")
    for k in ("vx", "vy", "Confidence"):
        v = obj[k]
        if isinstance(v, bool) or not isinstance(v, (int, float, str)):
            raise ExtractionError(FailureKind.INVALID_VALUE, f"{k} is not a number")
        if isinstance(v, str):  # "4.2" is tolerated, "nan"/"inf" are not
            try:
                v = float(v)
            except ValueError:
                raise ExtractionError(FailureKind.INVALID_VALUE, f"{k} is not a number") from None
            obj[k] = v
        if not math.isfinite(float(v)):
            raise ExtractionError(FailureKind.NON_FINITE, f"{k} is not finite")
    if not isinstance(obj["Reasoning"], str):
        obj["Reasoning"] = json.dumps(obj["Reasoning"])[:1000]
    try:
        a = ActionSchema.model_validate(obj)
    except ValidationError as e:
        raise ExtractionError(FailureKind.INVALID_VALUE, e.errors()[0]["msg"]) from None
    speed = math.hypot(a.vx, a.vy)
    if speed > v_max + speed_tol:
        raise ExtractionError(FailureKind.OVER_SPEED, f"speed {speed:.3g} m/s exceeds v_max {v_max:g}")
    conf = min(max(a.Confidence, 0.0), 1.0)  # a confidence outside [0, 1] is not worth a retry
    return Advice(vx=a.vx, vy=a.vy, confidence=conf, reasoning=a.Reasoning[:1000])
