"""The paper's greedy heuristic (§6.3, after sar-path-planning; docs/model.md §8 "Heuristic (greedy)").

What the DCU may use: the static map (every BZ, NFZ and RZ rectangle, as in its observation),
every GE's position and remaining data, its own position, energy and slot count, and the OUs
within the perception radius PR (20 m) only. No path search, no map of distances, no look-ahead
beyond the next slot's flight segment (at most v_max * t_fly = 10 m plus ``clearance``, inside
PR). Every number is in :class:`GreedyConfig` (``conf/advisor/greedy.yaml``). Fully batched.

The rules, applied every slot in this order:

1. Target. Sticky: kept until its GE is served or abandoned (rule 6). The next target is the
   nearest GE with data by straight-line distance, among those not abandoned; none left -> LA.
2. Head home (latched for the rest of the episode) when the slots left only suffice for the
   return, ``t_max - step <= home_time_factor * ceil(d_LA / (v_max t_fly)) + home_time_reserve``,
   or the energy left only suffices for it, ``E <= home_energy_factor * E_min(d_LA) +
   home_energy_reserve`` (E_min of docs/model.md §7 r8). With SPEC's numbers the energy rule never
   binds (a mission uses at most ~337 kJ of 800 kJ), so the time rule is the one that acts.
3. Desired velocity: straight at the target at v_max, shortened so the step ends on it (on a GE
   it then hovers until the GE is served; on the LA centre it stops, which lands).
4. Residential zones: a flight segment that touches an RZ (inflated by ``rz_inflate``) flies at
   most ``rz_speed_margin * v_limit``.
5. Local detour around BZ/NFZ (bug-style): the step's segment must keep ``clearance`` from
   every BZ and NFZ and end inside the area. If the straight heading fails, the heading is
   turned in steps of 360/``headings`` degrees to one side until a free one is found (hover if
   none). The side is chosen at the start of a detour (the side with the smaller free turn;
   left on a tie) and kept while the detour lasts and ``side_memory`` slots after, so the DCU
   follows an obstacle's side instead of turning back and forth.
6. Loop escape: when the distance to the target has not improved by ``progress_eps`` for
   ``stall_patience`` slots, a GE target is abandoned for the rest of the episode (the next
   nearest is taken), and an LA target flips the detour side.
7. OUs, over everything above: if the chosen velocity's predicted closest approach to a visible
   OU (constant velocities over the flight phase) is below ``ou_safety_distance`` (or below the
   current distance when that is smaller), the DCU hovers if hovering is safe, else retreats at
   v_max straight away from the nearest visible OU, turned as little as needed to be safe and
   clear of BZ/NFZ; if nothing is safe, the clear move with the largest closest approach. It
   re-decides every slot, so it waits until the OU has passed.

The memory (target, side, stall counter, abandoned GEs, homing latch) is per batch row; it
restarts for a row whose ``step`` is not the previous call's plus one or whose GEs are not the
previous call's, and for every row when the batch size changes (SAC+Heuristic passes only the
triggered rows).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

import torch
from pydantic import Field
from torch import Tensor

from uavlae.envs import physics as ph
from uavlae.envs.config import EnvConfig, make_env_config
from uavlae.policies.controller import StateController
from uavlae.validation import StrictModel, parse_model

STATE_IN_KEYS = (
    "position", "energy_left", "step", "ge_pos", "ge_remaining", "ge_mask", "ou_pos", "ou_vel",
    "ou_mask", "nfz", "nfz_mask", "rz", "rz_mask", "bz", "bz_mask", "landing",
)
_EPS = 1e-3  # metres: a point already nearer an obstacle than the clearance may not get nearer


class GreedyConfig(StrictModel):
    """Numbers of the greedy heuristic; ``conf/advisor/greedy.yaml`` mirrors it one-to-one."""

    clearance: float = Field(8.0, ge=0)  # m: the step's segment keeps this far from BZ/NFZ
    boundary_margin: float = Field(1.0, ge=0)  # m: every step ends this far inside the area
    headings: int = Field(32, ge=4, le=360)  # detour and retreat headings: a turn step of 360/headings degrees
    side_memory: int = Field(10, ge=0)  # slots the detour side is kept after a detour ends
    stall_patience: int = Field(60, ge=1)  # slots without progress before the loop-escape rule
    progress_eps: float = Field(0.5, ge=0)  # m: an improvement of the best distance to the target
    home_time_factor: float = Field(1.5, ge=1)  # on the straight-line slots to LA
    home_time_reserve: int = Field(20, ge=0)  # slots kept on top
    home_energy_factor: float = Field(1.5, ge=1)  # on E_min(d_LA)
    home_energy_reserve: float = Field(5000.0, ge=0)  # J kept on top
    rz_speed_margin: float = Field(0.95, gt=0, le=1)  # |v| <= margin * v_limit on a segment touching an RZ
    rz_inflate: float = Field(1.0, ge=0)  # m: RZs are tested inflated by this much
    ou_safety_distance: float = Field(5.0, gt=0)  # m: least predicted closest approach to a visible OU


def make_greedy_config(cfg: Any = None, **overrides: Any) -> GreedyConfig:
    """Build a :class:`GreedyConfig` from a mapping / OmegaConf node; ``ValueError`` names the field."""
    return parse_model(GreedyConfig, cfg, prefix="greedy", title="greedy", **overrides)


def _rotate(v: Tensor, angle: Tensor) -> Tensor:
    """Rotate [..., 2] vectors counter-clockwise by ``angle`` (broadcast over the leading dims)."""
    c, s = torch.cos(angle), torch.sin(angle)
    return torch.stack([c * v[..., 0] - s * v[..., 1], s * v[..., 0] + c * v[..., 1]], dim=-1)


class GreedyPolicy(StateController):
    """The paper's greedy controller (module doc: the rules); ``act(state)`` or ``forward(td)``.

    Args:
        env_cfg: the world (area, speeds, energy model, perception radius, t_max).
        cfg: the heuristic's numbers (default: :class:`GreedyConfig`'s).
    """

    state_keys = STATE_IN_KEYS
    in_keys = [("state", k) for k in STATE_IN_KEYS]

    def __init__(self, env_cfg: EnvConfig | Mapping | None = None, cfg: GreedyConfig | Mapping | None = None):
        super().__init__()
        self.env_cfg = make_env_config(env_cfg)
        self.cfg = make_greedy_config(cfg)
        self._mem: dict[str, Tensor] | None = None

    # ------------------------------------------------------------------ state (exact resume)
    def cache_state(self) -> dict[str, Any]:
        """The per-row memory as plain tensors (actions depend on it: checkpoints hold it)."""
        return {"memory": None if self._mem is None else {k: v.clone() for k, v in self._mem.items()}}

    def load_cache_state(self, state: Mapping[str, Any]) -> None:
        mem = state.get("memory")
        self._mem = None if mem is None else {k: v.clone() for k, v in mem.items()}

    # ------------------------------------------------------------------ acting
    def _memory(self, s: dict[str, Tensor]) -> dict[str, Tensor]:
        p, step = s["position"], s["step"].to(torch.int64)
        B, G = p.shape[0], s["ge_pos"].shape[-2]
        mem = self._mem
        if mem is None or mem["target"].shape[0] != B or mem["abandoned"].shape[-1] != G or mem["target"].device != p.device:
            mem = {
                "valid": torch.zeros(B, dtype=torch.bool, device=p.device),
                "last_step": torch.zeros(B, dtype=torch.int64, device=p.device),
                "target": torch.full((B,), -1, dtype=torch.int64, device=p.device),
                "side": torch.zeros(B, dtype=p.dtype, device=p.device),
                "side_ttl": torch.zeros(B, dtype=torch.int64, device=p.device),
                "best_dist": torch.full((B,), math.inf, dtype=p.dtype, device=p.device),
                "stall": torch.zeros(B, dtype=torch.int64, device=p.device),
                "homing": torch.zeros(B, dtype=torch.bool, device=p.device),
                "abandoned": torch.zeros(B, G, dtype=torch.bool, device=p.device),
                "sig": torch.zeros(B, 2 * G, dtype=p.dtype, device=p.device),
            }
        # a row is the same episode only if its step follows on and its GEs are the same ones
        # (SAC+Heuristic hands over a different subset of rows from call to call)
        sig = s["ge_pos"].to(p.dtype).flatten(1)
        fresh = ~mem["valid"] | (step != mem["last_step"] + 1) | (sig != mem["sig"]).any(-1)
        mem = {k: v.clone() for k, v in mem.items()}
        mem["target"] = torch.where(fresh, -1, mem["target"])
        mem["side"] = torch.where(fresh, 0.0, mem["side"])
        mem["side_ttl"] = torch.where(fresh, 0, mem["side_ttl"])
        mem["best_dist"] = torch.where(fresh, math.inf, mem["best_dist"])
        mem["stall"] = torch.where(fresh, 0, mem["stall"])
        mem["homing"] = mem["homing"] & ~fresh
        mem["abandoned"] = mem["abandoned"] & ~fresh.unsqueeze(-1)
        mem["sig"] = sig.clone()
        return mem

    def _choose_target(self, s: dict[str, Tensor], mem: dict[str, Tensor]) -> tuple[Tensor, Tensor, Tensor]:
        """Rules 1, 2 and 6: the target index (G for LA), its position and whether it changed."""
        c, ec = self.cfg, self.env_cfg
        m = ec.motion
        p = s["position"]
        B, G = p.shape[0], s["ge_pos"].shape[-2]
        la = s["landing"].to(p.dtype)
        la_c = 0.5 * (la[..., :2] + la[..., 2:])
        d_la = torch.linalg.vector_norm(la_c - p, dim=-1)
        # rule 2: the return's slots (straight line) or energy are all that is left
        steps_left = (ec.t_max - s["step"].to(torch.int64)).to(p.dtype)
        need_t = c.home_time_factor * torch.ceil(d_la / (m.v_max * m.t_fly)) + c.home_time_reserve
        need_e = c.home_energy_factor * ph.min_return_energy(d_la, ec.energy, m) + c.home_energy_reserve
        mem["homing"] = mem["homing"] | (steps_left <= need_t) | (s["energy_left"].to(p.dtype) <= need_e)

        has_data = s["ge_mask"] & (s["ge_remaining"] > 0) & ~mem["abandoned"]
        tgt = mem["target"]
        if G:
            still = (tgt >= 0) & (tgt < G) & has_data.gather(1, tgt.clamp(0, G - 1).unsqueeze(-1)).squeeze(-1)
        else:
            still = torch.zeros_like(mem["homing"])
        still = (still & ~mem["homing"]) | ((tgt == G) & (mem["homing"] | ~has_data.any(-1)))
        d_ge = torch.linalg.vector_norm(s["ge_pos"].to(p.dtype) - p.unsqueeze(-2), dim=-1)
        d_ge = torch.where(has_data, d_ge, torch.full_like(d_ge, math.inf))
        nearest = d_ge.argmin(-1) if G else torch.zeros(B, dtype=torch.int64, device=p.device)
        go_ge = has_data.any(-1) & ~mem["homing"]
        new = torch.where(go_ge, nearest, torch.full_like(nearest, G))
        target = torch.where(still, tgt, new)
        changed = target != tgt
        ge_pos = torch.cat([s["ge_pos"].to(p.dtype), la_c.unsqueeze(-2)], dim=-2)
        tgt_pos = ge_pos.gather(1, target.view(B, 1, 1).expand(B, 1, 2)).squeeze(1)
        return target, tgt_pos, changed

    def _rz_cap(self, s: dict[str, Tensor], p: Tensor, v: Tensor) -> Tensor:
        """Rule 4 on candidate velocities ``v`` [B, C, 2]."""
        c, m = self.cfg, self.env_cfg.motion
        pc = p.unsqueeze(1).expand_as(v)
        rz = s["rz"].to(p.dtype)
        grown = rz + c.rz_inflate * torch.tensor([-1.0, -1.0, 1.0, 1.0], dtype=p.dtype, device=p.device)
        touch = ph.segment_hits_rects(pc, pc + v * m.t_fly, grown.unsqueeze(1), s["rz_mask"].unsqueeze(1)).any(-1)
        spd = torch.linalg.vector_norm(v, dim=-1, keepdim=True)
        cap = c.rz_speed_margin * m.v_limit
        return torch.where(touch.unsqueeze(-1) & (spd > cap), v * (cap / spd.clamp_min(1e-9)), v)

    def _clear(self, s: dict[str, Tensor], p: Tensor, v: Tensor) -> Tensor:
        """Rule 5's test on candidates [B, C, 2]: the segment keeps the clearance, the end is inside A."""
        c, ec = self.cfg, self.env_cfg
        a, m = ec.area, ec.motion
        rects = torch.cat([s["bz"], s["nfz"]], dim=-2).to(p.dtype)
        rmask = torch.cat([s["bz_mask"], s["nfz_mask"]], dim=-1)
        d_r = ph.point_rect_distance(p, rects, rmask)  # [B, P]
        margin = torch.minimum(torch.full_like(d_r, c.clearance), (d_r - _EPS).clamp_min(0.0))
        sign = torch.tensor([-1.0, -1.0, 1.0, 1.0], dtype=p.dtype, device=p.device)
        grown = rects + margin.unsqueeze(-1) * sign
        pc = p.unsqueeze(1).expand_as(v)
        end = pc + v * m.t_fly
        hit = ph.segment_hits_rects(pc, end, grown.unsqueeze(1), rmask.unsqueeze(1)).any(-1)
        edge = torch.minimum(
            ph.boundary_distance(p, a.x_size, a.y_size), torch.full_like(p[..., 0], c.boundary_margin)
        ).unsqueeze(-1)
        inside = (
            (end[..., 0] >= edge) & (end[..., 0] <= a.x_size - edge)
            & (end[..., 1] >= edge) & (end[..., 1] <= a.y_size - edge)
        )
        still = torch.linalg.vector_norm(v, dim=-1) == 0  # hovering never moves into anything
        return (~hit & inside) | still

    def _ou_clearance(self, s: dict[str, Tensor], p: Tensor, v: Tensor) -> tuple[Tensor, Tensor]:
        """Rule 7's test on candidates [B, C, 2]: (safe [B, C], least closest approach [B, C])."""
        ec = self.env_cfg
        ou_pos, ou_vel = s["ou_pos"].to(p.dtype), s["ou_vel"].to(p.dtype)
        d_now = torch.linalg.vector_norm(ou_pos - p.unsqueeze(-2), dim=-1)  # [B, K]
        visible = (s["ou_mask"] & (d_now <= ec.safety.perception_radius)).unsqueeze(1)  # [B, 1, K]
        pc = p.unsqueeze(1).expand_as(v)
        appr = ph.closest_approach(pc, v, ou_pos.unsqueeze(1), ou_vel.unsqueeze(1), ec.motion.t_fly)  # [B, C, K]
        need = torch.minimum(torch.full_like(d_now, self.cfg.ou_safety_distance), d_now - _EPS).unsqueeze(1)
        safe = ((appr >= need) | ~visible).all(-1)
        least = torch.where(visible, appr, torch.full_like(appr, math.inf)).amin(-1)
        return safe, least

    def _velocity(self, s: dict[str, Tensor]) -> Tensor:
        c, m = self.cfg, self.env_cfg.motion
        p = s["position"]
        B, G = p.shape[0], s["ge_pos"].shape[-2]
        dt = p.dtype
        mem = self._memory(s)
        target, tgt_pos, changed = self._choose_target(s, mem)

        # rule 6 bookkeeping: progress toward the (possibly new) target
        dist = torch.linalg.vector_norm(tgt_pos - p, dim=-1)
        best = torch.where(changed, torch.full_like(dist, math.inf), mem["best_dist"])
        improved = dist < best - c.progress_eps
        mem["stall"] = torch.where(changed | improved, 0, mem["stall"] + 1)
        mem["best_dist"] = torch.where(improved | changed, dist, best)
        mem["side"] = torch.where(changed, 0.0, mem["side"])
        stuck = mem["stall"] >= c.stall_patience
        if bool(stuck.any()):
            on_ge = stuck & (target < G)
            if G and bool(on_ge.any()):
                ab = torch.zeros_like(mem["abandoned"])
                ab[on_ge.nonzero().squeeze(-1), target[on_ge]] = True
                mem["abandoned"] = mem["abandoned"] | ab
                mem["target"] = target
                target, tgt_pos, changed2 = self._choose_target(s, mem)
                dist = torch.linalg.vector_norm(tgt_pos - p, dim=-1)
                mem["best_dist"] = torch.where(changed2, dist, mem["best_dist"])
                mem["side"] = torch.where(changed2, 0.0, mem["side"])
            on_la = stuck & (target == G)
            mem["side"] = torch.where(on_la, -torch.where(mem["side"] == 0, 1.0, mem["side"]), mem["side"])
            mem["side_ttl"] = torch.where(on_la, c.side_memory, mem["side_ttl"])
            mem["stall"] = torch.where(stuck, 0, mem["stall"])
        mem["target"] = target

        # rule 3: straight at the target, the step ending on it
        to_t = tgt_pos - p
        speed = torch.minimum(dist / m.t_fly, torch.full_like(dist, m.v_max))
        unit = to_t / dist.clamp_min(1e-9).unsqueeze(-1)
        unit = torch.where((dist > 0).unsqueeze(-1), unit, torch.zeros_like(unit))

        # rules 4 and 5: turns k = 0..H/2 to each side, k = 0 first; the RZ cap on each
        H = c.headings
        k = torch.arange(H // 2 + 1, dtype=dt, device=p.device)
        step_angle = 2 * math.pi / H
        sides = torch.tensor([1.0, -1.0], dtype=dt, device=p.device)
        angles = (sides.view(2, 1) * k.view(1, -1) * step_angle).reshape(-1)  # [2 (H/2 + 1)]
        cand = _rotate(unit.unsqueeze(1), angles.unsqueeze(0)) * speed.view(B, 1, 1)  # [B, 2K, 2]
        cand = self._rz_cap(s, p, cand)
        free = self._clear(s, p, cand).view(B, 2, -1)
        n_k = k.numel()
        big = n_k + 1
        first = torch.where(free, k.to(torch.int64).view(1, 1, -1), big).amin(-1)  # [B, 2] smallest free turn per side
        side_mem = mem["side"]
        pref = torch.where(first[:, 0] <= first[:, 1], 1.0, -1.0)  # left on a tie
        side = torch.where(side_mem != 0, side_mem, pref)
        side_i = torch.where(side > 0, 0, 1)
        k_pick = first.gather(1, side_i.unsqueeze(-1)).squeeze(-1)
        none_free = k_pick >= big
        idx = side_i * n_k + k_pick.clamp_max(n_k - 1)
        v = cand.gather(1, idx.view(B, 1, 1).expand(B, 1, 2)).squeeze(1)
        v = torch.where(none_free.unsqueeze(-1), torch.zeros_like(v), v)
        detour = (k_pick > 0) & ~none_free
        mem["side"] = torch.where(detour, side, torch.where(mem["side_ttl"] > 0, mem["side"], 0.0))
        mem["side_ttl"] = torch.where(detour, c.side_memory, (mem["side_ttl"] - 1).clamp_min(0))

        # rule 7: visible OUs override: hover if safe, else retreat
        safe, _ = self._ou_clearance(s, p, v.unsqueeze(1))
        unsafe = ~safe[:, 0]
        if bool(unsafe.any()):
            rows = unsafe.nonzero().squeeze(-1)
            sub = {key: t[rows] for key, t in s.items()}
            pr = p[rows]
            v = v.index_copy(0, rows, self._evade(sub, pr))
        mem["valid"] = torch.ones_like(mem["valid"])
        mem["last_step"] = s["step"].to(torch.int64).clone()
        self._mem = mem
        return v

    def _evade(self, s: dict[str, Tensor], p: Tensor) -> Tensor:
        """Rule 7 for the rows whose chosen move comes too close to a visible OU."""
        c, ec = self.cfg, self.env_cfg
        m = ec.motion
        R, dt = p.shape[0], p.dtype
        ou_pos = s["ou_pos"].to(dt)
        d_now = torch.linalg.vector_norm(ou_pos - p.unsqueeze(-2), dim=-1)
        visible = s["ou_mask"] & (d_now <= ec.safety.perception_radius)
        nearest = torch.where(visible, d_now, torch.full_like(d_now, math.inf)).argmin(-1)
        q = ou_pos.gather(1, nearest.view(R, 1, 1).expand(R, 1, 2)).squeeze(1)
        away = p - q
        away = away / torch.linalg.vector_norm(away, dim=-1, keepdim=True).clamp_min(1e-9)
        H = c.headings
        k = torch.arange(H // 2 + 1, dtype=dt, device=p.device)
        # turns 0, +1, -1, +2, -2, ...: the retreat nearest straight away first
        order = torch.stack([k, -k], -1).reshape(-1)[1:] * (2 * math.pi / H)
        retreat = _rotate(away.unsqueeze(1), order.unsqueeze(0)) * m.v_max  # [R, C, 2]
        cand = torch.cat([torch.zeros_like(retreat[:, :1]), retreat], dim=1)  # hover first
        cand = self._rz_cap(s, p, cand)
        free = self._clear(s, p, cand)
        safe, least = self._ou_clearance(s, p, cand)
        C = cand.shape[1]
        rank = torch.arange(C, device=p.device).unsqueeze(0).expand(R, C)
        ok = free & safe
        pick_ok = torch.where(ok, rank, C).amin(-1)
        pick_best = torch.where(free, least, torch.full_like(least, -math.inf)).argmax(-1)
        pick = torch.where(pick_ok < C, pick_ok, pick_best)
        return cand.gather(1, pick.view(R, 1, 1).expand(R, 1, 2)).squeeze(1)
