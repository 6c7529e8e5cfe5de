"""Which of a run's evaluations is its best: the score ``trainer.keep_best`` keeps the highest of,
and the pilot study's "best on the way" column reads. Plain Python, so a report imports it
without the training stack."""

from __future__ import annotations

import math
from collections.abc import Mapping

__all__ = ["selection_score"]


def selection_score(metrics: Mapping[str, float]) -> float:
    """DCR + SLR - CR - RVR of an evaluation (each in [0, 1]; a missing or NaN one scores -inf).
    **[decision]** the task done and the rules kept weigh alike; ECR is left out, being on no
    common scale with them."""
    parts = [metrics.get(k, math.nan) for k in ("DCR", "SLR", "CR", "RVR")]
    if any(not math.isfinite(float(v)) for v in parts):
        return -math.inf
    dcr, slr, cr, rvr = (float(v) for v in parts)
    return dcr + slr - cr - rvr
