"""The LLM advisor: states in, validated velocities or typed failures out.

``LLMAdvisor.advise(states)`` (async) sends one request per distinct prompt, all at once under
a concurrency limit; each runs the extractor's ask-again loop (paper: at most 10 attempts).
``advise_sync`` serves a plain training loop from one background event loop and one client;
``submit`` starts the same work there and returns a future at once (the loop runs its updates
while the requests are in flight).
The advisor never applies a fallback itself: an :class:`AdviceFailure` goes back to the
caller, and the override module applies its one setting, ``advisor.fallback``.

An endpoint that is down stops the run: after ``max_failed_rows`` rows in a row that the
endpoint did not answer (connection refused, 5xx or 429 after the retries, no answer within
``row_deadline_s``), every call raises one :class:`EndpointError` naming the endpoint and what
failed. A row that got answers, valid or not, shows the endpoint is up and resets the count.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import contextlib
import logging
import os
import threading
import time
from collections import Counter, OrderedDict, deque
from dataclasses import replace
from string import Template
from typing import Any, Sequence

import httpx

from .cache import AdviceCache, cache_key
from .client import BadResponse, PermanentFailure, RequestFailed, RowDeadline, chat_completion
from .config import LLMConfig, make_llm_config
from .extractor import extract_action
from .prompt import build_messages, episode_text, retry_message, template
from .schema import (Advice, AdviceFailure, CacheMissError, EndpointError, ExtractionError, FailureKind,
                     action_json_schema, answer_keys)
from .state import AdvisorState, rounded_state

log = logging.getLogger("uavlae.llm")


def action_grammar(cfg: LLMConfig) -> str:
    """The GBNF of ``response_format: grammar``: the file of ``grammar_style`` (auto: of the
    observation style) with the Reasoning's bound and the keys' order filled in."""
    style = cfg.observation if cfg.grammar_style == "auto" else cfg.grammar_style
    gbnf = "action_compact.gbnf" if style == "compact" else "action.gbnf"
    rule = {"vx": "vx", "vy": "vy", "Confidence": "confidence", "Reasoning": "reasoning"}
    fields = " sep ".join(rule[k] for k in answer_keys(cfg.reasoning_first))
    return Template(template(gbnf)).substitute(reasoning_max_chars=cfg.reasoning_max_chars, fields=fields)


class AdvisorStats:
    """Counters for the training logs; ``snapshot()`` gives flat ``{name: number}``."""

    def __init__(self, window: int = 4096):
        self._lock = threading.Lock()
        self._window = window
        self.reset()

    def reset(self) -> None:
        with getattr(self, "_lock", threading.Lock()):
            self.requests = 0  # advice asked for (states)
            self.calls = 0  # HTTP requests sent, retries included
            self.cache_hits = 0
            self.retries = 0  # transport retries (connect error, timeout, 429, 5xx)
            self.ask_again = 0  # extractor rejections followed by a new attempt
            self.advice_ok = 0
            self.failures: Counter[str] = Counter()  # final failures by kind
            self.rejected: Counter[str] = Counter()  # rejected answers by kind
            self.prompt_tokens = 0
            self.cached_prompt_tokens = 0  # of prompt_tokens, reused from the server's prefix cache
            self.completion_tokens = 0
            self.call_s = 0.0  # the answered calls' latencies, summed: the time spent on the LLM
            self.latencies: deque[float] = deque(maxlen=self._window)  # per answered HTTP call

    def __getstate__(self) -> dict:
        d = self.__dict__.copy()
        d.pop("_lock")
        return d

    def __setstate__(self, d: dict) -> None:
        self.__dict__.update(d)
        self._lock = threading.Lock()

    def add(self, **kw: int) -> None:
        with self._lock:
            for k, v in kw.items():
                setattr(self, k, getattr(self, k) + v)

    def snapshot(self, reset: bool = False) -> dict[str, float]:
        with self._lock:
            lat = sorted(self.latencies)

            def q(p: float) -> float:
                return lat[min(len(lat) - 1, int(p * len(lat)))] if lat else float("nan")

            out: dict[str, float] = {
                "requests": self.requests, "calls": self.calls, "cache_hits": self.cache_hits,
                "retries": self.retries, "ask_again": self.ask_again, "advice_ok": self.advice_ok,
                "failures": sum(self.failures.values()), "prompt_tokens": self.prompt_tokens,
                "cached_prompt_tokens": self.cached_prompt_tokens,
                "completion_tokens": self.completion_tokens, "call_s": self.call_s,
                "latency_p50_s": q(0.50), "latency_p95_s": q(0.95),
            }
            out.update({f"failures/{k}": v for k, v in sorted(self.failures.items())})
            out.update({f"rejected/{k}": v for k, v in sorted(self.rejected.items())})
        if reset:
            self.reset()
        return out


class LLMAdvisor:
    """See the module docstring. ``transport`` (tests) replaces the network layer of httpx."""

    def __init__(self, cfg: Any = None, *, base_url: str | None = None,
                 transport: httpx.AsyncBaseTransport | None = None):
        self.cfg: LLMConfig = make_llm_config(cfg)
        self._base_url = base_url
        self._transport = transport
        self.stats = AdvisorStats()
        self._cache = (AdviceCache(self.cfg.cache_path) if self.cfg.cache_mode != "off"
                       and self.cfg.cache_path else None)
        if self.cfg.cache_key_round and self._cache is not None:
            log.info("LLM advice cache keyed on the state's numbers rounded to %g (beyond the paper): "
                     "near-identical states share one answer", self.cfg.cache_key_round)
        self._init_lazy()

    # -- lifecycle ---------------------------------------------------------------------------
    def _init_lazy(self) -> None:
        self._client: httpx.AsyncClient | None = None
        self._client_loop: asyncio.AbstractEventLoop | None = None
        self._slots: asyncio.Semaphore | None = None
        self._loop: asyncio.AbstractEventLoop | None = None  # advise_sync's background loop
        self._thread: threading.Thread | None = None
        self._server_cm: contextlib.AbstractContextManager | None = None
        self._server_url: str | None = None
        self.local_server = None  # LocalServer (base_url, pid) when this advisor started one
        self._lock = threading.Lock()
        self._fatal: EndpointError | None = None  # a permanent endpoint fault: every later call raises it
        self._endpoint_ok = False  # has this endpoint ever answered with a chat completion?
        self._unanswered: list[tuple[FailureKind, str]] = []  # the rows in a row the endpoint did not answer
        # slot_affinity: episode (map) -> server slot, least recently used slot first to go
        self._slot_of: OrderedDict[str, int] = OrderedDict()
        self._slot_order: list[int] = []  # LRU first; filled from the server's /props
        self._n_slots: int | None = None  # the server's slot count; 0: no slot affinity there
        self._primed = False  # every slot holds the cached system prompt
        self.on_call: Any = None  # benchmarks: called with each ChatResult (server timings)

    def __getstate__(self) -> dict:
        """The client, loop, server and key never travel; a copy re-creates them lazily."""
        return {"cfg": self.cfg, "_base_url": self._base_url, "stats": self.stats, "_cache": self._cache}

    def __setstate__(self, d: dict) -> None:
        self.__dict__.update(d)
        self._transport = None
        self._init_lazy()

    def __repr__(self) -> str:
        return (f"LLMAdvisor(model={self.cfg.model!r}, base_url={self.base_url_or_none!r}, "
                f"cache_mode={self.cfg.cache_mode!r}, max_failed_rows={self.cfg.max_failed_rows!r})")

    def __enter__(self) -> "LLMAdvisor":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    def close(self) -> None:
        """Close the client, stop the background loop and any server this advisor started."""
        client, loop = self._client, self._client_loop
        self._client = None
        if client is not None and loop is not None and not loop.is_closed():
            if loop is self._loop and loop.is_running():
                with contextlib.suppress(Exception):
                    asyncio.run_coroutine_threadsafe(client.aclose(), loop).result(10)
        if self._loop is not None:
            self._loop.call_soon_threadsafe(self._loop.stop)
            if self._thread is not None:
                self._thread.join(10)
            with contextlib.suppress(Exception):
                self._loop.close()
            self._loop = self._thread = None
        self._n_slots, self._primed, self._slot_order = None, False, []
        self._slot_of.clear()
        if self._server_cm is not None:
            cm, self._server_cm, self._server_url, self.local_server = self._server_cm, None, None, None
            cm.__exit__(None, None, None)
        if self._cache is not None:
            self._cache.close()

    @property
    def base_url_or_none(self) -> str | None:
        return self._base_url or self.cfg.base_url or self._server_url

    def _resolve_base_url(self) -> str:
        url = self.base_url_or_none
        if url is not None:
            return url
        with self._lock:
            if self._server_url is None:  # base_url null + server.autostart: start the local one
                from .server import local_server

                cm = local_server(self.cfg.server)
                srv = cm.__enter__()
                self._server_cm, self._server_url, self.local_server = cm, srv.base_url, srv
                log.info("started local LLM server pid %d at %s", srv.pid, srv.base_url)
        return self._server_url  # type: ignore[return-value]

    def _api_key(self) -> str | None:
        name = self.cfg.api_key_env
        return (os.environ.get(name) or None) if name else None

    # -- before a run ----------------------------------------------------------------------
    def check_key(self) -> None:
        """Raise :class:`EndpointError` naming the variable when the endpoint needs a key
        (``llm.key_required``) and ``llm.api_key_env`` holds none: no request is sent."""
        c = self.cfg
        if c.key_required and not self._api_key():
            raise EndpointError(f"llm.api_key_env: the environment variable {c.api_key_env} is not set (or empty), and "
                                f"{c.base_url or 'the endpoint'} answers nobody without a key; export "
                                f"{c.api_key_env}=<your key> and run again")

    def preflight(self, state: AdvisorState) -> None:
        """One question before a run does any work: the key's variable (:meth:`check_key`), then
        ``state`` asked once of ``llm.base_url`` at the run's settings, one attempt with its
        transport retries. Any chat completion passes, valid action or not; a key it refuses, a
        URL that does not answer and a model it does not serve raise one :class:`EndpointError`
        naming the URL or the variable. Neither cached nor counted."""
        self.check_key()
        if self.base_url_or_none is None:
            return  # the local server: started up front (start), nothing to ask before
        asyncio.run_coroutine_threadsafe(self._preflight(state), self._background_loop()).result()

    async def _preflight(self, state: AdvisorState) -> None:
        c, url = self.cfg, self.base_url_or_none.rstrip("/") + "/chat/completions"  # type: ignore[union-attr]
        client, slots = self._http()
        headers = {"Content-Type": "application/json"}
        if self._api_key():
            headers["Authorization"] = f"Bearer {self._api_key()}"
        key_note = f" (key from ${c.api_key_env})" if c.api_key_env else ""
        try:
            await chat_completion(client, url, self._body(self._messages(state), state, 1), headers,
                                  timeout_s=c.timeout_s, max_retries=c.max_retries, backoff_base_s=c.backoff_base_s,
                                  backoff_max_s=c.backoff_max_s, retry_after_max_s=c.retry_after_max_s,
                                  max_response_bytes=c.max_response_bytes, slot=slots,
                                  deadline=RowDeadline(c.row_deadline_s))
        except PermanentFailure as e:
            self._set_fatal(url, e)
            raise self._fatal from None  # type: ignore[misc]
        except (RequestFailed, BadResponse) as e:
            raise EndpointError(f"LLM endpoint {url}{key_note} did not answer a first question before the run: "
                                f"{self._redact(str(e))[:200]}; check llm.base_url (and that the server runs), or "
                                "llm.timeout_s and llm.max_retries for a slow one") from None

    def start(self) -> str:
        """The endpoint's URL, starting the local server now when ``llm.base_url`` is null (not at
        the first request, where its start would count as a training step)."""
        return self._resolve_base_url()

    def _redact(self, text: str) -> str:
        key = self._api_key()
        return text.replace(key, "***") if key else text

    def _http(self) -> tuple[httpx.AsyncClient, asyncio.Semaphore]:
        loop = asyncio.get_running_loop()
        if self._client is None or self._client_loop is not loop:
            limits = httpx.Limits(max_connections=self.cfg.max_concurrency,
                                  max_keepalive_connections=self.cfg.max_concurrency)
            self._client = httpx.AsyncClient(transport=self._transport, limits=limits,
                                             follow_redirects=False, trust_env=False)
            self._client_loop = loop
            self._slots = asyncio.Semaphore(self.cfg.max_concurrency)
        return self._client, self._slots  # type: ignore[return-value]

    # -- request building ------------------------------------------------------------------
    async def _discover_slots(self, base_url: str) -> None:
        """How many slots the llama.cpp server has (``/props``); 0 (affinity off) when it does
        not say, e.g. a server that is not llama.cpp."""
        client, _ = self._http()
        root = base_url.rstrip("/").removesuffix("/v1")
        n = 0
        try:
            r = await client.get(f"{root}/props", timeout=30)
            if r.status_code == 200:
                n = int(r.json().get("total_slots") or 0)
        except (httpx.HTTPError, ValueError, TypeError, AttributeError):
            n = 0
        if n == 0:
            log.info("LLM server at %s does not report its slots: slot_affinity off", base_url)
        with self._lock:
            self._n_slots, self._slot_order = n, list(range(n))

    def _slot(self, state: AdvisorState) -> int | None:
        """The server slot for ``state`` (slot_affinity): the one that served its episode last,
        else the least recently used one, which forgets its previous episode."""
        if not self.cfg.slot_affinity or not self._n_slots:
            return None
        with self._lock:
            ep = episode_text(state)
            slot = self._slot_of.get(ep)
            if slot is None:
                slot = self._slot_order[0]
                for e in [e for e, s in self._slot_of.items() if s == slot]:
                    del self._slot_of[e]
                self._slot_of[ep] = slot
            self._slot_order.remove(slot)
            self._slot_order.append(slot)
            return slot

    async def _prime_slots(self, base_url: str, source: int) -> None:
        """Copy slot ``source``'s cache (the system prompt, just evaluated) into every other slot
        through llama.cpp's slot save/restore: a few ms each instead of evaluating the system
        prompt once per slot. A server without it (no slot save path) is left as it is."""
        self._primed = True
        n = self._n_slots or 0
        if n < 2:
            return
        client, _ = self._http()
        root = base_url.rstrip("/").removesuffix("/v1")
        name = f"uavlae-prefix-{os.getpid()}.bin"
        try:
            r = await client.post(f"{root}/slots/{source}?action=save", json={"filename": name}, timeout=30)
            if r.status_code != 200:
                raise httpx.HTTPError(f"HTTP {r.status_code}")
            for k in range(n):
                if k != source:
                    r = await client.post(f"{root}/slots/{k}?action=restore", json={"filename": name}, timeout=30)
                    if r.status_code != 200:
                        raise httpx.HTTPError(f"HTTP {r.status_code}")
        except httpx.HTTPError as e:
            log.info("LLM server slots not primed (%s): each slot evaluates the system prompt once", e)

    def _body(self, messages: list[dict], state: AdvisorState, attempt: int,
              slot: int | None = None) -> dict[str, Any]:
        c = self.cfg
        temperature = c.temperature
        if attempt > 1 and c.retry_temperature is not None:
            temperature = c.retry_temperature  # greedy decoding would repeat a rejected answer
        body: dict[str, Any] = {"model": c.model, "messages": messages, "temperature": temperature,
                                "top_p": c.top_p, "max_tokens": c.max_tokens, "stream": False}
        if c.seed is not None:
            body["seed"] = c.seed + attempt - 1
        if slot is not None:
            body["id_slot"] = slot  # llama.cpp: this slot's cache holds the episode's prefix
        v_max = state.limits.v_max
        if c.response_format == "json_schema":
            body["response_format"] = {"type": "json_schema", "json_schema": {
                "name": "uav_action", "strict": True,
                "schema": action_json_schema(v_max, c.reasoning_max_chars, c.reasoning_first)}}
        elif c.response_format == "json_object":
            body["response_format"] = {"type": "json_object"}
        elif c.response_format == "grammar":
            body["grammar"] = action_grammar(c)
        return body

    def request_body(self, state: AdvisorState) -> dict[str, Any]:
        """The first attempt's request body for ``state`` (benchmarks, debugging)."""
        return self._body(self._messages(state), state, 1, self._slot(state))

    def _messages(self, state: AdvisorState) -> list[dict]:
        c = self.cfg
        return build_messages(state, c.prompt_ablation, c.observation, c.reasoning_max_chars, c.example,
                              c.reasoning_first, c.view, c.view_radius)

    def _key(self, messages: list[dict], state: AdvisorState) -> str:
        c = self.cfg
        extra: dict[str, Any] = {"cache_key_round": c.cache_key_round} if c.cache_key_round else {}
        if c.grammar_style != "auto":  # not in the messages; keys of the default settings stay as they were
            extra["grammar_style"] = c.grammar_style
        if c.reasoning_first:
            extra["reasoning_first"] = True
        return cache_key({**extra, "model": c.model, "messages": messages, "temperature": c.temperature,
                          "top_p": c.top_p, "max_tokens": c.max_tokens, "seed": c.seed,
                          "response_format": c.response_format,
                          "reasoning_max_chars": c.reasoning_max_chars, "v_max": state.limits.v_max})

    # -- the main API ----------------------------------------------------------------------
    async def advise(self, states: Sequence[AdvisorState]) -> list[Advice | AdviceFailure]:
        """One result per state, in order. Raises CacheMissError on a miss in replay_only."""
        if not states:
            return []
        if self._fatal is not None:
            raise self._fatal
        self.stats.add(requests=len(states))
        prompts = [self._messages(s) for s in states]
        keys = [self._key(self._messages(rounded_state(s, self.cfg.cache_key_round))
                          if self.cfg.cache_key_round else m, s) for m, s in zip(prompts, states)]
        results: list[Advice | AdviceFailure | None] = [None] * len(states)
        todo: dict[str, list[int]] = {}
        for i, k in enumerate(keys):
            hit = self._cache.get(k) if self._cache is not None else None
            if hit is not None:
                results[i] = hit
                self.stats.add(cache_hits=1, advice_ok=1)
            else:
                todo.setdefault(k, []).append(i)  # identical prompts share one request
        if todo and self.cfg.cache_mode == "replay_only":
            n = sum(len(v) for v in todo.values())
            raise CacheMissError(f"replay_only: {n} of {len(states)} prompts are not in the cache "
                                 f"{self._cache.path if self._cache else None} (first key {next(iter(todo))})")
        if todo:
            base_url = await asyncio.to_thread(self._resolve_base_url) if self.base_url_or_none is None \
                else self.base_url_or_none
            url = base_url.rstrip("/") + "/chat/completions"
            uniq = list(todo.items())
            if self.cfg.slot_affinity and self._n_slots is None:
                await self._discover_slots(base_url)
            slots = [self._slot(states[idx[0]]) for _, idx in uniq]
            answers: list = []
            if self.cfg.slot_affinity and self._n_slots and not self._primed:
                # the first answer fills its slot with the system prompt; then every slot gets a copy
                k, idx = uniq[0]
                answers.append(await self._advise_one(url, prompts[idx[0]], states[idx[0]], k, slots[0]))
                if self._fatal is None:
                    await self._prime_slots(base_url, slots[0])
            answers += await asyncio.gather(*(self._advise_one(url, prompts[idx[0]], states[idx[0]], k, slot)
                                              for (k, idx), slot in list(zip(uniq, slots))[len(answers):]))
            if self._fatal is not None:
                raise self._fatal
            for (k, idx), a in zip(uniq, answers):
                for i in idx:
                    results[i] = a
        return results  # type: ignore[return-value]

    async def _advise_one(self, url: str, messages: list[dict], state: AdvisorState,
                          key: str, slot: int | None = None) -> Advice | AdviceFailure:
        c = self.cfg
        client, slots = self._http()
        headers = {"Content-Type": "application/json"}
        api_key = self._api_key()
        if api_key:
            headers["Authorization"] = f"Bearer {api_key}"
        history: list[FailureKind] = []
        t0 = time.perf_counter()
        current = messages
        clock = RowDeadline(c.row_deadline_s)
        answered = False  # did the endpoint answer this row at all (a valid action or not)?

        def on_retry(kind: FailureKind, detail: str) -> None:
            self.stats.add(retries=1, calls=1)
            log.debug("LLM request retry (%s): %s", kind.value, self._redact(detail))

        for attempt in range(1, c.max_attempts + 1):
            if self._fatal is not None:  # a sibling request met a permanent fault: stop asking
                return self._fail(FailureKind.HTTP_ERROR, "endpoint refused", attempt, history)
            if clock.left() <= 0:
                return self._row_failed(url, FailureKind.TIMEOUT, clock.why(), attempt - 1, history, answered)
            try:
                res = await chat_completion(
                    client, url, self._body(current, state, attempt, slot), headers, timeout_s=c.timeout_s,
                    max_retries=c.max_retries, backoff_base_s=c.backoff_base_s,
                    backoff_max_s=c.backoff_max_s, retry_after_max_s=c.retry_after_max_s,
                    max_response_bytes=c.max_response_bytes, slot=slots, on_retry=on_retry,
                    stop=lambda: self._fatal is not None, deadline=clock)
            except PermanentFailure as e:
                self.stats.add(calls=0 if e.status is None else 1)
                if e.status == 200 and self._endpoint_ok:  # it served chat completions before: a glitch
                    kind, reason = FailureKind.INVALID_JSON, e.detail
                    answered = True
                else:
                    self._set_fatal(url, e)
                    return self._fail(FailureKind.HTTP_ERROR, e.detail, attempt, history)
            except RequestFailed as e:
                self.stats.add(calls=1)
                return self._row_failed(url, e.kind, e.detail, attempt, history, answered)
            except BadResponse as e:
                self.stats.add(calls=1)
                kind, reason = e.kind, e.detail
                answered = True
            else:
                answered = True
                self._endpoint_ok = True
                if self.on_call is not None:
                    self.on_call(res)
                self.stats.add(calls=1, prompt_tokens=res.prompt_tokens, cached_prompt_tokens=res.cached_tokens,
                               completion_tokens=res.completion_tokens, call_s=res.latency_s)
                with self.stats._lock:
                    self.stats.latencies.append(res.latency_s)
                try:
                    advice = extract_action(res.text, state.limits.v_max, max_chars=c.max_response_bytes)
                except ExtractionError as e:
                    kind, reason = e.kind, e.detail
                    if res.finish_reason == "length" and kind in (
                            FailureKind.INVALID_JSON, FailureKind.NO_JSON, FailureKind.MISSING_KEYS):
                        kind, reason = FailureKind.TRUNCATED, "the answer was cut off at max_tokens"
                else:
                    advice = replace(advice, attempts=attempt, latency_s=time.perf_counter() - t0)
                    if self._cache is not None and c.cache_mode == "read_write":
                        self._cache.put(key, c.model, advice)
                    self.stats.add(advice_ok=1)
                    with self._lock:
                        self._unanswered.clear()
                    return advice
            history.append(kind)
            with self.stats._lock:
                self.stats.rejected[kind.value] += 1
            log.debug("LLM answer rejected (%s): %s", kind.value, self._redact(reason))
            if attempt < c.max_attempts:
                self.stats.add(ask_again=1)
                current = messages + [retry_message(reason, state.limits)]
        return self._row_failed(url, history[-1], f"no valid action in {c.max_attempts} attempts", c.max_attempts,
                                history, answered)

    def _row_failed(self, url: str, kind: FailureKind, detail: str, attempts: int, history: list[FailureKind],
                    answered: bool) -> AdviceFailure:
        """A row with no valid action. One the endpoint did not answer counts toward
        ``max_failed_rows``; one it answered (with bad actions) shows it is up."""
        failure = self._fail(kind, detail, attempts, history)
        limit = self.cfg.max_failed_rows
        with self._lock:
            if answered:
                self._unanswered.clear()
                return failure
            self._unanswered.append((kind, failure.detail))
            if limit is not None and len(self._unanswered) >= limit and self._fatal is None:
                self._fatal = EndpointError(self._outage(url))
        return failure

    def _outage(self, url: str) -> str:
        what = {FailureKind.CONNECTION: "could not connect", FailureKind.TIMEOUT: "no answer in time",
                FailureKind.SERVER_ERROR: "server error (5xx)", FailureKind.RATE_LIMITED: "rate limited (429)",
                FailureKind.HTTP_ERROR: "request refused (4xx)"}
        kinds = Counter(k for k, _ in self._unanswered)
        summary = ", ".join(f"{what.get(k, k.value)} x{n}" for k, n in kinds.most_common())
        n = len(self._unanswered)
        c = self.cfg
        key_note = f" (key from ${c.api_key_env})" if c.api_key_env else ""
        return (f"LLM endpoint {url}{key_note} left {n} rows in a row unanswered ({summary}); the last: "
                f"{self._redact(self._unanswered[-1][1])[:200]}. The run stops (llm.max_failed_rows={n}; "
                "null lets advisor.fallback act on every failed row instead)")

    def _set_fatal(self, url: str, e: PermanentFailure) -> None:
        if self._fatal is not None:
            return
        c = self.cfg
        if e.status in (401, 403):
            why = (f"rejected the API key (HTTP {e.status}); set a valid key in the environment variable "
                   f"{c.api_key_env}" if c.api_key_env else
                   f"needs an API key (HTTP {e.status}); name its environment variable in llm.api_key_env")
        elif e.status == 200:
            why = "is not an OpenAI-compatible server (its answer is not a chat completion); check llm.base_url"
        else:
            why = (f"does not serve model {c.model!r} at /chat/completions (HTTP {e.status}); "
                   "check llm.base_url and llm.model")
        key_note = f" (key from ${c.api_key_env})" if c.api_key_env else ""
        self._fatal = EndpointError(f"LLM endpoint {url}{key_note} {why}. Server said: "
                                    f"{self._redact(e.detail)[:200]}")

    def _fail(self, kind: FailureKind, detail: str, attempts: int,
              history: list[FailureKind]) -> AdviceFailure:
        # logged once per step by the caller, with the fallback setting that acts, or ended by
        # the EndpointError's one message
        with self.stats._lock:
            self.stats.failures[kind.value] += 1
        detail = self._redact(detail)
        log.debug("LLM advice failed (%s) after %d attempt(s): %s", kind.value, attempts, detail)
        return AdviceFailure(kind=kind, detail=detail, attempts=attempts, history=tuple(history))

    # -- sync wrapper for a plain training loop ---------------------------------------------
    def _background_loop(self) -> asyncio.AbstractEventLoop:
        with self._lock:
            if self._loop is None:
                loop = asyncio.new_event_loop()
                t = threading.Thread(target=loop.run_forever, name="uavlae-llm-loop", daemon=True)
                t.start()
                self._loop, self._thread = loop, t
        return self._loop

    def submit(self, states: Sequence[AdvisorState]) -> concurrent.futures.Future:
        """:meth:`advise` started on the background loop; returns at once. The requests are in
        flight while the caller works; ``future.result(timeout)`` gives the answers."""
        return asyncio.run_coroutine_threadsafe(self.advise(list(states)), self._background_loop())

    def advise_sync(self, states: Sequence[AdvisorState], timeout: float | None = None
                    ) -> list[Advice | AdviceFailure]:
        """Blocking :meth:`advise`, on one long-lived background loop (safe inside Jupyter too)."""
        if not states:
            return []
        return self.submit(states).result(timeout)
