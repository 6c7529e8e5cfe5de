"""Prompt generator (paper §5.3.2, Fig. 3): three-part chain-of-thought prompt from one state.

Parts (a) task, (b) guidelines and (c) output format form the system message; it depends only
on the world limits, the ablation and the output style, so a server with prompt caching reuses
it as a prefix for every state. The current observation (the rest of part (a)) is the user
message, in one of two styles:

- ``compact`` (default): only what the paper's prompt lists (DCU position and velocity, GEs
  with their remaining data, the zones, the visible OUs) at the precision that matters (whole
  metres, 0.1 m/s, 0.1 data units), ordered from what never changes within an episode (the
  landing area, the zones) through what changes slowly (the GEs' remaining data) to what
  changes every slot (OUs, the DCU), so consecutive calls for the same row share all but the
  last lines as an exact cached prefix.
- ``verbose``: the earlier observation, which also quotes the energy left and the distances to
  the nearest obstacle of each kind.

Part (c) shows an example answer (``example``): the paper's numbers, a placeholder that gives
only the format, or none (the keys are named); ``reasoning_first`` orders the answer Reasoning,
vx, vy, Confidence, so the velocity is decoded after the bounded Reasoning. Each choice is fixed
for a run, so the system message stays one exact prefix.

``view="local"`` (the LLM-alone baseline, paper §6.1) shows the state as the extraction left it
(:func:`~uavlae.llm.state.advisor_states_from_tensordict` with ``view_radius``: the zones and
OUs within that radius, every GE); the compact style then uses ``observation_local.txt``, which
says so and adds the energy left of E_limit, and part (a) names the energy among the DCU state.

Texts live in ``templates/``; every number comes from :class:`~uavlae.llm.state.WorldLimits`
or the state.
"""

from __future__ import annotations

import math
from functools import lru_cache
from importlib import resources
from string import Template

from .schema import answer_keys
from .state import AdvisorState, Rect, WorldLimits

OBSERVATIONS = ("compact", "verbose")
VIEWS = ("full", "local")
EXAMPLE_KINDS = ("paper", "placeholder", "none")
# part (c)'s example answer, field by field: the paper's numbers (and the compact style's short
# Reasoning), or a placeholder that shows only the format. A small model copies a numeric
# example into most answers (benchmarks/advice_quality.md), hence the other two kinds.
PAPER_EXAMPLE_VELOCITY = (4.2, 1.6)  # (vx, vy) of the paper's example answer, m/s
_VX, _VY = (str(v) for v in PAPER_EXAMPLE_VELOCITY)
_EXAMPLE_FIELDS = {
    ("paper", "verbose"): {"vx": _VX, "vy": _VY, "Confidence": "0.86",
                           "Reasoning": '"Moves toward GE with remaining data, avoids NFZ/OUs/buildings, and respects RZ."'},
    ("paper", "compact"): {"vx": _VX, "vy": _VY, "Confidence": "0.9", "Reasoning": '"toward GE, clear of zones"'},
    ("placeholder", "verbose"): {"vx": "<number>", "vy": "<number>", "Confidence": "<number>", "Reasoning": '"<text>"'},
}
_EXAMPLE_FIELDS[("placeholder", "compact")] = _EXAMPLE_FIELDS[("placeholder", "verbose")]
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


def _check_style(observation: str) -> None:
    if observation not in OBSERVATIONS:
        raise ValueError(f"prompt observation style must be one of {list(OBSERVATIONS)}, got {observation!r}")


def example_answer(observation: str = "compact", example: str = "paper", reasoning_first: bool = False) -> str:
    """Part (c)'s example answer, spaced as the observation style's grammar writes it."""
    _check_style(observation)
    if example not in EXAMPLE_KINDS:
        raise ValueError(f"prompt example must be one of {list(EXAMPLE_KINDS)}, got {example!r}")
    if example == "none":
        return ""
    fields = _EXAMPLE_FIELDS[(example, observation)]
    sep = ", " if observation == "verbose" else ","
    colon = ": " if observation == "verbose" else ":"
    return "{" + sep.join(f'"{k}"{colon}{fields[k]}' for k in answer_keys(reasoning_first)) + "}"


def _check_view(view: str) -> None:
    if view not in VIEWS:
        raise ValueError(f"prompt view must be one of {list(VIEWS)}, got {view!r}")


@lru_cache(maxsize=64)
def system_prompt(lim: WorldLimits, ablation: str = "none", observation: str = "compact",
                  reasoning_max_chars: int = 40, example: str = "paper", reasoning_first: bool = False,
                  view: str = "full", view_radius: float = 20.0) -> str:
    """Parts (a)-(c). The compact style states the Reasoning bound (its answers are cut there);
    without an example (``example="none"``) part (c) names the keys in their order instead.
    The local view quotes the OUs' radius as the smaller of it and the perception radius and
    names the energy left of E_limit among the DCU state."""
    _check_style(observation)
    _check_view(view)
    lines = "\n".join(f"{i}) {g}" for i, g in enumerate(guidelines(lim, ablation), 1))
    bound = f" (Reasoning at most {reasoning_max_chars} characters)" if observation == "compact" else ""
    answer = example_answer(observation, example, reasoning_first)
    lead = {"paper": ", for example:\n", "placeholder": ", in this form:\n"}.get(example)
    shown = (lead + answer if lead else " with the keys " + ", ".join(answer_keys(reasoning_first)) + " in this order.")
    dcu_state = "position, velocity" if observation == "compact" else "position, velocity, energy left"
    limits = _limit_vars(lim)
    if view == "local":
        dcu_state = f"position, velocity, energy left of the energy budget E_limit = {limits['e_limit']} J"
        limits["perception_radius"] = _compact(min(lim.perception_radius, view_radius))
    return Template(template("system.txt")).substitute(
        limits, guidelines=lines, reasoning_bound=bound, example=shown, dcu_state=dcu_state).strip()


def visible_ou_distance(s: AdvisorState) -> float:
    """Distance to the nearest OU within the perception radius (inf: none visible). The env's
    own ``d_ou`` counts every OU (it feeds reward r2); the prompt quotes only what the DCU sees."""
    pr = s.limits.perception_radius
    return min((o.distance for o in s.ous if o.distance <= pr), default=math.inf)


def compact_observation_prompt(s: AdvisorState) -> str:
    """The compact observation (module docstring): static lines first, the DCU's last."""
    ges = " ".join(f"({_num(g.x, 0)},{_num(g.y, 0)},{_num(g.remaining, 1)})" for g in s.ges) or "none"
    pr = s.limits.perception_radius
    ous = " ".join(f"({_num(o.x, 0)},{_num(o.y, 0)},{_num(o.vx)},{_num(o.vy)})"
                   for o in s.ous if o.distance <= pr) or "none"
    return Template(template("observation_compact.txt")).substitute(
        landing=_rect(s.limits.landing), bz=_rects(s.bz), nfz=_rects(s.nfz), rz=_rects(s.rz),
        ges=ges, ous=ous, x=_num(s.position[0], 0), y=_num(s.position[1], 0),
        vx=_num(s.velocity[0]), vy=_num(s.velocity[1]), in_rz=", inside an RZ" if s.in_rz else "",
    ).strip()


def local_observation_prompt(s: AdvisorState, view_radius: float) -> str:
    """The compact observation of the local view: the zones and OUs in view (the extraction
    filtered them), every GE, the energy left of E_limit on the DCU's line."""
    ges = " ".join(f"({_num(g.x, 0)},{_num(g.y, 0)},{_num(g.remaining, 1)})" for g in s.ges) or "none"
    r = min(s.limits.perception_radius, view_radius)
    ous = " ".join(f"({_num(o.x, 0)},{_num(o.y, 0)},{_num(o.vx)},{_num(o.vy)})"
                   for o in s.ous if o.distance <= r) or "none"
    return Template(template("observation_local.txt")).substitute(
        landing=_rect(s.limits.landing), view_radius=_compact(view_radius), bz=_rects(s.bz), nfz=_rects(s.nfz),
        rz=_rects(s.rz), ges=ges, ous=ous, x=_num(s.position[0], 0), y=_num(s.position[1], 0),
        vx=_num(s.velocity[0]), vy=_num(s.velocity[1]), energy_left=_num(s.energy_left, 0),
        e_limit=_num(s.limits.e_limit, 0), in_rz=", inside an RZ" if s.in_rz else "",
    ).strip()


def observation_prompt(s: AdvisorState, observation: str = "compact", view: str = "full",
                       view_radius: float = 20.0) -> str:
    _check_style(observation)
    _check_view(view)
    if observation == "compact":
        return local_observation_prompt(s, view_radius) if view == "local" else compact_observation_prompt(s)
    lim = s.limits
    ges = " ".join(f"({_num(g.x, 0)},{_num(g.y, 0)},{_num(g.remaining, 2)})" for g in s.ges) or "none"  # whole metres: fewer tokens
    ous = " ".join(f"({_num(o.x)},{_num(o.y)},{_num(o.vx)},{_num(o.vy)})" for o in s.ous
                   if o.distance <= lim.perception_radius) or "none"
    return Template(template("observation.txt")).substitute(
        _limit_vars(lim),
        x=_num(s.position[0]), y=_num(s.position[1]), vx=_num(s.velocity[0]), vy=_num(s.velocity[1]),
        energy_left=_num(s.energy_left, 0), in_rz=", inside an RZ" if s.in_rz else "",
        d_bz=_num(s.d_bz), d_nfz=_num(s.d_nfz), d_rz=_num(s.d_rz), d_ou=_num(visible_ou_distance(s)),
        d_boundary=_num(s.d_boundary), d_la=_num(s.d_la),
        ges=ges, bz=_rects(s.bz), nfz=_rects(s.nfz), rz=_rects(s.rz), ous=ous,
    ).strip()


def episode_text(s: AdvisorState) -> str:
    """What identifies a state's episode for the server's slots: its map (the zones; the whole
    map when the state shows only the zones in view)."""
    return s.episode or f"{_rects(s.bz)}|{_rects(s.nfz)}|{_rects(s.rz)}"


def build_messages(s: AdvisorState, ablation: str = "none", observation: str = "compact",
                   reasoning_max_chars: int = 40, example: str = "paper",
                   reasoning_first: bool = False, view: str = "full",
                   view_radius: float = 20.0) -> list[dict[str, str]]:
    """The chat messages for one state: system (parts a-c), user (the observation)."""
    return [
        {"role": "system", "content": system_prompt(s.limits, ablation, observation, reasoning_max_chars,
                                                    example, reasoning_first, view, float(view_radius))},
        {"role": "user", "content": observation_prompt(s, observation, view, view_radius)},
    ]


def retry_message(reason: str, lim: WorldLimits) -> dict[str, str]:
    """The ask-again turn. It quotes only our own rejection reason, never the model's text, so
    instructions smuggled into a bad answer do not reach the next prompt."""
    return {"role": "user",
            "content": Template(template("retry.txt")).substitute(_limit_vars(lim), reason=reason).strip()}
