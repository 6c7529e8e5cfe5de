"""One OpenAI-compatible ``/chat/completions`` request with bounded retries (async httpx).

Retried with exponential backoff and jitter: connection errors, timeouts, 5xx, and 429 (after
``Retry-After`` when the server sends it, capped). Other 4xx fail at once. The whole request,
body included, has one deadline, and the body is read up to a byte limit, so a slow drip or a
huge answer can neither hang nor exhaust memory. A :class:`RowDeadline` bounds one row's
requests together: every request, retry and backoff ends by it.
"""

from __future__ import annotations

import asyncio
import email.utils
import json
import math
import random
import time
from dataclasses import dataclass
from typing import Any, Callable

import httpx

from .schema import FailureKind


@dataclass(frozen=True)
class ChatResult:
    text: str | None
    finish_reason: str | None
    prompt_tokens: int
    completion_tokens: int
    latency_s: float
    timings: dict | None = None  # llama.cpp's own: cache_n, prompt_n, prompt_ms, predicted_n, predicted_ms
    cached_tokens: int = 0  # prompt tokens the server reused from its prefix cache


class RequestFailed(Exception):
    """The server could not be asked (after retries). ``kind`` is a transport FailureKind."""

    def __init__(self, kind: FailureKind, detail: str):
        super().__init__(f"{kind.value}: {detail}")
        self.kind, self.detail = kind, detail


class PermanentFailure(Exception):
    """The endpoint refused in a way no retry can fix: 401, 403, 404/405 (no such route or
    model), a 400 naming an unknown model, or a 200 whose body is not a chat completion."""

    def __init__(self, status: int | None, detail: str):
        super().__init__(detail)
        self.status, self.detail = status, detail


_UNKNOWN_MODEL = ("model_not_found", "not exist", "not found", "unknown model", "invalid model",
                  "no such model")


class BadResponse(Exception):
    """The server answered 200, but with a body we cannot use (too large, not JSON)."""

    def __init__(self, kind: FailureKind, detail: str):
        super().__init__(f"{kind.value}: {detail}")
        self.kind, self.detail = kind, detail


class RowDeadline:
    """What one row may cost in time, whatever its attempts and retries. The clock starts when
    the row's first request is sent, not while the row waits behind other rows for a free
    connection, so a busy but healthy server does not fail rows that were never asked."""

    def __init__(self, seconds: float):
        self.seconds = float(seconds)
        self.t0: float | None = None

    def start(self) -> None:
        if self.t0 is None:
            self.t0 = time.monotonic()

    def left(self) -> float:
        return math.inf if self.t0 is None else self.seconds - (time.monotonic() - self.t0)

    def why(self) -> str:
        return f"no valid answer within the row deadline of {self.seconds:g} s (llm.row_deadline_s)"


class _Retryable(Exception):
    def __init__(self, kind: FailureKind, detail: str, wait: float | None = None):
        super().__init__(detail)
        self.kind, self.detail, self.wait = kind, detail, wait


def parse_retry_after(value: str | None) -> float | None:
    """Seconds from a Retry-After header (delta-seconds or an HTTP date); None if absent/bad."""
    if not value:
        return None
    value = value.strip()
    try:
        return max(0.0, float(value))
    except ValueError:
        pass
    try:
        when = email.utils.parsedate_to_datetime(value)
    except (TypeError, ValueError):
        return None
    return max(0.0, when.timestamp() - time.time())


async def _read_limited(r: httpx.Response, limit: int) -> bytes:
    declared = r.headers.get("content-length")
    if declared is not None and declared.isdigit() and int(declared) > limit:
        raise BadResponse(FailureKind.TOO_LARGE, f"response of {declared} bytes > {limit}")
    buf = bytearray()
    async for chunk in r.aiter_bytes():
        buf += chunk
        if len(buf) > limit:
            raise BadResponse(FailureKind.TOO_LARGE, f"response over {limit} bytes")
    return bytes(buf)


async def _post_once(client: httpx.AsyncClient, url: str, body: dict, headers: dict,
                     timeout_s: float, max_bytes: int) -> ChatResult:
    t0 = time.perf_counter()
    async with client.stream("POST", url, json=body, headers=headers, timeout=timeout_s) as r:
        if r.status_code == 429:
            raise _Retryable(FailureKind.RATE_LIMITED, "HTTP 429",
                             parse_retry_after(r.headers.get("retry-after")))
        if r.status_code >= 500:
            raise _Retryable(FailureKind.SERVER_ERROR, f"HTTP {r.status_code}")
        if r.status_code >= 400:
            snippet = (await _read_limited(r, 1 << 20))[:300].decode("utf-8", "replace")
            low = snippet.lower()
            if r.status_code in (401, 403, 404, 405) or (
                    r.status_code == 400 and "model" in low and any(m in low for m in _UNKNOWN_MODEL)):
                raise PermanentFailure(r.status_code, f"HTTP {r.status_code}: {snippet}")
            raise RequestFailed(FailureKind.HTTP_ERROR, f"HTTP {r.status_code}: {snippet}")
        raw = await _read_limited(r, max_bytes)
    latency = time.perf_counter() - t0
    try:
        data = json.loads(raw)
        choice = data["choices"][0]
        text = choice.get("message", {}).get("content")
        finish = choice.get("finish_reason")
    except (ValueError, KeyError, IndexError, TypeError, AttributeError) as e:
        # a 200 that is not a chat completion at all (an HTML page, another API): the wrong server
        raise PermanentFailure(r.status_code, f"HTTP {r.status_code} with a body that is not an OpenAI chat "
                               f"completion ({type(e).__name__}): {raw[:120].decode('utf-8', 'replace')!r}") from None
    usage = data.get("usage") or {}
    details = usage.get("prompt_tokens_details") if isinstance(usage, dict) else None
    cached = (details or {}).get("cached_tokens") if isinstance(details, dict) else None
    if cached is None:  # DeepSeek names it so (its price differs from a computed token's)
        cached = usage.get("prompt_cache_hit_tokens")
    return ChatResult(
        text=text if isinstance(text, str) else None,
        finish_reason=finish if isinstance(finish, str) else None,
        prompt_tokens=int(usage.get("prompt_tokens") or 0),
        completion_tokens=int(usage.get("completion_tokens") or 0),
        cached_tokens=int(cached or 0),
        latency_s=latency,
        timings=data.get("timings") if isinstance(data.get("timings"), dict) else None,
    )


async def chat_completion(
    client: httpx.AsyncClient,
    url: str,
    body: dict[str, Any],
    headers: dict[str, str],
    *,
    timeout_s: float,
    max_retries: int,
    backoff_base_s: float,
    backoff_max_s: float,
    retry_after_max_s: float,
    max_response_bytes: int,
    slot: asyncio.Semaphore | None = None,
    on_retry: Callable[[FailureKind, str], None] | None = None,
    stop: Callable[[], bool] | None = None,
    deadline: RowDeadline | None = None,
) -> ChatResult:
    """POST ``body`` to ``url``; raise RequestFailed after ``max_retries`` retries or at the
    row's ``deadline``, or BadResponse."""
    deadline = deadline or RowDeadline(math.inf)
    last: _Retryable | None = None
    retries = 0

    async def post() -> ChatResult:
        deadline.start()
        limit = min(timeout_s, deadline.left())
        if limit <= 0:
            raise _Expired()
        async with asyncio.timeout(limit):
            return await _post_once(client, url, body, headers, limit, max_response_bytes)

    for retries in range(max_retries + 1):
        try:
            if slot is not None:
                async with slot:
                    if stop is not None and stop():  # a request queued behind a permanent fault
                        raise PermanentFailure(None, "not sent: the endpoint refused an earlier request")
                    return await post()
            return await post()
        except _Retryable as e:
            last = e
        except (TimeoutError, httpx.TimeoutException, _Expired):
            if deadline.left() <= 0:
                raise RequestFailed(FailureKind.TIMEOUT, f"{deadline.why()}{_after(retries)}") from None
            last = _Retryable(FailureKind.TIMEOUT, f"no complete answer within {timeout_s:g} s")
        except httpx.TransportError as e:  # connect refused/reset, protocol errors
            last = _Retryable(FailureKind.CONNECTION, f"{type(e).__name__}: {e}")
        if retries == max_retries:
            break
        wait = min(backoff_max_s, backoff_base_s * 2**retries) * (0.5 + random.random() / 2)
        if last.wait is not None:  # Retry-After, honoured up to the cap
            wait = min(last.wait, retry_after_max_s)
        if wait >= deadline.left():  # the row would run out while waiting: it fails now
            break
        if on_retry is not None:
            on_retry(last.kind, last.detail)
        await asyncio.sleep(wait)
    assert last is not None
    raise RequestFailed(last.kind, f"{last.detail}{_after(retries)}")


class _Expired(Exception):
    """The row's deadline had passed before a request could be sent."""


def _after(retries: int) -> str:
    return f" (after {retries} retries)" if retries else ""
