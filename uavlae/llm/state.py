"""Plain data the prompt generator reads: one batch element's raw state and the world limits.

Nothing here imports the rest of uavlae. :func:`advisor_states_from_tensordict` reads the env's
raw ``("state", NAME)`` entries (docs/env_contract.md) with torch/tensordict only, so this
package can be tested on a hand-built TensorDict before, and independently of, the env.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Sequence

Rect = tuple[float, float, float, float]  # (x0, y0, x1, y1): south-west and north-east corners


@dataclass(frozen=True)
class WorldLimits:
    """The env-config numbers the prompt quotes (never hard-coded in a template)."""

    x_size: float
    y_size: float
    v_max: float
    v_limit: float
    perception_radius: float
    landing: Rect
    e_limit: float

    @classmethod
    def from_env_config(cls, cfg: Any) -> "WorldLimits":
        """Read an ``EnvConfig`` (or anything shaped like it) by attribute, without importing it."""
        return cls(
            x_size=float(cfg.area.x_size),
            y_size=float(cfg.area.y_size),
            v_max=float(cfg.motion.v_max),
            v_limit=float(cfg.motion.v_limit),
            perception_radius=float(cfg.safety.perception_radius),
            landing=tuple(float(v) for v in cfg.area.landing),  # type: ignore[arg-type]
            e_limit=float(cfg.energy.e_limit),
        )


@dataclass(frozen=True)
class GroundEquipment:
    x: float
    y: float
    remaining: float  # data still to collect


@dataclass(frozen=True)
class OtherUAV:
    x: float
    y: float
    vx: float
    vy: float
    distance: float


@dataclass(frozen=True)
class AdvisorState:
    """One batch element, unnormalised. Distances are to the nearest of each kind (inf: none)."""

    position: tuple[float, float]
    velocity: tuple[float, float]
    energy_left: float
    limits: WorldLimits
    ges: tuple[GroundEquipment, ...] = ()  # only GEs with remaining data
    nfz: tuple[Rect, ...] = ()
    rz: tuple[Rect, ...] = ()
    bz: tuple[Rect, ...] = ()
    ous: tuple[OtherUAV, ...] = ()  # only OUs within the perception radius, nearest first
    d_bz: float = math.inf
    d_nfz: float = math.inf
    d_rz: float = math.inf
    d_ou: float = math.inf
    d_boundary: float = math.inf
    d_la: float = math.inf
    extra: dict[str, float] = field(default_factory=dict)  # free slot for callers; not in the prompt
    # the episode's whole map when the zones above are only the ones in view (view_radius):
    # the server slot of the episode is chosen by it, not by what happens to be in view
    episode: str = ""

    @property
    def in_rz(self) -> bool:
        x, y = self.position
        return any(r[0] <= x <= r[2] and r[1] <= y <= r[3] for r in self.rz)


_DISTANCES = ("d_bz", "d_nfz", "d_rz", "d_ou", "d_boundary", "d_la")


def rect_distance(r: Rect, x: float, y: float) -> float:
    """Distance (m) from the point (x, y) to the rectangle ``r`` (0 inside or on it)."""
    dx = max(r[0] - x, 0.0, x - r[2])
    dy = max(r[1] - y, 0.0, y - r[3])
    return math.hypot(dx, dy)


def _rows(td: Any, idx: Any) -> list[int]:
    import torch

    if isinstance(idx, torch.Tensor):
        if idx.dtype == torch.bool:
            return [int(i) for i in idx.reshape(-1).nonzero().reshape(-1).tolist()]
        return [int(i) for i in idx.reshape(-1).tolist()]
    if isinstance(idx, int):
        return [idx]
    return [int(i) for i in idx]


def advisor_states_from_tensordict(
    td: Any, idx: Sequence[int] | Any, limits: WorldLimits, *, ge_eps: float = 1e-9,
    view_radius: float | None = None,
) -> list[AdvisorState]:
    """Build one :class:`AdvisorState` per selected row of a ``[B]`` tensordict.

    ``td`` holds the ``("state", NAME)`` entries of the env contract (the root after reset, or
    ``td["next"]`` after a step). ``idx`` is a list of row indices or a ``[B]`` bool mask.
    OUs are kept only within ``limits.perception_radius`` (nearest first); GEs only with
    remaining data > ``ge_eps``; zones only where their mask is set.

    ``view_radius`` (m; the LLM-alone view, ``LLMConfig.view="local"``): only the zones of
    which some part lies within it of the DCU (each as its whole rectangle) and only the OUs
    within it (and within the perception radius); every GE stays; a nearest distance to a zone
    or OU beyond it reads inf. The state's ``episode`` then names the whole map.
    """
    rows = _rows(td, idx)
    if not rows:
        return []
    import torch

    sel = torch.as_tensor(rows, dtype=torch.long)
    s = td.get("state")

    def take(name: str) -> list:
        return s.get(name).detach()[sel.to(s.get(name).device)].cpu().tolist()

    pos, vel, energy = take("position"), take("velocity"), take("energy_left")
    ge_pos, ge_rem, ge_mask = take("ge_pos"), take("ge_remaining"), take("ge_mask")
    ou_pos, ou_vel, ou_mask = take("ou_pos"), take("ou_vel"), take("ou_mask")
    zones = {k: (take(k), take(f"{k}_mask")) for k in ("nfz", "rz", "bz")}
    dists = {k: take(k) for k in _DISTANCES}
    pr = limits.perception_radius if view_radius is None else min(limits.perception_radius, float(view_radius))

    out = []
    for j in range(len(rows)):
        x, y = float(pos[j][0]), float(pos[j][1])
        ges = tuple(
            GroundEquipment(float(p[0]), float(p[1]), float(r))
            for p, r, m in zip(ge_pos[j], ge_rem[j], ge_mask[j])
            if m and r > ge_eps
        )
        ous = []
        for p, v, m in zip(ou_pos[j], ou_vel[j], ou_mask[j]):
            if not m:
                continue
            d = math.hypot(p[0] - x, p[1] - y)
            if d <= pr:
                ous.append(OtherUAV(float(p[0]), float(p[1]), float(v[0]), float(v[1]), d))
        ous.sort(key=lambda o: o.distance)
        rects = {
            k: tuple(tuple(float(c) for c in r) for r, m in zip(rects[j], masks[j]) if m)
            for k, (rects, masks) in zones.items()
        }
        episode = ""
        d = {k: float(dists[k][j]) for k in _DISTANCES}
        if view_radius is not None:
            episode = "|".join(" ".join(map(str, rects[k])) for k in ("bz", "nfz", "rz"))
            rects = {k: tuple(r for r in rs if rect_distance(r, x, y) <= view_radius) for k, rs in rects.items()}
            # a nearest distance beyond the view would tell of what is out of it
            d.update({k: math.inf for k in ("d_bz", "d_nfz", "d_rz", "d_ou") if d[k] > view_radius})
        out.append(
            AdvisorState(
                position=(x, y),
                velocity=(float(vel[j][0]), float(vel[j][1])),
                energy_left=float(energy[j]),
                limits=limits,
                ges=ges,
                nfz=rects["nfz"],  # type: ignore[arg-type]
                rz=rects["rz"],  # type: ignore[arg-type]
                bz=rects["bz"],  # type: ignore[arg-type]
                ous=tuple(ous),
                **d,
                episode=episode,
            )
        )
    return out


def example_states(n: int, limits: WorldLimits, seed: int = 0) -> list[AdvisorState]:
    """``n`` distinct, plausible states (benchmarks, tests, demos); not the env's distribution."""
    import random

    rng = random.Random(seed)
    X, Y, pr = limits.x_size, limits.y_size, limits.perception_radius

    def rect() -> Rect:
        w, h = rng.uniform(0.1, 0.4) * X, rng.uniform(0.1, 0.4) * Y
        x0, y0 = rng.uniform(0, X - w), rng.uniform(0, Y - h)
        return (round(x0, 1), round(y0, 1), round(x0 + w, 1), round(y0 + h, 1))

    out = []
    for _ in range(n):
        x, y = rng.uniform(0, X), rng.uniform(0, Y)
        ous = []
        for _ in range(rng.randint(0, 2)):
            a, d = rng.uniform(0, 6.283), rng.uniform(2, pr)
            ous.append(OtherUAV(x + d * math.cos(a), y + d * math.sin(a), rng.uniform(-3, 3),
                                rng.uniform(-3, 3), d))
        ous.sort(key=lambda o: o.distance)
        out.append(AdvisorState(
            position=(x, y), velocity=(rng.uniform(-3, 3), rng.uniform(-3, 3)),
            energy_left=rng.uniform(0.2, 1.0) * limits.e_limit, limits=limits,
            ges=tuple(GroundEquipment(rng.uniform(0, X), rng.uniform(0, Y), rng.uniform(0.1, 3))
                      for _ in range(rng.randint(3, 12))),
            nfz=tuple(rect() for _ in range(rng.randint(1, 3))),
            rz=tuple(rect() for _ in range(rng.randint(1, 3))),
            bz=tuple(rect() for _ in range(rng.randint(1, 3))),
            ous=tuple(ous), d_bz=rng.uniform(0, 60), d_nfz=rng.uniform(0, 60), d_rz=rng.uniform(0, 60),
            d_ou=ous[0].distance if ous else math.inf, d_boundary=min(x, y, X - x, Y - y),
            d_la=math.hypot(x - (limits.landing[0] + limits.landing[2]) / 2,
                            y - (limits.landing[1] + limits.landing[3]) / 2),
        ))
    return out


def rounded_state(s: AdvisorState, step: float | None) -> AdvisorState:
    """``s`` with every number the prompt quotes rounded to a multiple of ``step`` (positions
    and zone corners in m, velocities in m/s, remaining data, energy and distances): the
    rounded cache key (``LLMConfig.cache_key_round``). ``None``: ``s`` itself."""
    if not step:
        return s

    def r(v: float) -> float:
        return v if not math.isfinite(v) else round(v / step) * step + 0.0  # + 0.0: no -0.0

    def rects(rs: tuple[Rect, ...]) -> tuple[Rect, ...]:
        return tuple(tuple(r(c) for c in q) for q in rs)  # type: ignore[misc]

    return AdvisorState(
        position=(r(s.position[0]), r(s.position[1])), velocity=(r(s.velocity[0]), r(s.velocity[1])),
        energy_left=r(s.energy_left), limits=s.limits,
        ges=tuple(GroundEquipment(r(g.x), r(g.y), r(g.remaining)) for g in s.ges),
        nfz=rects(s.nfz), rz=rects(s.rz), bz=rects(s.bz),
        ous=tuple(OtherUAV(r(o.x), r(o.y), r(o.vx), r(o.vy), o.distance) for o in s.ous),
        **{k: r(getattr(s, k)) for k in _DISTANCES}, episode=s.episode,
    )
