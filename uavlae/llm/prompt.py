"""Prompt generator (paper §5.3.2, Fig. 3): three-part chain-of-thought prompt from one state.

Parts (a) task, (b) guidelines and (c) output format form the system message; it depends only
on the world limits and the ablation, so a server with prompt caching reuses its prefix for
every state. The current observation (the rest of part (a)) is the user message. Texts live in
``templates/``; every number comes from :class:`~uavlae.llm.state.WorldLimits` or the state.
"""

from __future__ import annotations

import math
from functools import lru_cache
from importlib import resources
from string import Template

from .state import AdvisorState, Rect, WorldLimits

ABLATIONS = {"none": None, "no_safety": "safety", "no_compliance": "compliance", "no_data": "data",
             "no_energy": "energy"}


@lru_cache(maxsize=None)
def template(name: str) -> str:
    return resources.files("uavlae.llm").joinpath("templates", name).read_text(encoding="utf-8")


def _num(v: float, nd: int = 1) -> str:
    if not math.isfinite(v):
        return "none"
    s = f"{v:.{nd}f}"
    return "0" if s.strip("-0.") == "" else s  # no "-0.0"


def _rect(r: Rect) -> str:
    return "(" + ",".join(_num(c, 0) for c in r) + ")"


def _rects(rs: tuple[Rect, ...]) -> str:
    return " ".join(_rect(r) for r in rs) if rs else "none"


def _compact(v: float) -> str:
    return _num(v, 0) if float(v).is_integer() else _num(v, 2)


def _limit_vars(lim: WorldLimits) -> dict[str, str]:
    return {
        "x_size": _compact(lim.x_size), "y_size": _compact(lim.y_size), "v_max": _compact(lim.v_max),
        "v_limit": _compact(lim.v_limit), "perception_radius": _compact(lim.perception_radius),
        "e_limit": _num(lim.e_limit, 0), "landing": _rect(lim.landing),
    }


def guidelines(lim: WorldLimits, ablation: str = "none") -> list[str]:
    """The reasoning guidelines left after ``ablation`` drops one of guidelines 1-4."""
    if ablation not in ABLATIONS:
        raise ValueError(f"prompt ablation must be one of {sorted(ABLATIONS)}, got {ablation!r}")
    drop = ABLATIONS[ablation]
    out = []
    for line in template("guidelines.txt").splitlines():
        if not line.strip() or line.startswith("#"):
            continue
        key, text = line.split(":", 1)
        if key.strip() != drop:
            out.append(Template(text.strip()).substitute(_limit_vars(lim)))
    return out


@lru_cache(maxsize=64)
def system_prompt(lim: WorldLimits, ablation: str = "none") -> str:
    lines = "\n".join(f"{i}) {g}" for i, g in enumerate(guidelines(lim, ablation), 1))
    return Template(template("system.txt")).substitute(_limit_vars(lim), guidelines=lines).strip()


def observation_prompt(s: AdvisorState) -> str:
    lim = s.limits
    ges = " ".join(f"({_num(g.x, 0)},{_num(g.y, 0)},{_num(g.remaining, 2)})" for g in s.ges) or "none"  # whole metres: fewer tokens
    ous = " ".join(f"({_num(o.x)},{_num(o.y)},{_num(o.vx)},{_num(o.vy)})" for o in s.ous) or "none"
    return Template(template("observation.txt")).substitute(
        _limit_vars(lim),
        x=_num(s.position[0]), y=_num(s.position[1]), vx=_num(s.velocity[0]), vy=_num(s.velocity[1]),
        energy_left=_num(s.energy_left, 0), in_rz=", inside an RZ" if s.in_rz else "",
        d_bz=_num(s.d_bz), d_nfz=_num(s.d_nfz), d_rz=_num(s.d_rz), d_ou=_num(s.d_ou),
        d_boundary=_num(s.d_boundary), d_la=_num(s.d_la),
        ges=ges, bz=_rects(s.bz), nfz=_rects(s.nfz), rz=_rects(s.rz), ous=ous,
    ).strip()


def build_messages(s: AdvisorState, ablation: str = "none") -> list[dict[str, str]]:
    """The chat messages for one state: system (parts a-c), user (the observation)."""
    return [
        {"role": "system", "content": system_prompt(s.limits, ablation)},
        {"role": "user", "content": observation_prompt(s)},
    ]


def retry_message(reason: str, lim: WorldLimits) -> dict[str, str]:
    """The ask-again turn. It quotes only our own rejection reason, never the model's text, so
    instructions smuggled into a bad answer do not reach the next prompt."""
    return {"role": "user",
            "content": Template(template("retry.txt")).substitute(_limit_vars(lim), reason=reason).strip()}
