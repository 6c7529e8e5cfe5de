"""The safety filter, beyond the paper: the executed velocity, changed as little as it can be so
that the coming slot keeps the rules (docs/model.md §10, "The safety filter").

Whatever acts (the actor, an advisor under the override, the random warm-up) proposes a velocity
``v_wish``; the filter screens a fixed set of candidate velocities around it against what the DCU
perceives, and executes the admissible candidate nearest to the wish. Over the flight phase
L_t -> L_t + v t_fly of the coming slot, a candidate is admissible when:

- **BZ / NFZ**: the segment keeps at least ``m = min(filter_clearance, d_now - 1 mm)`` from every
  building and no-fly zone (``d_now``: the DCU's distance to that rectangle now), and its end is
  no nearer to any of them than ``min(filter_clearance, d_now)``: a DCU already inside the
  clearance never gets nearer;
- **boundary**: its end lies at least ``min(boundary_margin, d_boundary_now)`` inside the area
  (the area is convex, so the whole segment does);
- **RZ**: a segment that touches an RZ inflated by ``rz_inflate`` flies at most
  ``rz_speed_margin * v_limit``; every candidate is capped so before it is tested;
- **OUs**: for every OU within the perception radius, the closest approach over the flight
  phase, the OU keeping its velocity of the last slot, is at least ``min(ou_safety_distance,
  d_now)`` (*OU-safe*), and where it can be, the DCU also keeps ``r_coll + ou_robust_margin`` from
  every point such an OU could reach at any speed up to v_max (*turn-proof*, sampled at
  ``ou_robust_samples`` instants).

The pick: the turn-proof OU-safe feasible candidate nearest the wish; else the OU-safe feasible
one nearest the wish; else the feasible one with the largest predicted closest approach.
Hovering is always feasible (its segment is a point at the current distances), so the static
rules (BZ, NFZ, boundary, RZ speed) hold by construction whatever is proposed; the OU rule holds
only under its assumption (docs/model.md §10 states the guarantee exactly).

The same screen serves the global planner's own filter (:mod:`uavlae.policies.heuristic`), which
tests a short candidate list first and the ring only where the first fails. The filter here tests
every candidate for every row with no data-dependent branch, so it is one fixed graph:
``torch.export`` carries it inside the exported pilot (:mod:`uavlae.export`).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, Literal, Protocol

import torch
from pydantic import Field
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torch import Tensor, nn

from uavlae.envs import physics as ph
from uavlae.envs.config import EnvConfig, make_env_config
from uavlae.validation import StrictModel, parse_model

EPS = 1e-3  # metres: keeps a point strictly outside the rectangle it is measured from

# the raw state entries the filter reads (docs/env_contract.md): the DCU, the static map, the OUs
STATE_KEYS = ("position", "ou_pos", "ou_vel", "ou_mask", "nfz", "nfz_mask", "rz", "rz_mask", "bz", "bz_mask")
MODES = ("off", "train_and_deploy", "deploy")


class SafetyFilterConfig(StrictModel):
    """``conf/safety_filter/default.yaml`` mirrors it one-to-one."""

    # off: nothing filtered; train_and_deploy: every executed action in training and the
    # evaluated / exported pilot; deploy: the evaluated / exported pilot only
    mode: Literal["off", "train_and_deploy", "deploy"] = "off"
    filter_clearance: float = Field(1.0, ge=0)  # m the segment keeps from BZ/NFZ (less when already nearer)
    boundary_margin: float = Field(1.0, ge=0)  # m every step ends inside the area
    rz_speed_margin: float = Field(0.95, gt=0, lt=1)  # |v| <= margin * v_limit on a segment touching an RZ
    rz_inflate: float = Field(1.0, ge=0)  # m the RZs are inflated by for that test
    ou_safety_distance: float = Field(5.0, gt=0)  # m of predicted closest approach to a perceived OU
    ou_robust_margin: float = Field(1.0, ge=0)  # m on top of r_coll for the turn-proof test
    ou_robust_samples: int = Field(5, ge=2, le=64)  # instants of the flight phase for that test
    # the candidates: the wish shortened by these factors, its x and y parts (a slide along an
    # axis-aligned wall) at the same factors, a ring of headings at these speeds, and hovering
    wish_fractions: tuple[float, ...] = (0.75, 0.5, 0.25, 0.1)
    headings: int = Field(16, ge=4, le=256)
    ring_speeds: tuple[float, ...] = (1.0, 0.5, 0.25)  # fractions of v_max
    # training only: reward minus penalty * |v_executed - v_wish| / v_max, so the actor learns not
    # to lean on the filter (0: the reward is the env's)
    penalty: float = Field(0.0, ge=0)
    # training only: the action a transition stores. executed: the filtered one (the critic never
    # sees an unsafe action, so a penalty lands on the corrected action); proposed: the wish, the
    # filter being part of the dynamics, so the critic prices the wish with its correction
    learn_from: Literal["executed", "proposed"] = "executed"
    # training only: the cost of a learner that constrains one (sac_lag, ppo_lagrangian, cpo) gains
    # cost * |v_executed - v_wish| / v_max, so its limit bounds how much the filter corrects
    cost: float = Field(0.0, ge=0)
    # beyond the filter's safety role, the pilot's speed rule: the wish flown in its direction at
    # v_max (a wish under CRUISE_FLOOR m/s, asking to hover, as it is) before the screen, as
    # P(v) falls from P(0) = 168 W to P(v_max) = 126 W (docs/model.md §4); the intervention counts
    # and prices are against that command. False: the wish as the actor sent it
    cruise: bool = False


# m/s: a wish slower than this asks to hover, and cruise leaves it as it is
CRUISE_FLOOR = 0.5


def cruise_action(action: Tensor, v_max: float) -> Tensor:
    """The action ``[..., 2]`` in its direction at ``v_max`` (|a| = 1 in the env's units) where
    its velocity (docs/model.md §2) is at least :data:`CRUISE_FLOOR` m/s, else as it is."""
    v = ph.action_to_velocity(action, v_max)
    speed = torch.linalg.vector_norm(v, dim=-1, keepdim=True)
    return torch.where(speed >= CRUISE_FLOOR, v / speed.clamp_min(CRUISE_FLOOR), action)


def make_safety_filter_config(cfg: Any = None, **overrides: Any) -> SafetyFilterConfig:
    """Build a :class:`SafetyFilterConfig`; ``ValueError`` names the field."""
    return parse_model(SafetyFilterConfig, cfg, prefix="safety_filter", title="safety filter", **overrides)


class ScreenLimits(Protocol):
    """The numbers :func:`screen` reads (the planner's ``HeuristicConfig`` has them too)."""

    filter_clearance: float
    boundary_margin: float
    rz_speed_margin: float
    rz_inflate: float
    ou_safety_distance: float
    ou_robust_margin: float
    ou_robust_samples: int


def inflate(rects: Tensor, margin: Tensor) -> Tensor:
    # (x0 - m, y0 - m, x1 + m, y1 + m), margin broadcast over [..., P]
    m = margin.unsqueeze(-1)
    sign = torch.tensor([-1.0, -1.0, 1.0, 1.0], dtype=rects.dtype, device=rects.device)
    return rects + m * sign


def blocked(p0: Tensor, p1: Tensor, rects: Tensor, margin: Tensor, mask: Tensor) -> Tensor:
    """True where the segment p0 -> p1 meets any rectangle inflated by ``margin`` (per rectangle)."""
    return ph.segment_hits_rects(p0, p1, inflate(rects, margin), mask).any(-1)


@dataclass
class Screened:
    """Candidates ``[B, C, 2]`` after the RZ cap, and per candidate ``[B, C]``: feasible (BZ,
    NFZ, boundary), OU-safe, turn-proof, and the predicted closest approach to a perceived OU."""

    cand: Tensor
    feasible: Tensor
    ou_ok: Tensor
    proof: Tensor
    clear: Tensor


def screen(s: Mapping[str, Tensor], p: Tensor, cand: Tensor, rects: Tensor, rmask: Tensor, edge: Tensor,
           lim: ScreenLimits, ec: EnvConfig, keep_distance: bool = False) -> Screened:
    """Screen candidate velocities ``cand`` ``[B, C, 2]`` from ``p`` ``[B, 2]`` (module doc).

    ``rects`` / ``rmask``: the BZs and NFZs ``[B, P, 4]``; ``edge`` ``[B]``: how far inside the
    area each step must end. ``keep_distance``: also refuse a step that ends nearer to a
    rectangle than ``min(filter_clearance, d_now)`` (the filter's rule; the planner plans its
    clearance itself)."""
    m, a = ec.motion, ec.area
    dt = p.dtype
    pc = p.unsqueeze(1).expand_as(cand)

    # RZ: a segment that touches an RZ flies at most margin * v_limit (a prefix of it stays legal)
    rz, rz_mask = s["rz"].to(dt), s["rz_mask"]
    rz_m = torch.full_like(rz[..., 0], lim.rz_inflate).unsqueeze(1)
    in_rz = blocked(pc, pc + cand * m.t_fly, rz.unsqueeze(1), rz_m, rz_mask.unsqueeze(1))
    spd = torch.linalg.vector_norm(cand, dim=-1, keepdim=True)
    cap = lim.rz_speed_margin * m.v_limit
    scale = torch.where(in_rz.unsqueeze(-1) & (spd > cap), cap / spd.clamp_min(1e-9), torch.ones_like(spd))
    cand = cand * scale
    end = pc + cand * m.t_fly

    # static safety: clear of BZ/NFZ by filter_clearance (less when already nearer), inside the area
    d_r = ph.point_rect_distance(p, rects, rmask)  # [B, P]
    fm = torch.minimum(torch.full_like(d_r, lim.filter_clearance), (d_r - EPS).clamp_min(0.0))
    hit = blocked(pc, end, rects.unsqueeze(1), fm.unsqueeze(1), rmask.unsqueeze(1))
    if keep_distance:
        d_end = ph.point_rect_distance(end, rects.unsqueeze(1), rmask.unsqueeze(1))  # [B, C, P]
        hold = torch.minimum(torch.full_like(d_r, lim.filter_clearance), d_r).unsqueeze(1)
        hit = hit | ((d_end < hold) & rmask.unsqueeze(1)).any(-1)
    e = edge.unsqueeze(-1)
    inside = (
        (end[..., 0] >= e) & (end[..., 0] <= a.x_size - e) & (end[..., 1] >= e) & (end[..., 1] <= a.y_size - e)
    )
    feasible = ~hit & inside  # [B, C]; hovering is always feasible

    # perceived OUs (perception radius only), assumed to keep their last velocity over the flight phase
    ou_pos, ou_vel = s["ou_pos"].to(dt), s["ou_vel"].to(dt)
    d_now = torch.linalg.vector_norm(ou_pos - p.unsqueeze(-2), dim=-1)  # [B, K]
    visible = (s["ou_mask"] & (d_now <= ec.safety.perception_radius)).unsqueeze(1)
    appr = ph.closest_approach(pc, cand, ou_pos.unsqueeze(1), ou_vel.unsqueeze(1), m.t_fly)  # [B, C, K]
    # safe: the closest approach keeps the safety distance, or at least does not shrink below now
    need = torch.minimum(torch.full_like(d_now, lim.ou_safety_distance), d_now - EPS).unsqueeze(1)
    ou_ok = ((appr >= need) | ~visible).all(-1)
    clear = ph.nearest_distance(torch.where(visible, appr, torch.full_like(appr, math.inf)))  # inf: none seen
    # turn-proof: |DCU(s) - OU(0)| - v_max s >= r_coll + margin at sampled s in [0, t_fly]
    ts = torch.linspace(0.0, m.t_fly, lim.ou_robust_samples, dtype=dt, device=p.device)
    r0 = (pc.unsqueeze(-2) - ou_pos.unsqueeze(1)).unsqueeze(-2)  # [B, C, K, 1, 2]
    track = r0 + cand[:, :, None, None, :] * ts.view(-1, 1)  # [B, C, K, S, 2]
    slack = torch.linalg.vector_norm(track, dim=-1) - m.v_max * ts  # OUs fly at most v_max
    proof = ((slack >= ec.safety.r_coll + lim.ou_robust_margin).all(-1) | ~visible).all(-1)
    return Screened(cand, feasible, ou_ok, proof, clear)


def choose(sc: Screened, v_wish: Tensor) -> Tensor:
    """The index ``[B]`` of the candidate to fly (module doc: nearest admissible to the wish)."""
    dev = torch.linalg.vector_norm(sc.cand - v_wish.unsqueeze(1), dim=-1)
    ninf = torch.full_like(dev, -math.inf)
    safe = sc.feasible & sc.ou_ok
    pick_proof = torch.where(safe & sc.proof, -dev, ninf).argmax(-1)
    pick_safe = torch.where(safe, -dev, ninf).argmax(-1)
    pick_best = torch.where(sc.feasible, sc.clear - 1e-3 * dev, ninf).argmax(-1)
    return torch.where((safe & sc.proof).any(-1), pick_proof, torch.where(safe.any(-1), pick_safe, pick_best))


def picked(sc: Screened, index: Tensor) -> Tensor:
    """The candidates ``[B, 2]`` at ``index`` ``[B]``."""
    return sc.cand.gather(1, index.view(-1, 1, 1).expand(-1, 1, 2)).squeeze(1)


class SafetyFilter(nn.Module):
    """The filter as a plain module: :meth:`velocity` on raw state tensors (exportable), and
    :meth:`filter_action` on an action in [-1, 1]^2. Build it with :func:`make_safety_filter`."""

    def __init__(self, env_cfg: EnvConfig | Mapping | None = None, cfg: SafetyFilterConfig | Mapping | None = None):
        super().__init__()
        self.env_cfg = make_env_config(env_cfg)
        self.cfg = make_safety_filter_config(cfg)
        c = self.cfg
        k = torch.arange(c.headings, dtype=torch.float32) * (2 * math.pi / c.headings)
        ring = torch.stack([torch.cos(k), torch.sin(k)], -1)  # [H, 2]
        speeds = torch.tensor(c.ring_speeds, dtype=torch.float32) * self.env_cfg.motion.v_max
        ring = (speeds.view(-1, 1, 1) * ring).reshape(-1, 2)
        self.register_buffer("fixed", torch.cat([torch.zeros(1, 2), ring], 0), persistent=False)  # hover first
        self.register_buffer("fractions", torch.tensor((1.0, *c.wish_fractions), dtype=torch.float32),
                             persistent=False)

    def candidates(self, v_wish: Tensor) -> Tensor:
        """``[B, C, 2]``: the wish and its shortenings, its x and y parts, the ring, hovering."""
        f = self.fractions.to(v_wish.dtype).view(1, -1, 1)
        w = v_wish.unsqueeze(1)
        x_part = w * torch.tensor([1.0, 0.0], dtype=w.dtype, device=w.device)
        y_part = w * torch.tensor([0.0, 1.0], dtype=w.dtype, device=w.device)
        fixed = self.fixed.to(v_wish.dtype).unsqueeze(0).expand(v_wish.shape[0], -1, -1)
        return torch.cat([w * f, x_part * f, y_part * f, fixed], dim=1)

    def velocity(self, s: Mapping[str, Tensor], v_wish: Tensor) -> Tensor:
        """The executed velocity ``[B, 2]`` for the wished one, from the raw state ``s``."""
        ec, a = self.env_cfg, self.env_cfg.area
        p = s["position"]
        dt = p.dtype
        rects = torch.cat([s["bz"], s["nfz"]], dim=-2).to(dt)
        rmask = torch.cat([s["bz_mask"], s["nfz_mask"]], dim=-1)
        edge = ph.boundary_distance(p, a.x_size, a.y_size).clamp_max(self.cfg.boundary_margin)
        sc = screen(s, p, self.candidates(v_wish.to(dt)), rects, rmask, edge, self.cfg, ec, keep_distance=True)
        return picked(sc, choose(sc, v_wish.to(dt)))

    def filter_action(self, s: Mapping[str, Tensor], action: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """``(executed action, changed [B] bool, |v_executed - v_wish| [B] in m/s)`` for an
        action in [-1, 1]^2 (as the env reads it: SPEC §2). With ``cruise`` the wish is the
        action at v_max (:func:`cruise_action`), and an unchanged row flies that."""
        v_max = self.env_cfg.motion.v_max
        command = cruise_action(action, v_max) if self.cfg.cruise else action
        wish = ph.action_to_velocity(command, v_max)
        v = self.velocity(s, wish)
        delta = torch.linalg.vector_norm(v - wish, dim=-1)
        # a change below a micrometre per second is float noise, not an intervention
        changed = delta > 1e-6
        executed = torch.where(changed.unsqueeze(-1), v / v_max, command)
        return executed, changed, delta


def make_safety_filter(cfg: Any, env_cfg: EnvConfig) -> SafetyFilter | None:
    """The filter of the ``safety_filter`` group, or None when its mode is ``off``."""
    c = make_safety_filter_config(cfg)
    return None if c.mode == "off" else SafetyFilter(env_cfg, c)


class SafetyStats:
    """Running counts of the filter's interventions: rows seen, rows changed, the summed change."""

    def __init__(self) -> None:
        self.reset()

    def reset(self) -> None:
        self.rows = 0
        self.changed = 0
        self.delta = 0.0

    def add(self, changed: Tensor, delta: Tensor, live: Tensor | None = None) -> None:
        if live is not None:
            changed, delta = changed[live], delta[live]
        self.rows += int(changed.numel())
        self.changed += int(changed.sum())
        self.delta += float(delta.sum())

    def snapshot(self, reset: bool = False) -> dict[str, float]:
        """``intervention_rate``: the share of rows changed; ``mean_change``: the mean |Δv| over
        the changed rows (m/s); ``rows``."""
        out = {"rows": float(self.rows), "intervention_rate": self.changed / self.rows if self.rows else 0.0,
               "mean_change": self.delta / self.changed if self.changed else 0.0}
        if reset:
            self.reset()
        return out

    def state_dict(self) -> dict[str, Any]:
        return {"rows": self.rows, "changed": self.changed, "delta": self.delta}

    def load_state_dict(self, state: Mapping[str, Any]) -> None:
        self.rows, self.changed, self.delta = int(state["rows"]), int(state["changed"]), float(state["delta"])


class FilteredPolicy(TensorDictModuleBase):
    """A policy whose ``"action"`` goes through the filter: what the evaluator flies as the
    deployed pilot. It writes ``("safety", "changed")`` and ``("safety", "delta")`` and counts
    the interventions of each row's first episode (:class:`SafetyStats`), as the evaluator
    scores each row's first episode only."""

    out_keys = ["action", ("safety", "changed"), ("safety", "delta")]

    def __init__(self, policy: Any, safety: SafetyFilter):
        super().__init__()
        self.policy = policy
        self.safety = safety
        self.in_keys = list(getattr(policy, "in_keys", ["observation"])) + [("state", k) for k in STATE_KEYS]
        self.stats = SafetyStats()
        self._ended: Tensor | None = None

    def reset(self) -> None:
        """Start counting anew (one evaluation's interventions)."""
        self.stats.reset()
        self._ended = None

    def forward(self, td: TensorDictBase) -> TensorDictBase:
        td = self.policy(td)
        apply_filter(self.safety, td)
        step = td.get(("state", "step"), None)
        done = td.get("done", None)
        live = None
        if step is not None and done is not None:
            ended = done.reshape(-1) if self._ended is None or self._ended.shape != done.reshape(-1).shape \
                else self._ended | done.reshape(-1)
            ended = ended & (step.reshape(-1) > 0)  # a fresh episode starts counting again
            live, self._ended = ~ended, ended
        self.stats.add(td.get(("safety", "changed")), td.get(("safety", "delta")), live)
        return td


def apply_filter(safety: SafetyFilter, td: TensorDictBase) -> TensorDictBase:
    """Filter ``td["action"]`` in place from ``td["state"]``; record whether and how much it changed."""
    s = {k: td.get(("state", k)) for k in STATE_KEYS}
    executed, changed, delta = safety.filter_action(s, td.get("action"))
    td.set("action", executed)
    td.set(("safety", "changed"), changed)
    td.set(("safety", "delta"), delta)
    return td


__all__ = [
    "CRUISE_FLOOR", "FilteredPolicy", "MODES", "STATE_KEYS", "SafetyFilter", "SafetyFilterConfig", "SafetyStats", "Screened",
    "apply_filter", "blocked", "choose", "cruise_action", "inflate", "make_safety_filter", "make_safety_filter_config", "picked",
    "screen",
]
