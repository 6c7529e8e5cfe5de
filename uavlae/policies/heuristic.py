"""A global planner, beyond the paper (``heuristic_kind: planner``, ``+exp=heuristic_planner``).

The paper's heuristic is greedy (:mod:`uavlae.policies.greedy`); this one plans shortest paths
around BZ/NFZ with energy and time budgets, a stronger baseline reported under its own name
(docs/model.md §8), which can also stand in for the LLM (``+exp=sac_heuristic_planner``, the LLM's
fallback with ``heuristic_kind: planner``).
It reads the env's raw ``("state", NAME)`` entries (docs/env_contract.md), uses only what the
DCU may know (the static map, GE data, its own energy, and OUs within the perception radius)
and returns an action ``[B, 2]`` in [-1, 1] (velocity / v_max). Fully batched; no loop over rows.

Decision, per slot:

1. Plan. BZ and NFZ are axis-aligned rectangles, so shortest paths around them (inflated by a
   clearance) run through the corners of the inflated rectangles: a visibility graph whose nodes
   are those corners (at a normal and a tight clearance), the GEs and the LA centre. Its
   all-pairs distances depend only on the scenario and are cached per batch row (Floyd-Warshall,
   rebuilt only for rows whose map changed). Each slot only the DCU's own edges are tested.
   [decision] Not an occupancy-grid distance field: it needs ~150-250 relaxation passes per
   target change, too many to run inside rollouts, and it is only approximate; the visibility
   graph is exact for rectangles.
2. Target: the GE with data nearest by path length among those the DCU can still afford (energy
   and time to get there, collect and return to LA, with safety factors); none left → LA.
3. Desired velocity: toward the next waypoint at v_max, shortened so the step ends on the
   waypoint (on top of a GE it hovers until the GE is served; at the LA centre it stops: lands).
4. Safety filter over candidate velocities (desired, half of it, hover, a ring of headings):
   speed capped in any RZ the segment touches, segment clear of BZ/NFZ and inside the area,
   predicted closest approach to every visible OU >= a safety distance (or not worse than now);
   the safe candidate nearest the desired velocity wins, else the one with the largest
   closest approach.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

import torch
from pydantic import Field, model_validator
from torch import Tensor

from uavlae.envs import physics as ph
from uavlae.envs.config import EnvConfig, make_env_config
from uavlae.policies.controller import StateController
from uavlae.policies.safety import EPS as _EPS
from uavlae.policies.safety import blocked as _blocked
from uavlae.policies.safety import choose, inflate as _inflate, picked, screen
from uavlae.validation import StrictModel, parse_model

# raw state entries the heuristic reads (docs/env_contract.md)
STATE_IN_KEYS = (
    "position", "energy_left", "step", "ge_pos", "ge_remaining", "ge_mask", "ou_pos", "ou_vel",
    "ou_mask", "nfz", "nfz_mask", "rz", "rz_mask", "bz", "bz_mask", "landing", "takeoff",
)


class HeuristicConfig(StrictModel):
    """Numbers of the greedy heuristic; ``conf/advisor/heuristic.yaml`` mirrors it one-to-one."""

    clearance: float = Field(8.0, gt=0)  # planned paths keep this far from BZ/NFZ (must be > d_min)
    tight_clearance: float = Field(2.5, gt=0)  # fallback clearance through gaps the normal one closes
    tight_cost: float = Field(3.0, ge=1)  # length factor of edges that are free only at the tight clearance
    clearance_slack: float = Field(0.5, ge=0)  # edges are tested at clearance - slack, so sides of an inflated rectangle are free
    filter_clearance: float = Field(1.0, ge=0)  # every executed segment keeps this far from BZ/NFZ
    boundary_margin: float = Field(1.0, ge=0)  # every step ends this far inside the area
    waypoint_reached: float = Field(0.5, gt=0)  # a graph node this close counts as reached
    energy_safety_factor: float = Field(1.5, ge=1)  # on physics.min_return_energy of the path
    energy_reserve: float = Field(5000.0, ge=0)  # J kept on top of the factor
    time_safety_factor: float = Field(1.2, ge=1)  # on the slots a detour and the return take
    time_reserve: int = Field(10, ge=0)  # slots kept before T_max
    service_slots: int = Field(2, ge=0)  # hover slots budgeted per GE
    ou_safety_distance: float = Field(5.0, gt=0)  # least predicted closest approach to a visible OU
    # [decision] an OU may redraw its velocity (p_turn) to anything up to v_max: where it can, the
    # DCU also keeps r_coll + this margin from every point a visible OU could reach in the slot
    ou_robust_margin: float = Field(1.0, ge=0)
    ou_robust_samples: int = Field(5, ge=2, le=64)  # time samples of the flight phase for that test
    ou_headings: int = Field(16, ge=4, le=256)  # ring of evasive headings
    ou_speed_fractions: tuple[float, ...] = (1.0, 0.5)  # their speeds, fractions of v_max
    rz_speed_margin: float = Field(0.95, gt=0, lt=1)  # |v| <= margin * v_limit when a segment touches an RZ
    rz_inflate: float = Field(1.0, ge=0)  # RZs are tested inflated by this much
    # slots between full replans of a row; on a straight leg toward a waypoint of a shortest path
    # the path stays optimal, so this only refreshes the energy / time budget and the target
    replan_period: int = Field(20, ge=1)

    @model_validator(mode="after")
    def _order(self) -> "HeuristicConfig":
        if self.tight_clearance > self.clearance:
            raise ValueError(f"tight_clearance={self.tight_clearance} must be <= clearance={self.clearance}")
        if self.clearance_slack >= self.tight_clearance:
            raise ValueError(
                f"clearance_slack={self.clearance_slack} must be < tight_clearance={self.tight_clearance}"
            )
        if not self.ou_speed_fractions or any(not 0 < f <= 1 for f in self.ou_speed_fractions):
            raise ValueError(f"ou_speed_fractions={self.ou_speed_fractions} must be non-empty, each in (0, 1]")
        return self


def make_heuristic_config(cfg: Any = None, **overrides: Any) -> HeuristicConfig:
    """Build a :class:`HeuristicConfig` from a mapping / OmegaConf node; ``ValueError`` names the field."""
    return parse_model(HeuristicConfig, cfg, prefix="heuristic", title="heuristic", **overrides)


class HeuristicPolicy(StateController):
    """The global planner; ``act(state)`` for raw tensors, ``forward(td)`` as a TorchRL policy.

    It keeps two per-row caches: the scenario's graph (rebuilt when a row's map changes) and the
    row's target and waypoint (replanned when the waypoint is near, the target is served, the
    filter deviated, every ``replan_period`` slots, or when ``step`` is not the previous call's
    plus one, e.g. after a reset or when it only acts on some slots as in SAC+Heuristic).

    Args:
        env_cfg: the world the policy acts in (area, speeds, energy model, perception radius).
        cfg: the heuristic's own numbers (default: :class:`HeuristicConfig`'s).
    """

    state_keys = STATE_IN_KEYS
    in_keys = [("state", k) for k in STATE_IN_KEYS]

    def __init__(self, env_cfg: EnvConfig | Mapping | None = None, cfg: HeuristicConfig | Mapping | None = None):
        super().__init__()
        self.env_cfg = make_env_config(env_cfg)
        self.cfg = make_heuristic_config(cfg)
        d_min = self.env_cfg.safety.d_min
        if self.cfg.clearance <= d_min:
            raise ValueError(
                f"advisor.clearance={self.cfg.clearance} must be > env.safety.d_min={d_min} "
                "so planned paths keep clear of buildings and NFZs"
            )
        self._cache: dict[str, Tensor] | None = None  # static graph per row
        self._plan_state: dict[str, Tensor] | None = None  # target and waypoint per row
        self.graph_rebuilds = 0  # rows whose graph was (re)built, for tests and benchmarks
        self.tight_rows = 0  # of those, rows that needed the tight corners

    # ------------------------------------------------------------------ state (exact resume)
    def cache_state(self) -> dict[str, Any]:
        """The per-row caches (scenario graph and plan) as plain tensors. Actions depend on the
        plan cache (a cached waypoint is kept until a replan), so a checkpoint holds it for a
        resume that acts exactly as the uninterrupted run would."""
        return {
            "graph": None if self._cache is None else {k: v.clone() for k, v in self._cache.items()},
            "plan": None if self._plan_state is None else {k: v.clone() for k, v in self._plan_state.items()},
        }

    def load_cache_state(self, state: Mapping[str, Any]) -> None:
        graph, plan = state.get("graph"), state.get("plan")
        self._cache = None if graph is None else {k: v.clone() for k, v in graph.items()}
        self._plan_state = None if plan is None else {k: v.clone() for k, v in plan.items()}

    # ------------------------------------------------------------------ static graph
    def _levels(self) -> tuple[float, float]:
        c = self.cfg
        return (c.clearance - c.clearance_slack, c.tight_clearance - c.clearance_slack)

    def _point_margins(self, pts: Tensor, rects: Tensor, rmask: Tensor) -> Tensor:
        """Per-level, per-rectangle test margins of segments from points [..., N, 2]: [..., L, N, P].

        A point nearer a rectangle than the test margin (a GE 5 m from a building, the DCU after an
        evasive move) tests its own segments with a margin just below its distance, so it is never
        shut in, and the rest of the map keeps the full margin.
        """
        d = ph.point_rect_distance(pts, rects.unsqueeze(-3), rmask.unsqueeze(-2))  # [..., N, P]
        lv = torch.tensor(self._levels(), dtype=pts.dtype, device=pts.device)
        return torch.minimum(lv.view(-1, 1, 1), (d - _EPS).clamp_min(0.0).unsqueeze(-3))

    def _build_graph(self, rects: Tensor, rmask: Tensor, points: Tensor, point_ok: Tensor, tight: bool) -> dict[str, Tensor]:
        """Nodes, their test margins and all-pairs shortest path lengths for a chunk of rows.

        Node order: the points (GEs, LA centre, TA centre), the corners at the normal clearance,
        then those at the tight clearance. Only the first ``n0`` nodes take part at the normal
        level (a tight corner lies inside its rectangle's normal margin). Without ``tight`` the
        tight corners are left out (invalid nodes): most maps need no tight passage.
        """
        c, a = self.cfg, self.env_cfg.area
        n, P = rmask.shape
        dt, dev = rects.dtype, rects.device
        levels = self._levels()
        bm = c.boundary_margin
        corners, corner_ok = [], []
        for li, m in enumerate((c.clearance, c.tight_clearance)):
            x0, y0, x1, y1 = (rects[..., i] for i in range(4))
            xs = torch.stack([x0 - m, x1 + m, x1 + m, x0 - m], -1)  # [n, P, 4]
            ys = torch.stack([y0 - m, y0 - m, y1 + m, y1 + m], -1)
            pts = torch.stack([xs.clamp(bm, a.x_size - bm), ys.clamp(bm, a.y_size - bm)], -1).reshape(n, 4 * P, 2)
            test = _inflate(rects, torch.full_like(rects[..., 0], levels[li]))
            inside = ph.point_in_rects(pts, test.unsqueeze(-3), rmask.unsqueeze(-2)).any(-1)
            corners.append(pts)
            corner_ok.append(rmask.repeat_interleave(4, dim=-1) & ~inside & (tight or li == 0))
        nodes = torch.cat([points] + corners, dim=-2)
        N, n0 = nodes.shape[-2], points.shape[-2] + 4 * P
        node_ok = torch.cat([point_ok] + corner_ok, dim=-1)
        corner_margin = torch.tensor(levels, dtype=dt, device=dev).view(1, 2, 1, 1).expand(n, 2, 8 * P, P)
        margin = torch.cat([self._point_margins(points, rects, rmask), corner_margin], dim=-2)  # [n, 2, N, P]

        # each undirected edge once; free at a level when it misses every rectangle inflated by
        # the smaller margin of its two ends
        use = N if tight else n0
        ii, jj = torch.triu_indices(use, use, 1, device=dev)
        length = torch.linalg.vector_norm(nodes[:, ii] - nodes[:, jj], dim=-1)  # [n, M]
        free = []
        for li, sel in enumerate((jj < n0, torch.ones_like(jj, dtype=torch.bool))):
            i, j = ii[sel], jj[sel]
            mg = torch.minimum(margin[:, li, i], margin[:, li, j])  # [n, M_level, P]
            f = torch.zeros_like(length, dtype=torch.bool)
            f[:, sel] = ~_blocked(nodes[:, i], nodes[:, j], rects.unsqueeze(1), mg, rmask.unsqueeze(1))
            free.append(f)
        inf = torch.full_like(length, math.inf)
        wp = torch.where(free[0], length, torch.where(free[1], length * c.tight_cost, inf))
        wp = torch.where(node_ok[:, ii] & node_ok[:, jj], wp, inf)
        w = torch.full((n, use, use), math.inf, dtype=dt, device=dev)
        w[:, ii, jj] = wp
        w[:, jj, ii] = wp
        w.diagonal(dim1=-2, dim2=-1).zero_()
        for k in range(use):  # Floyd-Warshall: D_ij = min(D_ij, D_ik + D_kj)
            w = torch.minimum(w, w[:, :, k : k + 1] + w[:, k : k + 1, :])
        dist = torch.full((n, N, N), math.inf, dtype=dt, device=dev)
        dist[:, :use, :use] = w
        return {"nodes": nodes, "node_ok": node_ok, "margin": margin, "dist": dist}

    def _build_rows(self, rects: Tensor, rmask: Tensor, points: Tensor, point_ok: Tensor) -> dict[str, Tensor]:
        """Graphs without tight corners (tight-level edges between the other nodes still count, at
        tight_cost); rows where that leaves two points apart get the tight corners too."""
        chunk = 64  # bounds the [rows, edges, P] edge test in memory
        n = rects.shape[0]
        parts = [
            self._build_graph(rects[r], rmask[r], points[r], point_ok[r], tight=False)
            for r in torch.arange(n, device=rects.device).split(chunk)
        ]
        built = {k: torch.cat([p[k] for p in parts]) for k in parts[0]}
        k = points.shape[-2]
        both = point_ok.unsqueeze(-1) & point_ok.unsqueeze(-2)
        apart = (both & torch.isinf(built["dist"][:, :k, :k])).flatten(1).any(-1)
        if bool(apart.any()):
            rows = apart.nonzero().squeeze(-1)
            parts = [
                self._build_graph(rects[r], rmask[r], points[r], point_ok[r], tight=True) for r in rows.split(chunk)
            ]
            for key in built:
                built[key] = built[key].index_copy(0, rows, torch.cat([p[key] for p in parts]))
            self.tight_rows += int(rows.numel())
        return built

    def _graph(self, rects: Tensor, rmask: Tensor, points: Tensor, point_ok: Tensor) -> tuple[dict[str, Tensor], Tensor]:
        """The cached graph for every row, rebuilt only for rows whose map changed (also returned)."""
        sig = torch.cat([rects.flatten(1), rmask.to(rects.dtype), points.flatten(1), point_ok.to(rects.dtype)], dim=-1)
        cache = self._cache
        if cache is None or cache["sig"].shape != sig.shape or cache["sig"].device != sig.device:
            changed = torch.ones(sig.shape[0], dtype=torch.bool, device=sig.device)
            cache = None
        else:
            changed = (cache["sig"] != sig).any(-1)
            if not bool(changed.any()):
                return cache, changed
        rows = changed.nonzero().squeeze(-1)
        built = self._build_rows(rects[rows], rmask[rows], points[rows], point_ok[rows])
        self.graph_rebuilds += int(rows.numel())
        if cache is None:
            cache = dict(built)
        else:
            for k, v in built.items():
                cache[k] = cache[k].index_copy(0, rows, v)
        cache["sig"] = sig.clone()
        self._cache = cache
        return cache, changed

    # ------------------------------------------------------------------ acting
    def _velocity(self, s: dict[str, Tensor]) -> Tensor:
        c, m = self.cfg, self.env_cfg.motion
        p = s["position"]
        dt = p.dtype
        B = p.shape[0]
        rects = torch.cat([s["bz"], s["nfz"]], dim=-2).to(dt)
        rmask = torch.cat([s["bz_mask"], s["nfz_mask"]], dim=-1)
        # graph points: the GEs, the LA centre (node G) and the TA centre (node G + 1)
        la, ta = s["landing"].to(dt), s["takeoff"].to(dt)
        centres = torch.stack([0.5 * (la[..., :2] + la[..., 2:]), 0.5 * (ta[..., :2] + ta[..., 2:])], dim=-2)
        points = torch.cat([s["ge_pos"].to(dt), centres], dim=-2)
        point_ok = torch.cat([s["ge_mask"], torch.ones_like(s["ge_mask"][:, :2])], dim=-1)
        g, changed = self._graph(rects, rmask, points, point_ok)

        # per-row plan cache: the target and the waypoint, replanned only where needed
        ps = self._plan_state
        if ps is None or ps["goal"].shape[0] != B or ps["goal"].device != p.device:
            ps = {
                "valid": torch.zeros(B, dtype=torch.bool, device=p.device),
                "last_step": torch.zeros(B, dtype=torch.int64, device=p.device),
                "plan_step": torch.zeros(B, dtype=torch.int64, device=p.device),
                "target": torch.zeros(B, dtype=torch.int64, device=p.device),
                "goal": torch.zeros(B, 2, dtype=dt, device=p.device),
                "deviated": torch.zeros(B, dtype=torch.bool, device=p.device),
            }
        step = s["step"].to(torch.int64)
        G = s["ge_pos"].shape[-2]
        if G:
            tgt = ps["target"].clamp_max(G - 1).unsqueeze(-1)
            tgt_done = (ps["target"] < G) & (s["ge_remaining"].gather(1, tgt).squeeze(-1) <= 0)
        else:
            tgt_done = torch.zeros_like(ps["valid"])
        near_goal = torch.linalg.vector_norm(ps["goal"] - p, dim=-1) <= m.v_max * m.t_fly
        replan = (
            ~ps["valid"] | changed | ps["deviated"] | tgt_done | near_goal
            | (step != ps["last_step"] + 1) | (step - ps["plan_step"] >= c.replan_period)
        )
        if bool(replan.any()):
            rows = replan.nonzero().squeeze(-1)
            sub = {k: v[rows] for k, v in s.items()}
            target, goal = self._plan(sub, rects[rows], rmask[rows], {k: v[rows] for k, v in g.items()})
            ps["target"] = ps["target"].index_copy(0, rows, target)
            ps["goal"] = ps["goal"].index_copy(0, rows, goal)
            ps["plan_step"] = ps["plan_step"].index_copy(0, rows, step[rows])
        goal = ps["goal"]

        # Eq. (1): the step ends on the goal when it is within v_max * t_fly
        to_goal = goal - p
        dist = torch.linalg.vector_norm(to_goal, dim=-1, keepdim=True)
        speed = torch.minimum(dist / m.t_fly, torch.full_like(dist, m.v_max))
        v_des = torch.where(dist > 0, to_goal / dist.clamp_min(1e-9) * speed, torch.zeros_like(to_goal))

        v, deviated = self._filter(s, p, v_des, rects, rmask, goal)
        ps["valid"] = torch.ones_like(ps["valid"])
        ps["last_step"] = step.clone()
        ps["deviated"] = deviated
        self._plan_state = ps
        return v

    def _plan(self, s: dict[str, Tensor], rects: Tensor, rmask: Tensor, g: dict[str, Tensor]) -> tuple[Tensor, Tensor]:
        """Target node (GE index, or G for LA) and next waypoint position for the given rows."""
        c, ec = self.cfg, self.env_cfg
        m = ec.motion
        p = s["position"]
        dt = p.dtype
        B = p.shape[0]
        G = s["ge_pos"].shape[-2]
        nodes, node_ok, D = g["nodes"], g["node_ok"], g["dist"]
        N = nodes.shape[-2]

        # the DCU's own edges to every node, at both clearances (normal: GEs, LA, normal corners)
        n0 = G + 2 + 4 * rects.shape[-2]
        mp = self._point_margins(p.unsqueeze(-2), rects, rmask)  # [B, 2, 1, P]
        mg = torch.minimum(mp, g["margin"])  # [B, 2, N, P]
        pp, rr, mm = p.unsqueeze(-2), rects.unsqueeze(1), rmask.unsqueeze(1)
        hit0 = _blocked(pp, nodes[:, :n0], rr, mg[:, 0, :n0], mm)
        use = N if bool(node_ok[:, n0:].any()) else n0  # tight corners exist only on maps that need them
        hit1 = _blocked(pp, nodes[:, :use], rr, mg[:, 1, :use], mm)
        hit1 = torch.cat([hit1, torch.ones_like(hit0[:, : N - use])], dim=-1)
        free0 = torch.cat([~hit0, torch.zeros_like(hit1[:, n0:])], dim=-1)
        d_pn = torch.linalg.vector_norm(nodes - p.unsqueeze(-2), dim=-1)  # [B, N]
        inf = torch.full_like(d_pn, math.inf)
        cost = torch.where(free0, d_pn, torch.where(~hit1, d_pn * c.tight_cost, inf))
        cost = torch.where(node_ok, cost, inf)

        # path lengths to every GE and to LA (nodes 0..G-1 and G)
        to_tgt = (cost.unsqueeze(-1) + D[:, :, : G + 1]).amin(-2)  # [B, G + 1]
        path_ge = to_tgt[:, :G]
        ge_to_la = D[:, :G, G]  # [B, G]

        # affordable GEs: get there, collect, return to LA, with safety factors (energy and time)
        hover = ph.slot_energy(torch.zeros((), dtype=dt, device=p.device), ec.energy, m)
        tour = path_ge + ge_to_la
        need_e = c.energy_safety_factor * (ph.min_return_energy(tour, ec.energy, m) + c.service_slots * hover)
        slots = torch.ceil(tour / (m.v_max * m.t_fly))
        need_t = c.time_safety_factor * (slots + c.service_slots) + c.time_reserve
        steps_left = (ec.t_max - s["step"]).to(dt).unsqueeze(-1)
        energy_left = s["energy_left"].to(dt).unsqueeze(-1)
        feasible = (
            s["ge_mask"] & (s["ge_remaining"] > 0) & torch.isfinite(path_ge)
            & (energy_left >= need_e + c.energy_reserve) & (steps_left >= need_t)
        )
        best_ge = torch.where(feasible, path_ge, torch.full_like(path_ge, math.inf)).argmin(-1)
        target = torch.where(feasible.any(-1), best_ge, torch.full_like(best_ge, G))  # [B]

        # next waypoint: the node minimising own edge + remaining path; nodes already reached skipped
        d_tgt = D.gather(2, target.view(B, 1, 1).expand(B, N, 1)).squeeze(-1)  # [B, N]
        is_tgt = torch.arange(N, device=p.device).unsqueeze(0) == target.unsqueeze(-1)
        reached = (d_pn < c.waypoint_reached) & ~is_tgt
        total = torch.where(reached, inf, cost) + d_tgt
        wp = total.argmin(-1)
        tgt_pos = nodes.gather(1, target.view(B, 1, 1).expand(B, 1, 2)).squeeze(1)
        wp_pos = nodes.gather(1, wp.view(B, 1, 1).expand(B, 1, 2)).squeeze(1)
        # no path at all (should not happen on a valid scenario): head straight, the filter keeps it safe
        goal = torch.where(torch.isfinite(total.amin(-1)).unsqueeze(-1), wp_pos, tgt_pos)
        return target, goal

    def _candidates(self, v_des: Tensor) -> Tensor:
        c, m = self.cfg, self.env_cfg.motion
        k = torch.arange(c.ou_headings, dtype=v_des.dtype, device=v_des.device) * (2 * math.pi / c.ou_headings)
        ring = torch.stack([torch.cos(k), torch.sin(k)], -1)  # [H, 2]
        f = torch.tensor(c.ou_speed_fractions, dtype=v_des.dtype, device=v_des.device) * m.v_max
        ring = (f.view(-1, 1, 1) * ring).reshape(-1, 2)
        fixed = torch.cat([torch.zeros_like(ring[:1]), ring], 0).unsqueeze(0).expand(v_des.shape[0], -1, -1)
        return torch.cat([v_des.unsqueeze(1), 0.5 * v_des.unsqueeze(1), fixed], dim=1)  # [B, C, 2]

    def _screen(
        self, s: dict[str, Tensor], p: Tensor, cand: Tensor, rects: Tensor, rmask: Tensor, goal: Tensor
    ) -> Any:
        """Candidates [B, C, 2] after the RZ cap; whether each is feasible, OU-safe and turn-proof; its OU
        clearance (:func:`uavlae.policies.safety.screen`, the safety filter's screen)."""
        a = self.env_cfg.area
        # every step ends this far inside the area (less where the DCU or its goal is nearer the edge)
        edge = torch.minimum(
            ph.boundary_distance(p, a.x_size, a.y_size), ph.boundary_distance(goal, a.x_size, a.y_size)
        ).clamp_max(self.cfg.boundary_margin)
        return screen(s, p, cand, rects, rmask, edge, self.cfg, self.env_cfg)

    def _filter(
        self, s: dict[str, Tensor], p: Tensor, v_des: Tensor, rects: Tensor, rmask: Tensor, goal: Tensor
    ) -> tuple[Tensor, Tensor]:
        """The executed velocity and whether it differs from the (RZ-capped) desired one."""
        first = self._screen(s, p, v_des.unsqueeze(1), rects, rmask, goal)
        v = first.cand[:, 0]
        bad = ~(first.feasible & first.ou_ok & first.proof)[:, 0]
        if bool(bad.any()):  # only those rows search the ring of candidates
            rows = bad.nonzero().squeeze(-1)
            sub = {k: t[rows] for k, t in s.items()}
            vd = v_des[rows]
            sc = self._screen(sub, p[rows], self._candidates(vd), rects[rows], rmask[rows], goal[rows])
            v = v.index_copy(0, rows, picked(sc, choose(sc, vd)))
        return v, bad
