"""What the advisor returns: a validated velocity, or a typed failure the caller acts on."""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import Enum
from typing import Any

from pydantic import BaseModel, ConfigDict


class FailureKind(str, Enum):
    # transport: retried with backoff up to max_retries, then final
    TIMEOUT = "timeout"
    CONNECTION = "connection"
    RATE_LIMITED = "rate_limited"  # 429 after the retries
    SERVER_ERROR = "server_error"  # 5xx after the retries
    HTTP_ERROR = "http_error"  # other 4xx (bad request, auth): not retried
    # content: the extractor rejects the answer; asked again up to max_attempts
    TOO_LARGE = "too_large"
    EMPTY = "empty"
    NO_JSON = "no_json"
    INVALID_JSON = "invalid_json"
    MISSING_KEYS = "missing_keys"
    NON_FINITE = "non_finite"
    INVALID_VALUE = "invalid_value"
    OVER_SPEED = "over_speed"
    TRUNCATED = "truncated"  # finish_reason == "length" and no valid action

    @property
    def is_transport(self) -> bool:
        return self in _TRANSPORT


_TRANSPORT = {FailureKind.TIMEOUT, FailureKind.CONNECTION, FailureKind.RATE_LIMITED,
              FailureKind.SERVER_ERROR, FailureKind.HTTP_ERROR}


class ActionSchema(BaseModel):
    """The strict JSON object of the prompt's part (c). Bounds are checked by the extractor."""

    model_config = ConfigDict(extra="ignore", allow_inf_nan=False, populate_by_name=True)

    vx: float
    vy: float
    Confidence: float
    Reasoning: str


def answer_keys(reasoning_first: bool = False) -> tuple[str, ...]:
    """The answer's keys in the order the grammar, the schema and the prompt's example write them."""
    return ("Reasoning", "vx", "vy", "Confidence") if reasoning_first else ("vx", "vy", "Confidence", "Reasoning")


def action_json_schema(v_max: float, reasoning_max_chars: int, reasoning_first: bool = False) -> dict[str, Any]:
    """JSON schema sent as ``response_format``. Servers may ignore the numeric bounds. llama.cpp
    writes the properties in their order here, so ``reasoning_first`` puts the Reasoning first."""
    props = {
        "vx": {"type": "number", "minimum": -v_max, "maximum": v_max},
        "vy": {"type": "number", "minimum": -v_max, "maximum": v_max},
        "Confidence": {"type": "number", "minimum": 0, "maximum": 1},
        "Reasoning": {"type": "string", "maxLength": reasoning_max_chars},
    }
    order = list(answer_keys(reasoning_first))
    return {
        "type": "object",
        "properties": {k: props[k] for k in order},
        "required": order,
        "additionalProperties": False,
    }


@dataclass(frozen=True)
class Advice:
    """A validated velocity (m/s). ``source`` is "llm" or "cache"."""

    vx: float
    vy: float
    confidence: float
    reasoning: str
    attempts: int = 1  # server answers it took (0 for a cache hit)
    source: str = "llm"
    latency_s: float = 0.0

    ok = True

    def action(self, v_max: float) -> tuple[float, float]:
        """The env action a in [-1, 1]^2 with v = v_max * a (SPEC §2)."""
        return (self.vx / v_max, self.vy / v_max)


@dataclass(frozen=True)
class AdviceFailure:
    """No valid action; the caller applies its one fallback setting (the override's
    ``advisor.fallback``: end the episode as the paper does, the actor's or the heuristic's action)."""

    kind: FailureKind
    detail: str
    attempts: int
    history: tuple[FailureKind, ...] = field(default_factory=tuple)  # kind of each rejected try

    ok = False


class ExtractionError(ValueError):
    def __init__(self, kind: FailureKind, detail: str):
        super().__init__(f"{kind.value}: {detail}")
        self.kind = kind
        self.detail = detail


class CacheMissError(RuntimeError):
    """replay_only cache mode met a prompt it has no answer for."""


class EndpointError(RuntimeError):
    """A permanent fault of the endpoint (rejected key, unknown model, not an OpenAI-compatible
    server), or an outage (``max_failed_rows`` rows in a row it did not answer): the run stops.
    The message names the endpoint, what failed and the key's environment variable, never the key."""
