"""uavlae: safe, compliant and economical UAV trajectory planning in low-altitude airspace."""

import os

from omegaconf import OmegaConf


def _unique_token() -> str:
    """Six hex digits drawn once per config (cached): default run folders made in the same
    second still differ."""
    return os.urandom(3).hex()


if not OmegaConf.has_resolver("uavlae.unique"):
    OmegaConf.register_new_resolver("uavlae.unique", _unique_token, use_cache=True)
