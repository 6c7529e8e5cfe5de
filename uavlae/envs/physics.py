"""The world's physics as pure, batched tensor functions (docs/model.md §2-§7).

Every function accepts any leading batch shape ``...``, runs on any device and float dtype,
never loops over batch elements or entities and never syncs with the host. Padded entities
come with a boolean presence mask; absent entries never count. Rectangles are
``(x0, y0, x1, y1)``. Numbers come from :mod:`uavlae.envs.config`; none is hard-coded here.
"""

from __future__ import annotations

import functools
import math

import torch
from torch import Tensor

from uavlae.envs.config import (
    ChannelConfig,
    CostConfig,
    EnergyConfig,
    EnvConfig,
    MotionConfig,
    OUConfig,
)

__all__ = [
    "ramp",
    "action_to_velocity",
    "propulsion_power",
    "slot_energy",
    "min_return_energy",
    "channel",
    "serve_ge",
    "point_in_rects",
    "point_rect_distance",
    "nearest_distance",
    "segment_hits_rects",
    "boundary_distance",
    "outside_area",
    "clip_to_area",
    "closest_approach",
    "ou_step",
    "reward_terms",
    "cost",
    "COST_EVENTS",
]

# The paper's four, then RZ speeding, whose weight is 0 by default (SPEC §7)
COST_EVENTS = ("boundary_exit", "ou_collision", "bz_collision", "nfz_entry", "rz_speeding")


# ----------------------------------------------------------------------------- shaping


def ramp(d: Tensor, d_min: float, d_safe: float) -> Tensor:
    # SPEC §7: ramp(d) = clip((d_safe - d) / (d_safe - d_min), 0, 1); ramp(+inf) = 0
    return ((d_safe - d) / (d_safe - d_min)).clamp(0.0, 1.0)


# ----------------------------------------------------------------------------- motion


def action_to_velocity(action: Tensor, v_max: float) -> Tensor:
    # SPEC §2: v = v_max * clip(a, -1, 1), rescaled so that |v| <= v_max
    v = v_max * action.clamp(-1.0, 1.0)
    speed = torch.linalg.vector_norm(v, dim=-1, keepdim=True)
    scale = torch.where(speed > v_max, v_max / speed.clamp_min(v_max), torch.ones_like(speed))
    return v * scale


# ----------------------------------------------------------------------------- energy


def propulsion_power(speed: Tensor, e: EnergyConfig) -> Tensor:
    # SPEC §4, Zeng 2019 rotary-wing power: P(V) = P0(1+3V²/U²) + Pi·sqrt(sqrt(1+V⁴/4v0⁴) - V²/2v0²) + ½d0ρsA V³
    v2 = speed * speed
    blade = e.p0 * (1.0 + 3.0 * v2 / e.u_tip**2)
    a = v2 / (2.0 * e.v0**2)
    # sqrt(1 + V⁴/4v0⁴) - V²/2v0² = sqrt(1 + a²) - a = 1 / (sqrt(1 + a²) + a): no cancellation at high speed
    induced = e.pi * torch.rsqrt(torch.sqrt(1.0 + a * a) + a)
    parasite = 0.5 * e.d0 * e.rho * e.s * e.rotor_area * speed * v2
    return blade + induced + parasite


@functools.lru_cache(maxsize=64)
def _power_at_cached(speed: float, e: EnergyConfig) -> float:
    return float(propulsion_power(torch.tensor(speed, dtype=torch.float64), e))


@torch.compiler.assume_constant_result
def _power_at(speed: float, e: EnergyConfig) -> float:
    """P(V) for one constant speed, in float64 (no tensor ops on the hot path). Under
    ``torch.compile`` it is evaluated once at trace time and baked in as a constant (the config
    is fixed per compiled env), instead of a graph break on ``float(tensor)``."""
    return _power_at_cached(speed, e)


def slot_energy(speed: Tensor, e: EnergyConfig, m: MotionConfig) -> Tensor:
    # SPEC §4: e(t) = P(|v|)·t_fly + P(0)·t_hover
    return propulsion_power(speed, e) * m.t_fly + _power_at(0.0, e) * m.t_hover


def min_return_energy(d_la: Tensor, e: EnergyConfig, m: MotionConfig) -> Tensor:
    # SPEC §7 r8: E_min = ceil(d_LA / (v_max·t_fly)) · (P(v_max)·t_fly + P(0)·t_hover)
    per_slot = _power_at(m.v_max, e) * m.t_fly + _power_at(0.0, e) * m.t_hover
    return torch.ceil(d_la / (m.v_max * m.t_fly)) * per_slot


# ----------------------------------------------------------------------------- data link


def channel(
    dcu_pos: Tensor, ge_pos: Tensor, altitude: float, tx_power: float, ch: ChannelConfig
) -> tuple[Tensor, Tensor]:
    # SPEC §3: d² = |(x,y,H)-(xi,yi,0)|², G = α/d², SNR = TP·G/N, B = log2(1+SNR)
    d2 = (dcu_pos.unsqueeze(-2) - ge_pos).square().sum(-1) + altitude**2
    snr = tx_power * (ch.alpha / d2) / ch.noise
    return snr, torch.log2(1.0 + snr)


def serve_ge(
    snr: Tensor,
    rate: Tensor,
    remaining: Tensor,
    mask: Tensor,
    threshold: float,
    t_hover: float,
    tie_noise: Tensor,
) -> tuple[Tensor, Tensor, Tensor]:
    # SPEC §3 TDMA: i* = argmax_{i: DV_i>0, SNR_i>=τ} B_i; TD = min(DV_i*, B_i*·t_hover); DV_i* -= TD
    eligible = mask & (remaining > 0) & (snr >= threshold)
    batch_shape = torch.broadcast_shapes(eligible.shape, rate.shape, tie_noise.shape)[:-1]
    if eligible.shape[-1] == 0:  # static shape, not a host sync
        td = torch.zeros(batch_shape, dtype=remaining.dtype, device=remaining.device)
        served = torch.full(batch_shape, -1, dtype=torch.int64, device=remaining.device)
        return td, served, remaining.clone()
    neg_inf = torch.tensor(-math.inf, dtype=rate.dtype, device=rate.device)
    score = torch.where(eligible, rate, neg_inf)
    best = score.amax(-1, keepdim=True)
    # exact ties at the best rate are broken by the caller's uniform noise (noise in [0, 1) > -1)
    tied = eligible & (score == best)
    pick = torch.where(tied, tie_noise.to(rate.dtype), torch.full_like(score, -1.0)).argmax(-1)
    any_eligible = eligible.any(-1)
    served = torch.where(any_eligible, pick, torch.full_like(pick, -1))
    onehot = torch.nn.functional.one_hot(pick, eligible.shape[-1]).bool() & any_eligible.unsqueeze(-1)
    dv = torch.where(onehot, remaining, torch.zeros_like(remaining)).sum(-1)
    b = torch.where(onehot, rate, torch.zeros_like(rate)).sum(-1)
    td = torch.where(any_eligible, torch.minimum(dv, b * t_hover), torch.zeros_like(dv))
    remaining_new = torch.where(onehot, remaining - td.unsqueeze(-1), remaining)
    return td, served, remaining_new


# ----------------------------------------------------------------------------- geometry


def _rect_parts(rects: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    return rects[..., 0], rects[..., 1], rects[..., 2], rects[..., 3]


def point_in_rects(p: Tensor, rects: Tensor, mask: Tensor) -> Tensor:
    # closed rectangle: x0 <= x <= x1 and y0 <= y <= y1
    x, y = p[..., 0:1], p[..., 1:2]
    x0, y0, x1, y1 = _rect_parts(rects)
    return (x >= x0) & (x <= x1) & (y >= y0) & (y <= y1) & mask


def nearest_point_in_rects(p: Tensor, rects: Tensor) -> Tensor:
    # the point of each closed rectangle nearest to p: p clamped into it ([..., R, 2] for [..., R, 4])
    lo, hi = rects[..., :2], rects[..., 2:]
    return torch.minimum(torch.maximum(p.unsqueeze(-2), lo), hi)


def point_rect_distance(p: Tensor, rects: Tensor, mask: Tensor) -> Tensor:
    # SPEC §7: d = |(max(x0-x, 0, x-x1), max(y0-y, 0, y-y1))|, 0 inside, +inf where absent
    x, y = p[..., 0:1], p[..., 1:2]
    x0, y0, x1, y1 = _rect_parts(rects)
    dx = torch.maximum(x0 - x, x - x1).clamp_min(0.0)
    dy = torch.maximum(y0 - y, y - y1).clamp_min(0.0)
    d = torch.hypot(dx, dy)
    return torch.where(mask, d, torch.full_like(d, math.inf))


def nearest_distance(dist: Tensor) -> Tensor:
    # d_nearest = min_z d_z, +inf over an empty set
    if dist.shape[-1] == 0:  # static shape, not a host sync
        return torch.full(dist.shape[:-1], math.inf, dtype=dist.dtype, device=dist.device)
    return dist.amin(-1)


def _boxes_overlap(p0: Tensor, p1: Tensor, rects: Tensor) -> Tensor:
    """The segment's bounding box meets the closed rectangle (p0, p1: [..., 2]; rects [..., 4])."""
    x0, y0, x1, y1 = _rect_parts(rects)
    ax, ay, bx, by = p0[..., 0], p0[..., 1], p1[..., 0], p1[..., 1]
    return (
        (torch.minimum(ax, bx) <= x1) & (torch.maximum(ax, bx) >= x0)
        & (torch.minimum(ay, by) <= y1) & (torch.maximum(ay, by) >= y0)
    )


def segment_hits_rects(p0: Tensor, p1: Tensor, rects: Tensor, mask: Tensor) -> Tensor:
    # Separating axes of a segment and a closed box: the box's x and y axes (bounding boxes
    # overlap) and the segment's normal (the corners are not all strictly on one side of its line).
    x0, y0, x1, y1 = _rect_parts(rects)
    ax, ay = p0[..., 0:1], p0[..., 1:2]
    bx, by = p1[..., 0:1], p1[..., 1:2]
    boxes = _boxes_overlap(p0.unsqueeze(-2), p1.unsqueeze(-2), rects)
    dx, dy = bx - ax, by - ay
    # side of corner (x, y): dx·(y - ay) - dy·(x - ax); extremes over the four corners
    cy0, cy1 = dx * (y0 - ay), dx * (y1 - ay)
    cx0, cx1 = dy * (x0 - ax), dy * (x1 - ax)
    lo = torch.minimum(cy0, cy1) - torch.maximum(cx0, cx1)
    hi = torch.maximum(cy0, cy1) - torch.minimum(cx0, cx1)
    return boxes & (lo <= 0) & (hi >= 0) & mask


def boundary_distance(p: Tensor, x_size: float, y_size: float) -> Tensor:
    # SPEC §7 r6: d = min(x, X-x, y, Y-y) inside A, 0 outside
    x, y = p[..., 0], p[..., 1]
    d = torch.minimum(torch.minimum(x, x_size - x), torch.minimum(y, y_size - y))
    return d.clamp_min(0.0)


def outside_area(p: Tensor, x_size: float, y_size: float) -> Tensor:
    # SPEC §5 boundary exit: L ∉ [0, X] × [0, Y]
    x, y = p[..., 0], p[..., 1]
    return (x < 0) | (x > x_size) | (y < 0) | (y > y_size)


def clip_to_area(p: Tensor, x_size: float, y_size: float) -> Tensor:
    # SPEC §5: the position is clipped back into [0, X] × [0, Y]
    return torch.stack((p[..., 0].clamp(0.0, x_size), p[..., 1].clamp(0.0, y_size)), dim=-1)


def closest_approach(p0: Tensor, v: Tensor, q0: Tensor, u: Tensor, t_fly: float) -> Tensor:
    # SPEC §5: min_{s in [0, t_fly]} |r0 + w s| with r0 = p0 - q0, w = v - u; s* = clip(-r0·w / |w|², 0, t_fly)
    r0 = p0.unsqueeze(-2) - q0
    w = v.unsqueeze(-2) - u
    w2 = w.square().sum(-1, keepdim=True)
    s = torch.where(w2 > 0, -(r0 * w).sum(-1, keepdim=True) / torch.where(w2 > 0, w2, torch.ones_like(w2)), 0.0)
    s = s.clamp(0.0, t_fly)
    return torch.linalg.vector_norm(r0 + w * s, dim=-1)


# ----------------------------------------------------------------------------- other UAVs


def _heading_velocity(speed: Tensor, heading: Tensor) -> Tensor:
    # v = speed · (cos θ, sin θ)
    return torch.stack((speed * torch.cos(heading), speed * torch.sin(heading)), dim=-1)


def _ou_move_ok(
    pos: Tensor, vel: Tensor, blocked: Tensor, blocked_mask: Tensor, x_size: float, y_size: float, t_fly: float
) -> Tensor:
    """True where the OU move pos -> pos + vel·t_fly meets no blocked rectangle and ends inside A."""
    end = pos + vel * t_fly
    hits = segment_hits_rects(pos, end, blocked.unsqueeze(-3), blocked_mask.unsqueeze(-2))  # [..., K, Z]
    return ~hits.any(-1) & ~outside_area(end, x_size, y_size)


def _retry_headings(
    pos: Tensor, v: Tensor, headings: Tensor, blocked: Tensor, blocked_mask: Tensor,
    x_size: float, y_size: float, t_fly: float,
) -> Tensor:
    """For every OU, the velocity of the first of ``headings`` ([T, ..., K]) at the same speed
    whose move is valid, else 0 (hover)."""
    speed = torch.linalg.vector_norm(v, dim=-1)
    tries = _heading_velocity(speed.expand_as(headings), headings)  # [T, ..., K, 2]
    tries_ok = _ou_move_ok(pos, tries, blocked, blocked_mask, x_size, y_size, t_fly)  # [T, ..., K]
    first = tries_ok.to(torch.uint8).argmax(0)  # argmax returns the first maximum
    chosen = torch.gather(tries, 0, first[None, ..., None].expand(1, *tries.shape[1:])).squeeze(0)
    return torch.where(tries_ok.any(0).unsqueeze(-1), chosen, torch.zeros_like(chosen))


def ou_noise(
    shape: torch.Size | tuple[int, ...], ou: OUConfig, m: MotionConfig, generator: torch.Generator,
    device: torch.device | str | None = None, dtype: torch.dtype = torch.float32,
) -> dict[str, Tensor]:
    """The random draws of one OU slot for OUs of shape ``[..., K]``, in this order: turn flags,
    speeds, headings, retry headings ``[heading_tries, ..., K]``. Every tensor is drawn every
    slot, so the random stream depends on the seed only, not on the data."""
    shape = torch.Size(shape)

    def u(*s: int) -> Tensor:
        return torch.rand(s, generator=generator, device=device, dtype=dtype)

    return {
        "turn": u(*shape) < ou.p_turn,
        "speed": u(*shape) * m.v_max,
        "heading": u(*shape) * (2.0 * math.pi),
        "retry_heading": u(ou.heading_tries, *shape) * (2.0 * math.pi),
    }


def ou_step(
    pos: Tensor,
    vel: Tensor,
    mask: Tensor,
    blocked: Tensor,
    blocked_mask: Tensor,
    x_size: float,
    y_size: float,
    ou: OUConfig,
    m: MotionConfig,
    generator: torch.Generator | None = None,
    noise: dict[str, Tensor] | None = None,
) -> tuple[Tensor, Tensor]:
    # SPEC §2: OU velocity redraw with prob p_turn, heading retries around BZ/NFZ/area edge, L' = L + v·t_fly
    if noise is None:
        noise = ou_noise(pos.shape[:-1], ou, m, generator, pos.device, pos.dtype)
    turn, new_speed, new_heading = noise["turn"], noise["speed"], noise["heading"]
    retry_heading = noise["retry_heading"]

    turned = _heading_velocity(new_speed, new_heading)
    v = torch.where(turn.unsqueeze(-1), turned, vel)
    ok = _ou_move_ok(pos, v, blocked, blocked_mask, x_size, y_size, m.t_fly)

    # a blocked move keeps its speed and tries new headings, the first valid one wins
    v = torch.where(ok.unsqueeze(-1), v, _retry_headings(pos, v, retry_heading, blocked, blocked_mask, x_size, y_size, m.t_fly))

    present = mask.unsqueeze(-1)
    new_pos = torch.where(present, pos + v * m.t_fly, pos)
    new_vel = torch.where(present, v, vel)
    return new_pos, new_vel


# ----------------------------------------------------------------------------- reward and cost


def reward_terms(
    *,
    collected: Tensor,
    d_ou: Tensor,
    d_bz: Tensor,
    d_nfz: Tensor,
    rz_speeding_excess: Tensor,
    d_boundary: Tensor,
    outside: Tensor,
    d_la: Tensor,
    all_collected: Tensor,
    energy_left: Tensor,
    e_min: Tensor,
    landed: Tensor,
    crashed: Tensor,
    cfg: EnvConfig,
) -> dict[str, Tensor]:
    # SPEC §7, Eq. (10): r = r1 + ... + r9 (+ landing bonus, crash penalty), each term weighted and signed
    s1, s2, s3, s4, s5, s6, s7, s8, s9 = cfg.reward.sigma
    d_min, d_safe = cfg.safety.d_min, cfg.safety.d_safe
    d_tar = cfg.reward.d_tar
    inputs = (collected, d_ou, d_bz, d_nfz, rz_speeding_excess, d_boundary, outside, d_la,
              all_collected, energy_left, e_min, landed, crashed)
    shape = torch.broadcast_shapes(*(t.shape for t in inputs))
    dtype = energy_left.dtype if energy_left.is_floating_point() else torch.get_default_dtype()
    zero = torch.zeros(shape, dtype=dtype, device=energy_left.device)

    def on(flag: Tensor, value: float | Tensor) -> Tensor:
        return torch.where(flag, value, zero)

    low_energy = energy_left < e_min
    if cfg.reward.r7_variant == "as_printed":
        # r7 as printed: -σ7(1 - d_LA/d_tar) for d_LA < d_tar
        r7 = on(d_la < d_tar, -s7 * (1.0 - d_la / d_tar))
    else:
        # r7 corrected: -σ7·min(d_LA, d_tar)/d_tar once all data is collected or E < E_min
        r7 = on(all_collected | low_energy, -s7 * d_la.clamp_max(d_tar) / d_tar)
    # r8: -σ8 (E_min - E)/E_min when E < E_min (E_min = 0 at LA: nothing to penalise)
    short = low_energy & (e_min > 0)
    r8 = on(short, -s8 * (e_min - energy_left) / torch.where(e_min > 0, e_min, torch.ones_like(e_min)))
    return {
        "r1": on(collected, s1),
        "r2": zero - s2 * ramp(d_ou, d_min, d_safe),
        "r3": zero - s3 * ramp(d_bz, d_min, d_safe),
        "r4": zero - s4 * ramp(d_nfz, d_min, d_safe),
        "r5": zero - s5 * rz_speeding_excess,
        "r6": torch.where(outside, -s6 + zero, -s6 * ramp(d_boundary, d_min, d_safe)),
        "r7": r7,
        "r8": r8,
        "r9": zero - s9,
        "landing": on(landed, cfg.reward.landing_bonus),
        "crash": on(crashed, -cfg.reward.crash_penalty),
    }


def cost(events: dict[str, Tensor], c: CostConfig) -> Tensor:
    # SPEC §7 CPO cost: c_t = Σ_k w_k · 1[event_k], k in boundary exit, OU collision, BZ collision, NFZ entry
    # (and RZ speeding, at weight 0 unless configured: adding 0 leaves the paper's sum bit for bit)
    total = None
    for name in COST_EVENTS:
        term = getattr(c, name) * events[name].to(torch.get_default_dtype())
        total = term if total is None else total + term
    return total
