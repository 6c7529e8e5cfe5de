"""One slot of the world as a pure function of tensors (docs/model.md §2-§7).

``world_step`` takes the raw state (a dict of tensors with leading batch shape ``[B]``), the
action and a ``torch.Generator`` and returns the next state, the events, every reward term,
the cost and the termination flags. Nothing here knows about TorchRL: ``UAVEnv`` only moves
these dicts in and out of its tensordicts.
"""

from __future__ import annotations

import torch
from torch import Tensor

from uavlae.envs import geodesic as geo
from uavlae.envs import physics as ph
from uavlae.envs.config import EnvConfig
from uavlae.envs.maps import MAP_CHANNELS, dcu_maps

# The raw state, one row per entry: its shape after the batch dimension B (in the padded sizes
# G GEs, K OUs, NFZ / RZ / BZ zones of each kind, H·W geodesic grid cells), its dtype, whether it
# is fixed for the episode, and what it holds. The env's specs, the step's key lists and
# docs/env_contract.md (tests/test_env.py checks it) all come from this table.
STATE_TABLE: tuple[tuple[str, tuple[int | str, ...], torch.dtype, bool, str], ...] = (
    ("nfz", ("NFZ", 4), torch.float32, True, "no-fly zones, (x0, y0, x1, y1)"),
    ("nfz_mask", ("NFZ",), torch.bool, True, "present no-fly zones"),
    ("rz", ("RZ", 4), torch.float32, True, "residential zones"),
    ("rz_mask", ("RZ",), torch.bool, True, "present residential zones"),
    ("bz", ("BZ", 4), torch.float32, True, "building zones"),
    ("bz_mask", ("BZ",), torch.bool, True, "present building zones"),
    ("ge_pos", ("G", 2), torch.float32, True, "GE positions"),
    ("ge_mask", ("G",), torch.bool, True, "present GEs"),
    ("takeoff", (4,), torch.float32, True, "TA rectangle"),
    ("landing", (4,), torch.float32, True, "LA rectangle"),
    ("data_total", (), torch.float32, True, "data volume of all GEs at the start"),
    ("position", (2,), torch.float32, False, "DCU position"),
    ("velocity", (2,), torch.float32, False, "DCU velocity in the last slot"),
    ("energy_used", (), torch.float32, False, "cumulative energy, J"),
    ("energy_left", (), torch.float32, False, "E_limit - energy_used"),
    ("slot_data", (), torch.float32, False, "data collected in the last slot"),
    ("data_collected", (), torch.float32, False, "data collected so far"),
    ("step", (), torch.int64, False, "slots since the reset"),
    ("ge_remaining", ("G",), torch.float32, False, "data left at each GE"),
    ("ou_pos", ("K", 2), torch.float32, False, "OU positions"),
    ("ou_vel", ("K", 2), torch.float32, False, "OU velocities"),
    ("ou_mask", ("K",), torch.bool, False, "present OUs"),
    ("served_ge", (), torch.int64, False, "GE served in the last slot, -1 none"),
    ("d_bz", (), torch.float32, False, "distance to the nearest BZ (0 inside, +inf when none)"),
    ("d_nfz", (), torch.float32, False, "distance to the nearest NFZ"),
    ("d_rz", (), torch.float32, False, "distance to the nearest RZ"),
    ("d_ou", (), torch.float32, False, "distance to the nearest OU"),
    ("d_boundary", (), torch.float32, False, "distance to the area boundary (0 outside)"),
    ("d_la", (), torch.float32, False, "distance to LA (0 inside)"),
)
GEO_KEY = "geo_field"  # only when uses_geodesic(cfg)
GEO_ROW = (GEO_KEY, ("G+1", "H·W"), torch.float32, True,
           "distance fields to LA and each GE, with reward.progress_metric: geodesic")
STATIC_KEYS = tuple(row[0] for row in STATE_TABLE if row[3])
DYNAMIC_KEYS = tuple(row[0] for row in STATE_TABLE if not row[3])
STATE_KEYS = STATIC_KEYS + DYNAMIC_KEYS


def uses_geodesic(cfg: EnvConfig) -> bool:
    return cfg.reward.progress_metric == "geodesic" and (cfg.reward.progress_weight > 0 or cfg.ego_features)


def state_keys(cfg: EnvConfig) -> tuple[str, ...]:
    """The raw state entries of this configuration: ``STATE_KEYS``, plus ``geo_field`` when the
    geodesic progress metric is in use."""
    return STATE_KEYS + ((GEO_KEY,) if uses_geodesic(cfg) else ())


def state_shapes(cfg: EnvConfig) -> dict[str, tuple[tuple[int, ...], torch.dtype]]:
    """``{key: (shape after the batch dimension, dtype)}`` of this configuration's raw state."""
    h, w = geo.grid_shape(cfg)
    g = cfg.ge.count.padded
    size = {"G": g, "K": cfg.ou.count.padded, "NFZ": cfg.zones.n_nfz.padded, "RZ": cfg.zones.n_rz.padded,
            "BZ": cfg.zones.n_bz.padded, "G+1": g + 1, "H·W": h * w}
    rows = {row[0]: row for row in (*STATE_TABLE, GEO_ROW)}
    return {k: (tuple(size.get(d, d) for d in rows[k][1]), rows[k][2]) for k in state_keys(cfg)}


def state_table_markdown() -> str:
    """The raw state as the Markdown table of ``docs/env_contract.md``."""
    lines = ["| key | shape | dtype | fixed per episode | holds |", "|---|---|---|---|---|"]
    for key, shape, dtype, static, what in (*STATE_TABLE, GEO_ROW):
        dims = ", ".join(["B", *map(str, shape)])
        lines.append(f"| `{key}` | `[{dims}]` | {str(dtype).removeprefix('torch.')} | {'yes' if static else 'no'} | {what} |")
    return "\n".join(lines)


ZONE_KINDS = ("nfz", "rz", "bz")  # the order of the zones in the observation, both frames
EVENT_KEYS = (
    "bz_collision", "nfz_entry", "ou_collision", "boundary_exit", "rz_speeding", "landed",
    "energy_exhausted",
)
REWARD_KEYS = ("r1", "r2", "r3", "r4", "r5", "r6", "r7", "r8", "r9", "landing", "crash", "progress")


def _rect_tensor(rect, batch: int, device, dtype=torch.float32) -> Tensor:
    return torch.tensor(rect, device=device, dtype=dtype).expand(batch, 4).clone()


def nearest_distances(state: dict[str, Tensor], cfg: EnvConfig) -> dict[str, Tensor]:
    """Distances from the DCU to the nearest BZ, NFZ, RZ, OU, boundary and LA (0 inside)."""
    p = state["position"]
    d_ou = torch.linalg.vector_norm(state["ou_pos"] - p.unsqueeze(-2), dim=-1)
    d_ou = d_ou.masked_fill(~state["ou_mask"], float("inf"))
    la = state["landing"].unsqueeze(-2)
    la_mask = torch.ones(la.shape[:-1], dtype=torch.bool, device=p.device)
    return {
        "d_bz": ph.nearest_distance(ph.point_rect_distance(p, state["bz"], state["bz_mask"])),
        "d_nfz": ph.nearest_distance(ph.point_rect_distance(p, state["nfz"], state["nfz_mask"])),
        "d_rz": ph.nearest_distance(ph.point_rect_distance(p, state["rz"], state["rz_mask"])),
        "d_ou": ph.nearest_distance(d_ou),
        "d_boundary": ph.boundary_distance(p, cfg.area.x_size, cfg.area.y_size),
        "d_la": ph.point_rect_distance(p, la, la_mask).squeeze(-1),
    }


def current_target(state: dict[str, Tensor]) -> tuple[Tensor, Tensor, Tensor]:
    """The DCU's current goal: the nearest GE with data left, or LA once every GE is empty.

    Returns ``(vector from the DCU to the target point, distance to the target, GEs with data
    left)``. The target point is the GE itself, or the nearest point of LA (distance 0 inside).
    """
    p = state["position"]
    has = state["ge_remaining"] > 0
    n_left = has.sum(-1)
    rel_ge = state["ge_pos"] - p.unsqueeze(-2)
    d_ge = torch.linalg.vector_norm(rel_ge, dim=-1).masked_fill(~has, float("inf"))
    if d_ge.shape[-1] > 0:
        near = d_ge.argmin(-1, keepdim=True)
        rel_near = torch.gather(rel_ge, -2, near.unsqueeze(-1).expand(*near.shape, 2)).squeeze(-2)
    else:
        rel_near = torch.zeros_like(p)
    rel_la = ph.nearest_point_in_rects(p, state["landing"].unsqueeze(-2)).squeeze(-2) - p
    rel = torch.where((n_left > 0).unsqueeze(-1), rel_near, rel_la)
    return rel, torch.linalg.vector_norm(rel, dim=-1), n_left


def progress_potential(state: dict[str, Tensor], cfg: EnvConfig) -> Tensor:
    """Φ(s) = −(distance to the current target + d_tar · GEs with data left) / d_tar.

    Finishing a GE raises Φ by 1 minus the (≤ d_tar) jump to the next target, so Φ only
    rises with real progress; the ``progress`` reward term is w·(Φ(s') − Φ(s)). The distance is
    the straight line, or with ``progress_metric: geodesic`` the way around BZs and NFZs.
    """
    d_tar = cfg.reward.d_tar
    if GEO_KEY in state:
        d, n_left = geo.geodesic_distance(state, cfg)  # the direction is not needed here
    else:
        _, d, n_left = current_target(state)
    return -(d + d_tar * n_left.to(d.dtype)) / d_tar


def rect_vectors(p: Tensor, rects: Tensor) -> Tensor:
    """Vector from ``p`` ``[..., 2]`` to the nearest point of each rectangle ``[..., R, 4]``:
    ``[..., R, 2]``, 0 inside."""
    return ph.nearest_point_in_rects(p, rects) - p.unsqueeze(-2)


def nearest_rect_vector(p: Tensor, rects: Tensor, mask: Tensor) -> Tensor:
    """Vector from ``p`` to the nearest point of the nearest present rectangle (0 inside; 0
    when none is present)."""
    if rects.shape[-2] == 0:
        return torch.zeros_like(p)
    vec = rect_vectors(p, rects)
    d = torch.linalg.vector_norm(vec, dim=-1).masked_fill(~mask, float("inf"))
    near = d.argmin(-1, keepdim=True)
    out = torch.gather(vec, -2, near.unsqueeze(-1).expand(*near.shape, 2)).squeeze(-2)
    return out * mask.any(-1, keepdim=True).to(p.dtype)


def saturate(vec: Tensor, scale: float) -> Tensor:
    """``vec`` ``[..., 2]`` with its length capped at ``scale``, its direction kept."""
    n = torch.linalg.vector_norm(vec, dim=-1, keepdim=True)
    return vec * (scale / n.clamp_min(scale))


def unit_vector(vec: Tensor, length: Tensor) -> Tensor:
    """``vec / length`` (``length`` its norm, ``[...]``); 0 for a zero vector, not NaN."""
    return vec / length.clamp_min(1e-6).unsqueeze(-1)


def sort_order(*keys: Tensor) -> Tensor:
    """Indices that sort the last dimension by ``keys[0]``, its ties by ``keys[1]``, and so on.

    Stable sorts from the least significant key up compose to the lexicographic order."""
    order = torch.argsort(keys[-1], dim=-1, stable=True)
    for key in reversed(keys[:-1]):
        order = torch.gather(order, -1, torch.argsort(torch.gather(key, -1, order), dim=-1, stable=True))
    return order


def take(x: Tensor, order: Tensor) -> Tensor:
    """``x`` ``[..., N]`` or ``[..., N, C]`` with its entities (dimension N) in ``order`` ``[..., N]``."""
    if x.dim() == order.dim():
        return torch.gather(x, -1, order)
    return torch.gather(x, -2, order.unsqueeze(-1).expand(*order.shape, x.shape[-1]))


def initial_state(scen: dict[str, Tensor], cfg: EnvConfig) -> dict[str, Tensor]:
    """The state at the start of an episode from a batched scenario (docs/env_contract.md)."""
    start = scen["start"]
    b, device = start.shape[0], start.device
    zeros = torch.zeros(b, device=device, dtype=start.dtype)
    ge_data = scen["ge_data"] * scen["ge_mask"]
    state = {
        "nfz": scen["nfz"], "nfz_mask": scen["nfz_mask"],
        "rz": scen["rz"], "rz_mask": scen["rz_mask"],
        "bz": scen["bz"], "bz_mask": scen["bz_mask"],
        "ge_pos": scen["ge_pos"], "ge_mask": scen["ge_mask"],
        "takeoff": _rect_tensor(cfg.area.takeoff, b, device),
        "landing": _rect_tensor(cfg.area.landing, b, device),
        "data_total": ge_data.sum(-1),
        "position": start.clone(),
        "velocity": torch.zeros_like(start),
        "energy_used": zeros.clone(),
        "energy_left": torch.full_like(zeros, cfg.energy.e_limit),
        "slot_data": zeros.clone(),
        "data_collected": zeros.clone(),
        "step": torch.zeros(b, device=device, dtype=torch.int64),
        "ge_remaining": ge_data.clone(),
        "ou_pos": scen["ou_pos"].clone(),
        "ou_vel": scen["ou_vel"] * scen["ou_mask"].unsqueeze(-1),
        "ou_mask": scen["ou_mask"],
        "served_ge": torch.full((b,), -1, device=device, dtype=torch.int64),
    }
    state.update(nearest_distances(state, cfg))
    if uses_geodesic(cfg):
        state[GEO_KEY] = geo.distance_fields(state, cfg)
    return state


def draw_noise(state: dict[str, Tensor], cfg: EnvConfig, generator: torch.Generator) -> dict[str, Tensor]:
    """Every random number one slot needs, drawn from the env's generator (outside the pure step):
    the OU draws (physics.ou_noise), then the GE tie-break noise."""
    ou_pos, ge = state["ou_pos"], state["ge_pos"]
    noise = ph.ou_noise(ou_pos.shape[:-1], cfg.ou, cfg.motion, generator, ou_pos.device, ou_pos.dtype)
    noise["ge_tie"] = torch.rand(ge.shape[:-1], generator=generator, device=ge.device, dtype=ge.dtype)
    return noise


def world_step(
    state: dict[str, Tensor], action: Tensor, cfg: EnvConfig, generator: torch.Generator
) -> tuple[dict[str, Tensor], dict[str, Tensor], dict[str, Tensor], Tensor, Tensor, Tensor]:
    """Advance every batch element by one slot Δt = t_fly + t_hover.

    Returns ``(next_state, events, reward_terms, cost, terminated, truncated)``; events and
    flags are bool ``[B]``, reward terms and cost float ``[B]``.
    """
    return world_step_core(state, action, draw_noise(state, cfg, generator), cfg)


def world_step_core(
    state: dict[str, Tensor], action: Tensor, noise: dict[str, Tensor], cfg: EnvConfig
) -> tuple[dict[str, Tensor], dict[str, Tensor], dict[str, Tensor], Tensor, Tensor, Tensor]:
    """``world_step`` with its random draws given: deterministic, and ``torch.compile``-able."""
    m, a = cfg.motion, cfg.area
    p0 = state["position"]
    # Eq. (1): L_{t+1} = L_t + v t_fly, |v| <= v_max
    v = ph.action_to_velocity(action, m.v_max)
    speed = torch.linalg.vector_norm(v, dim=-1)
    p1_raw = p0 + v * m.t_fly
    boundary_exit = ph.outside_area(p1_raw, a.x_size, a.y_size)
    p1 = ph.clip_to_area(p1_raw, a.x_size, a.y_size)

    # Other UAVs move during the same flight phase; collisions use the closest approach.
    ou_pos, ou_mask = state["ou_pos"], state["ou_mask"]
    blocked = torch.cat([state["bz"], state["nfz"]], dim=-2)
    blocked_mask = torch.cat([state["bz_mask"], state["nfz_mask"]], dim=-1)
    ou_new, ou_vel = ph.ou_step(
        ou_pos, state["ou_vel"], ou_mask, blocked, blocked_mask, a.x_size, a.y_size, cfg.ou, m, noise=noise
    )
    ou_u = (ou_new - ou_pos) / m.t_fly
    approach = ph.closest_approach(p0, v, ou_pos, ou_u, m.t_fly)
    ou_collision = ((approach < cfg.safety.r_coll) & ou_mask).any(-1)
    bz_collision = ph.segment_hits_rects(p0, p1_raw, state["bz"], state["bz_mask"]).any(-1)
    nfz_entry = ph.segment_hits_rects(p0, p1_raw, state["nfz"], state["nfz_mask"]).any(-1)
    in_rz = ph.segment_hits_rects(p0, p1_raw, state["rz"], state["rz_mask"]).any(-1)
    # a tolerance of 1e-4 m/s so that flying exactly at v_limit (rounded in float32) is legal
    rz_speeding = in_rz & (speed > m.v_limit + 1e-4)

    # Hover phase at L_{t+1}: TDMA service of at most one GE (SPEC §3).
    tie = noise["ge_tie"]
    snr, rate = ph.channel(p1, state["ge_pos"], a.altitude, cfg.ge.tx_power, cfg.channel)
    td, served, remaining = ph.serve_ge(
        snr, rate, state["ge_remaining"], state["ge_mask"], cfg.channel.snr_threshold, m.t_hover, tie
    )
    energy_used = state["energy_used"] + ph.slot_energy(speed, cfg.energy, m)
    energy_left = cfg.energy.e_limit - energy_used
    data_collected = state["data_collected"] + td

    nxt = {k: state[k] for k in STATIC_KEYS}
    if GEO_KEY in state:
        nxt[GEO_KEY] = state[GEO_KEY]
    nxt.update(
        position=p1, velocity=v, energy_used=energy_used, energy_left=energy_left, slot_data=td,
        data_collected=data_collected, step=state["step"] + 1, ge_remaining=remaining,
        ou_pos=ou_new, ou_vel=ou_vel, ou_mask=ou_mask, served_ge=served,
    )
    nxt.update(nearest_distances(nxt, cfg))

    all_collected = ~(remaining > 0).any(-1)
    in_la = ph.point_in_rects(p1, nxt["landing"].unsqueeze(-2), torch.ones_like(speed, dtype=torch.bool).unsqueeze(-1)).squeeze(-1)
    collided = bz_collision | nfz_entry | ou_collision
    crashed = collided & cfg.terminate_on_collision
    landed = in_la & ((speed <= m.v_land) | all_collected) & ~crashed
    energy_exhausted = energy_left <= 0
    terminated = landed | energy_exhausted | crashed
    truncated = (nxt["step"] >= cfg.t_max) & ~terminated

    events = {
        "bz_collision": bz_collision, "nfz_entry": nfz_entry, "ou_collision": ou_collision,
        "boundary_exit": boundary_exit, "rz_speeding": rz_speeding, "landed": landed,
        "energy_exhausted": energy_exhausted,
    }
    e_min = ph.min_return_energy(nxt["d_la"], cfg.energy, m)
    excess = torch.where(rz_speeding, (speed - m.v_limit) / (m.v_max - m.v_limit), torch.zeros_like(speed))
    terms = ph.reward_terms(
        collected=td > 0, d_ou=nxt["d_ou"], d_bz=nxt["d_bz"], d_nfz=nxt["d_nfz"],
        rz_speeding_excess=excess, d_boundary=nxt["d_boundary"], outside=boundary_exit,
        d_la=nxt["d_la"], all_collected=all_collected, energy_left=energy_left, e_min=e_min,
        landed=landed, crashed=crashed, cfg=cfg,
    )
    w = cfg.reward.progress_weight
    if w > 0:  # static: the branch costs nothing when the term is off
        terms["progress"] = w * (progress_potential(nxt, cfg) - progress_potential(state, cfg))
    else:
        terms["progress"] = torch.zeros_like(energy_left)
    cost = ph.cost(events, cfg.cost)
    return nxt, events, terms, cost, terminated, truncated


class ObservationLayout:
    """Normalisation constants and sizes of the flat observation (SPEC §6), in one of two frames
    (``env.obs_frame``).

    ``world`` (the default) is the paper's o_t: absolute GE positions, zone rectangles by their
    absolute corner and sides, the DCU's own position, TA and LA, every entity at its index.

    ``ego`` [decision] holds the same information relative to the DCU, translated only (the axes
    stay east and north: a heading-rotated frame is undefined while the DCU hovers, and the action
    is a world-frame velocity), each kind of entity sorted so that no column depends on an
    entity's index:

    - every GE: its vector from the DCU / diagonal, data left / ``ge.data_max``, a has-data flag
      and a presence flag; those with data left first, then the emptied ones, each nearest first,
      the absent ones last as zeros;
    - every NFZ, RZ and BZ: its rectangle relative to the DCU, (x0-px, y0-py, x1-px, y1-py) /
      area side, the vector to its nearest point (0 inside) saturated at ``obs_distance_scale``
      and divided by it, an inside flag and a presence flag; per kind nearest first (ties, as
      inside overlapping RZs, by the distance to the centre), the absent ones last as zeros;
    - the boundary: the distances to the west, east, south and north edges / area side; LA: its
      rectangle relative to the DCU / area side, the vector to its nearest point / diagonal, an
      in-LA flag;
    - the OUs within the perception radius as in ``world`` (they are relative there already);
    - energy left / E_limit, velocity / v_max, the last slot's data / ``ge.data_max``, the slots
      left (1 - step / t_max);
    - the current target (``current_target``: the nearest GE with data, else LA's nearest point)
      as its unit direction and its distance / diagonal.

    ``extra_features`` and ``ego_features`` append their columns after either frame's. In the
    ``ego`` frame the extra columns are mostly redundant (the zone vectors hold the distances, the
    LA vector the distance to LA) and the ego columns repeat the target and the nearest BZ and NFZ
    vectors, except with ``reward.progress_metric: geodesic``, where the target column reads a
    planner's distance field: a training-only aid either way.

    With ``env.maps.enabled`` the observation is the flat one (``flat_size`` columns) followed by
    the local and the global map of :func:`uavlae.envs.maps.dcu_maps`, each flattened in its
    ``[C, S, S]`` order (``map_shapes``); ``size`` counts them all."""

    def __init__(self, cfg: EnvConfig):
        self.cfg = cfg
        self.frame = cfg.obs_frame
        self.n_ge = cfg.ge.count.padded
        self.n_ou = cfg.ou.count.padded
        self.n_zone = (cfg.zones.n_nfz.padded, cfg.zones.n_rz.padded, cfg.zones.n_bz.padded)
        self.extra = cfg.extra_features
        self.ego = cfg.ego_features
        # the kind (index into ZONE_KINDS) of each zone of the three kinds concatenated
        self._zone_kind = torch.repeat_interleave(torch.arange(3), torch.tensor(self.n_zone))
        spec = self._column_spec()
        self._columns, i = {}, 0
        for name, divisors in spec:
            self._columns[name] = slice(i, i + len(divisors))
            i += len(divisors)
        self._divisor = self._column_divisors(spec)
        self.flat_size = self._divisor.numel()
        m = cfg.maps
        c = len(MAP_CHANNELS)
        self.map_shapes = ((c, m.local_size, m.local_size), (c, m.global_size, m.global_size)) if m.enabled else ()
        self.size = self.flat_size + sum(a * b * d for a, b, d in self.map_shapes)

    def columns(self) -> dict[str, slice]:
        """Where the parts of the flat observation lie: ``{name: slice of columns}`` in
        :meth:`build`'s order; the names are the frame's (``_world_spec``, ``_ego_frame_spec``),
        then ``extra`` and the ``ego_features`` columns when on."""
        return dict(self._columns)

    def _column_spec(self) -> list[tuple[str, list[float]]]:
        """Every part of the flat observation in :meth:`build`'s order: its name and the
        normalising divisor of each of its columns (1 for flags and counts)."""
        cfg = self.cfg
        a, scale = cfg.area, cfg.obs_distance_scale
        spec = self._world_spec() if self.frame == "world" else self._ego_frame_spec()
        if self.extra:
            spec.append(("extra", [scale] * 4 + [a.diagonal, 1.0]))
        if self.ego:
            # target vector / diagonal, its unit direction, nearest BZ and NFZ point vectors
            # (saturated at obs_distance_scale, divided by it)
            spec += [("target", [a.diagonal] * 2), ("target_dir", [1.0] * 2), ("bz_vec", [scale] * 2),
                     ("nfz_vec", [scale] * 2)]
        return spec

    def _ou_spec(self) -> list[tuple[str, list[float]]]:
        # the same in both frames: the OUs are relative to the DCU in the paper's o_t already
        k, pr = self.n_ou, self.cfg.safety.perception_radius
        return [("ou_rel", [pr] * (2 * k)), ("ou_vel", [self.cfg.motion.v_max] * (2 * k)), ("ou_seen", [1.0] * k)]

    def _world_spec(self) -> list[tuple[str, list[float]]]:
        cfg = self.cfg
        a, m, g = cfg.area, cfg.motion, self.n_ge
        xy, xyxy = [a.x_size, a.y_size], [a.x_size, a.y_size, a.x_size, a.y_size]
        spec = [("ge_pos", xy * g), ("ge_data", [cfg.ge.data_max] * g), ("ge_tp", [1.0] * g), ("ge_present", [1.0] * g)]
        for name, n in zip(ZONE_KINDS, self.n_zone):
            spec += [(name, xyxy * n), (f"{name}_present", [1.0] * n)]
        return spec + self._ou_spec() + [
            ("position", xy), ("velocity", [m.v_max] * 2), ("energy_left", [cfg.energy.e_limit]),
            ("slot_data", [cfg.ge.data_max]), ("takeoff", xyxy), ("landing", xyxy),
        ]

    def _ego_frame_spec(self) -> list[tuple[str, list[float]]]:
        cfg = self.cfg
        a, g, d, scale = cfg.area, self.n_ge, cfg.area.diagonal, cfg.obs_distance_scale
        xyxy = [a.x_size, a.y_size, a.x_size, a.y_size]
        spec = [("ge_rel", [d] * (2 * g)), ("ge_data", [cfg.ge.data_max] * g), ("ge_has_data", [1.0] * g),
                ("ge_present", [1.0] * g)]
        for name, n in zip(ZONE_KINDS, self.n_zone):
            spec += [(f"{name}_rel", xyxy * n), (f"{name}_near", [scale] * (2 * n)), (f"{name}_inside", [1.0] * n),
                     (f"{name}_present", [1.0] * n)]
        spec += [("boundary", [a.x_size, a.x_size, a.y_size, a.y_size]), ("landing_rel", xyxy),
                 ("landing_near", [d] * 2), ("in_landing", [1.0])]
        return spec + self._ou_spec() + [
            ("energy_left", [cfg.energy.e_limit]), ("velocity", [cfg.motion.v_max] * 2),
            ("slot_data", [cfg.ge.data_max]), ("slots_left", [float(cfg.t_max)]),
            ("goal_dir", [1.0] * 2), ("goal_dist", [d]),
        ]

    @staticmethod
    def _column_divisors(spec: list[tuple[str, list[float]]]) -> Tensor:
        """The normalising divisor of every observation column, in the order ``build`` lays out
        the raw columns: one division of the whole row at the end gives exactly the per-part
        divisions, at a fraction of the cost."""
        return torch.tensor([x for _, divisors in spec for x in divisors], dtype=torch.float64)

    def build(self, s: dict[str, Tensor]) -> Tensor:
        """The normalised observation ``[B, size]`` of the raw state ``s`` (SPEC §6), the maps last."""
        p = s["position"]
        frame = self._base_parts(s) if self.frame == "world" else self._ego_frame_parts(s)
        parts = frame + self._extra_parts(s) + self._ego_parts(s)
        flat = torch.cat(parts, dim=-1) / self._divisor.to(device=p.device, dtype=p.dtype)
        if not self.map_shapes:
            return flat
        return torch.cat([flat, *(m.flatten(1) for m in dcu_maps(s, self.cfg))], dim=-1)

    def _ou_parts(self, s: dict[str, Tensor]) -> list[Tensor]:
        """The OUs inside the perception radius, nearest first: relative position, velocity, flag
        (``[..., 2K]``, ``[..., 2K]``, ``[..., K]``)."""
        p = s["position"]
        rel = s["ou_pos"] - p.unsqueeze(-2)
        dist = torch.linalg.vector_norm(rel, dim=-1)
        visible = s["ou_mask"] & (dist <= self.cfg.safety.perception_radius)
        order = torch.argsort(dist.masked_fill(~visible, float("inf")), dim=-1, stable=True)
        vis = torch.gather(visible, -1, order).to(p.dtype)
        # (x / scale) * vis == (x * vis) / scale exactly: vis is 0 or 1
        rel = take(rel, order) * vis.unsqueeze(-1)
        vel = take(s["ou_vel"], order) * vis.unsqueeze(-1)
        return [rel.flatten(-2), vel.flatten(-2), vis]

    def _base_parts(self, s: dict[str, Tensor]) -> list[Tensor]:
        """The raw (unnormalised) columns of the world frame, ``[B, n]`` each: GEs, zones, OUs, the DCU."""
        p = s["position"]
        b = p.shape[0]
        parts = []
        # GEs: position, remaining data, transmit power, presence
        ge_mask = s["ge_mask"].to(p.dtype)
        parts += [
            s["ge_pos"].flatten(1),
            s["ge_remaining"],
            ge_mask,  # TP / TP: every present GE transmits at the configured power
            ge_mask,
        ]
        # Zones: south-west corner, length, width, presence
        for name in ZONE_KINDS:
            r = s[name]
            parts += [torch.cat([r[..., :2], r[..., 2:] - r[..., :2]], dim=-1).flatten(1), s[name + "_mask"].to(p.dtype)]
        parts += self._ou_parts(s)
        # DCU: position, velocity, energy left, data of the last slot, TA, LA
        parts += [
            p,
            s["velocity"],
            s["energy_left"].unsqueeze(-1),
            s["slot_data"].unsqueeze(-1),
            s["takeoff"],
            s["landing"],
        ]
        return [t.reshape(b, -1) for t in parts]

    def _ego_frame_parts(self, s: dict[str, Tensor]) -> list[Tensor]:
        """The raw columns of the ego frame, ``[..., n]`` each (class docstring), in
        ``_ego_frame_spec``'s order."""
        cfg = self.cfg
        a, scale = cfg.area, cfg.obs_distance_scale
        p = s["position"]
        dt = p.dtype
        pp = torch.cat([p, p], dim=-1).unsqueeze(-2)  # subtracted from (x0, y0, x1, y1)
        # GEs: data left first, then emptied, each nearest first; absent last, zeroed
        present = s["ge_mask"]
        has = (s["ge_remaining"] > 0) & present
        rel = s["ge_pos"] - p.unsqueeze(-2)
        group = (~has).to(torch.int64) + (~present).to(torch.int64)  # 0 data left, 1 emptied, 2 absent
        order = sort_order(group, torch.linalg.vector_norm(rel, dim=-1))
        keep = take(present, order).to(dt)
        parts = [(take(rel, order) * keep.unsqueeze(-1)).flatten(-2), take(s["ge_remaining"], order) * keep,
                 take(has, order).to(dt), keep]
        # zones: per kind nearest first (ties by the distance to the centre), absent last, zeroed;
        # the three kinds sorted at once with the kind as the first key, a third of the ops
        r = torch.cat([s[name] for name in ZONE_KINDS], dim=-2)
        mask = torch.cat([s[name + "_mask"] for name in ZONE_KINDS], dim=-1)
        vec = rect_vectors(p, r)
        dist = torch.linalg.vector_norm(vec, dim=-1).masked_fill(~mask, float("inf"))
        centre = torch.linalg.vector_norm((r[..., :2] + r[..., 2:]) / 2 - p.unsqueeze(-2), dim=-1)
        order = sort_order(self._zone_kind.to(p.device).expand_as(dist), dist, centre)
        keep = take(mask, order).to(dt)
        rel = take(r - pp, order) * keep.unsqueeze(-1)
        near = take(saturate(vec, scale), order) * keep.unsqueeze(-1)
        inside = take(ph.point_in_rects(p, r, mask), order).to(dt)
        i = 0
        for n in self.n_zone:
            parts += [rel[..., i : i + n, :].flatten(-2), near[..., i : i + n, :].flatten(-2), inside[..., i : i + n],
                      keep[..., i : i + n]]
            i += n
        # the boundary (west, east, south, north) and LA
        x, y = p[..., 0:1], p[..., 1:2]
        la = s["landing"].unsqueeze(-2)
        in_la = ph.point_in_rects(p, la, torch.ones(la.shape[:-1], dtype=torch.bool, device=p.device))
        parts += [torch.cat([x, a.x_size - x, y, a.y_size - y], dim=-1), (la - pp).squeeze(-2),
                  rect_vectors(p, la).squeeze(-2), in_la.to(dt)]
        parts += self._ou_parts(s)
        # the DCU: energy left, velocity, last slot's data, slots left (t_max - step, / t_max)
        parts += [s["energy_left"].unsqueeze(-1), s["velocity"], s["slot_data"].unsqueeze(-1),
                  (cfg.t_max - s["step"]).to(dt).unsqueeze(-1)]
        # the current target: unit direction, distance
        rel, d, _ = current_target(s)
        return parts + [unit_vector(rel, d), d.unsqueeze(-1)]

    def _extra_parts(self, s: dict[str, Tensor]) -> list[Tensor]:
        """The raw extra columns (none when off): distances to the nearest zones, the boundary and
        LA, and whether the DCU is inside an RZ."""
        if not self.extra:
            return []
        near = torch.stack([s["d_bz"], s["d_nfz"], s["d_rz"], s["d_boundary"]], dim=-1)
        return [
            near.clamp(max=self.cfg.obs_distance_scale),
            s["d_la"].unsqueeze(-1),
            (s["d_rz"] <= 0).to(s["position"].dtype).unsqueeze(-1),
        ]

    def _ego_parts(self, s: dict[str, Tensor]) -> list[Tensor]:
        """The raw ``ego_features`` columns (none when off), ``[B, 2]`` each."""
        cfg = self.cfg
        p = s["position"]
        parts = []
        if self.ego:
            if GEO_KEY in s:  # the way to go around BZs and NFZs, times the length of that way
                d, unit, _ = geo.geodesic_target(s, cfg)
                rel = unit * d.clamp_max(cfg.reward.d_tar).unsqueeze(-1)
            else:
                rel, d, _ = current_target(s)
                unit = unit_vector(rel, d)
            parts += [rel, unit]
            for name in ("bz", "nfz"):
                # length saturates at obs_distance_scale
                parts.append(saturate(nearest_rect_vector(p, s[name], s[name + "_mask"]), cfg.obs_distance_scale))
        return parts
