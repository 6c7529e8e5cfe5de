"""LLM advisor (paper §5.3): prompt generator, extractor, OpenAI-compatible client, cache and a
local llama.cpp server. Imports nothing else of uavlae; see README.md in this folder."""

from .advisor import AdvisorStats, LLMAdvisor
from .cache import AdviceCache, cache_key
from .config import LLMConfig, ServerConfig, make_llm_config
from .extractor import extract_action
from .prompt import build_messages, observation_prompt, system_prompt
from .schema import Advice, AdviceFailure, CacheMissError, EndpointError, ExtractionError, FailureKind
from .state import (AdvisorState, GroundEquipment, OtherUAV, WorldLimits, advisor_states_from_tensordict,
                    example_states, rounded_state)

__all__ = [
    "Advice", "AdviceCache", "AdviceFailure", "AdvisorState", "AdvisorStats", "CacheMissError",
    "EndpointError", "ExtractionError", "FailureKind", "GroundEquipment", "LLMAdvisor", "LLMConfig", "OtherUAV",
    "ServerConfig", "WorldLimits", "advisor_states_from_tensordict", "example_states", "build_messages", "cache_key",
    "extract_action", "make_llm_config", "observation_prompt", "rounded_state", "system_prompt",
]
