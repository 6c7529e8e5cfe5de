"""Geodesic distance fields: the flying distance around buildings and no-fly zones.

Used by the opt-in progress reward with ``reward.progress_metric: geodesic`` and its ego-centric
direction column ([decision] beyond the paper, ``env=shaped_geodesic``). For every scenario and
every target (each GE, then LA) the distance from each cell centre of a regular grid to the
target, moving between the 8 neighbouring cells and never through a cell whose centre lies within
``progress_clearance`` of a BZ or NFZ, is computed once when the scenario's episode starts
(batched Bellman-Ford relaxation). With ``progress_clearance_cost`` k >= 1 (``env=shaped_geodesic_soft``)
the cells within the clearance are passable at k times the step length and only those within
``safety.d_min`` are walls, so a GE in a corridor narrower than twice the clearance can be reached.
A step then only reads the four cell centres around the DCU (the distance, interpolated
bilinearly) and, for the direction column, the nine cells around it, so the per-step cost is a
few gathers.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from uavlae.envs import physics as ph
from uavlae.envs.config import EnvConfig

_BIG = 1.0e6  # stands for "unreachable" after the fill of blocked cells (finite: no inf·0)


def grid_shape(cfg: EnvConfig) -> tuple[int, int]:
    c = cfg.reward.progress_grid_cell
    return math.ceil(cfg.area.y_size / c), math.ceil(cfg.area.x_size / c)


def _centres(cfg: EnvConfig, device, dtype) -> tuple[Tensor, Tensor]:
    c = cfg.reward.progress_grid_cell
    h, w = grid_shape(cfg)
    ys = (torch.arange(h, device=device, dtype=dtype) + 0.5) * c
    xs = (torch.arange(w, device=device, dtype=dtype) + 0.5) * c
    return ys, xs


def _neighbour_min(f: Tensor, dim: int, out: Tensor) -> Tensor:
    """out[i] = min(f[i - 1], f[i + 1]) along ``dim`` (one side only at the edges)."""
    n = f.shape[dim]
    torch.minimum(f.narrow(dim, 0, n - 2), f.narrow(dim, 2, n - 2), out=out.narrow(dim, 1, n - 2))
    out.narrow(dim, 0, 1).copy_(f.narrow(dim, 1, 1))
    out.narrow(dim, n - 1, 1).copy_(f.narrow(dim, n - 2, 1))
    return out


def _relax_step(f: Tensor, c: float | Tensor, row: Tensor, col: Tensor, dia: Tensor) -> Tensor:
    """min(f, f(neighbour) + step length) over the 8 neighbours (``row``/``col``/``dia``: scratch).
    ``c``: the straight step's length, or per cell ([..., H, W]: the cost of a step into it)."""
    _neighbour_min(f, -1, row)  # west / east neighbours
    _neighbour_min(f, -2, col)  # south / north
    _neighbour_min(row, -2, dia)  # the four diagonal neighbours
    torch.minimum(row, col, out=row)
    f = torch.minimum(f, row.add_(c))
    return torch.minimum(f, dia.add_(c * math.sqrt(2.0)))


def _relax_chunk(f: Tensor, blocked: Tensor, c: float | Tensor, max_iters: int) -> Tensor:
    f = f.masked_fill(blocked, math.inf)
    scratch = torch.empty_like(f), torch.empty_like(f), torch.empty_like(f)
    for it in range(max_iters):
        prev = f.clone() if it % 8 == 7 else None
        f = _relax_step(f, c, *scratch).masked_fill_(blocked, math.inf)
        if prev is not None and torch.equal(prev, f):
            break
    return f


def _relax(f: Tensor, free: Tensor, c: float | Tensor, max_iters: int, chunk: int = 128) -> Tensor:
    """Bellman-Ford on the 8-connected grid: f[n, y, x] = min(f, f(neighbour) + step length)
    over free cells, until nothing changes. ``f``: [N, H, W] (inf away from the sources); the
    grids are relaxed ``chunk`` at a time, which keeps the working set in cache. ``c``: the
    straight step's length, or per cell ([N, H, W]: the length of a step into that cell)."""
    if min(f.shape[-2:]) < 3:
        raise ValueError(f"the geodesic grid needs at least 3 x 3 cells, got {tuple(f.shape[-2:])}")
    blocked = ~free
    per_cell = isinstance(c, Tensor)
    return torch.cat(
        [_relax_chunk(f[i : i + chunk], blocked[i : i + chunk], c[i : i + chunk] if per_cell else c, max_iters)
         for i in range(0, f.shape[0], chunk)]
    ) if f.shape[0] else f


def _zone_distance(points: Tensor, state: dict[str, Tensor]) -> Tensor:
    """Distance from each point ``[B, P, 2]`` to the nearest BZ or NFZ (``inf`` when none)."""
    d = [ph.point_rect_distance(points, state[n].unsqueeze(1), state[n + "_mask"].unsqueeze(1)) for n in ("bz", "nfz")]
    d = torch.cat(d, dim=-1)
    return ph.nearest_distance(d)


def _wall_distance(cfg: EnvConfig) -> float:
    """Cells whose centre is this close to a BZ or NFZ are walls: the clearance, or with a
    ``progress_clearance_cost`` only ``safety.d_min`` (the rest of the clearance costs more)."""
    r = cfg.reward
    return min(cfg.safety.d_min, r.progress_clearance) if r.progress_clearance_cost > 0 else r.progress_clearance


def _fill_blocked(f: Tensor, c: float | Tensor, rounds: int = 2) -> Tensor:
    """Blocked cells (and unreachable ones) get their nearest free neighbour's value plus the
    step, two cells deep, then ``_BIG``: the interpolation next to a wall stays finite, and the
    fill cannot reach across a zone (at least 50 m wide) to a lower value on its far side,
    which would point the way through it."""
    scratch = torch.empty_like(f), torch.empty_like(f), torch.empty_like(f)
    for _ in range(rounds):
        # free cells already hold their minimum for the same step lengths: only blocked ones change
        f = _relax_step(f, c, *scratch)
    return torch.nan_to_num(f, posinf=_BIG).clamp_max(_BIG)


def distance_fields(state: dict[str, Tensor], cfg: EnvConfig) -> Tensor:
    """``[B, G + 1, H·W]``: per scenario, the geodesic distance from every cell centre to each
    GE (padded GEs: ``_BIG``) and, last, to LA."""
    ge_pos, ge_mask = state["ge_pos"], state["ge_mask"]
    b, g = ge_mask.shape
    device, dtype = ge_pos.device, ge_pos.dtype
    c = cfg.reward.progress_grid_cell
    h, w = grid_shape(cfg)
    ys, xs = _centres(cfg, device, dtype)
    cells = torch.stack(torch.meshgrid(xs, ys, indexing="xy"), dim=-1).view(1, h * w, 2)  # row-major (y, x)
    # blocked: the centre is within progress_clearance of a BZ or an NFZ (with a clearance cost:
    # within d_min, and the cells between cost progress_clearance_cost times the step)
    d_zone = _zone_distance(cells.expand(b, -1, -1), state).view(b, h, w)
    blocked = d_zone <= _wall_distance(cfg)
    k = cfg.reward.progress_clearance_cost
    cost = None
    if k > 0:
        cost = torch.where(d_zone <= cfg.reward.progress_clearance, k, 1.0).to(dtype)
    # sources: the cell holding each GE (its distance to the centre); LA: the cells whose centre is
    # within one cell of the LA rectangle (their distance to it)
    src = torch.full((b, g + 1, h, w), math.inf, device=device, dtype=dtype)
    iy = (ge_pos[..., 1] / c).floor().long().clamp(0, h - 1)
    ix = (ge_pos[..., 0] / c).floor().long().clamp(0, w - 1)
    d0 = torch.hypot(ge_pos[..., 0] - xs[ix], ge_pos[..., 1] - ys[iy])
    bi = torch.arange(b, device=device).unsqueeze(-1).expand(b, g)
    gi = torch.arange(g, device=device).unsqueeze(0).expand(b, g)
    src[bi[ge_mask], gi[ge_mask], iy[ge_mask], ix[ge_mask]] = d0[ge_mask]
    la = state["landing"].view(b, 1, 1, 4)
    d_la = ph.point_rect_distance(cells, la, torch.ones(b, 1, 1, dtype=torch.bool, device=device)).view(b, h, w)
    src[:, g] = torch.where(d_la <= c, d_la, torch.full_like(d_la, math.inf))
    # a target's own cells are always free (a GE may lie closer to a zone than the clearance)
    free = ~blocked.unsqueeze(1) | src.isfinite()
    flat = src.view(b * (g + 1), h, w)
    free_n = free.reshape(b * (g + 1), h, w)
    step = c if cost is None else (cost * c).unsqueeze(1).expand(b, g + 1, h, w).reshape(b * (g + 1), h, w)
    f = _relax(flat, free_n, step, max_iters=h * w)
    f = _fill_blocked(f, step)
    f = f.view(b, g + 1, h, w)
    f[:, :g] = torch.where(ge_mask.view(b, g, 1, 1), f[:, :g], torch.full_like(f[:, :g], _BIG))
    return f.view(b, g + 1, h * w)


def _corners(p: Tensor, cfg: EnvConfig) -> tuple[Tensor, Tensor, Tensor]:
    """Flat indices of the 4 centres around ``p`` [B, 2] (order 00, 10, 01, 11 in x, y) and the
    fractional position between them."""
    c = cfg.reward.progress_grid_cell
    h, w = grid_shape(cfg)
    gx = (p[..., 0] / c - 0.5).clamp(0.0, w - 1.0)
    gy = (p[..., 1] / c - 0.5).clamp(0.0, h - 1.0)
    x0 = gx.floor().clamp(max=max(w - 2, 0)).long()
    y0 = gy.floor().clamp(max=max(h - 2, 0)).long()
    tx, ty = gx - x0, gy - y0
    x1, y1 = (x0 + 1).clamp(max=w - 1), (y0 + 1).clamp(max=h - 1)
    idx = torch.stack((y0 * w + x0, y0 * w + x1, y1 * w + x0, y1 * w + x1), dim=-1)
    return idx, tx, ty


def geodesic_lookup(field: Tensor, p: Tensor, cfg: EnvConfig) -> Tensor:
    """Bilinear value ``[B, T]`` of each of the ``T`` fields of every row at its position ``p``."""
    idx, tx, ty = _corners(p, cfg)
    b, t, _ = field.shape
    v = torch.gather(field, 2, idx.unsqueeze(1).expand(b, t, 4))
    f00, f10, f01, f11 = v.unbind(-1)
    tx, ty = tx.unsqueeze(-1), ty.unsqueeze(-1)
    return (1 - ty) * ((1 - tx) * f00 + tx * f10) + ty * ((1 - tx) * f01 + tx * f11)


def _cell_steps(device) -> tuple[Tensor, Tensor]:
    """The 3 x 3 neighbourhood as (dy, dx) offsets, the centre first."""
    d = torch.tensor([(0, 0)] + [(dy, dx) for dy in (-1, 0, 1) for dx in (-1, 0, 1) if dy or dx], device=device)
    return d[:, 0], d[:, 1]


def _pick_target(state: dict[str, Tensor], cfg: EnvConfig) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """``(geodesic distance to the current target, the target's field index, the geodesically
    nearest GE with data, GEs with data left)``: the target is that GE, else LA (the last field).
    The distance is at most ``2 d_tar`` (a target the grid cannot reach reads as far, not as
    infinitely far)."""
    field, p = state["geo_field"], state["position"]
    val = geodesic_lookup(field, p, cfg)
    b, t, _ = field.shape
    g = t - 1
    has = state["ge_remaining"] > 0
    n_left = has.sum(-1)
    d_ge = val[:, :g].masked_fill(~has, math.inf)
    near = d_ge.argmin(-1) if g > 0 else torch.zeros(b, dtype=torch.long, device=p.device)
    pick = torch.where(n_left > 0, near, torch.full_like(near, g))
    d = torch.gather(val, 1, pick.unsqueeze(-1)).squeeze(-1).clamp_max(2.0 * cfg.reward.d_tar)
    return d, pick, near, n_left


def geodesic_distance(state: dict[str, Tensor], cfg: EnvConfig) -> tuple[Tensor, Tensor]:
    """``(geodesic distance to the current target, GEs with data left)``, see ``_pick_target``."""
    d, _, _, n_left = _pick_target(state, cfg)
    return d, n_left


def geodesic_target(state: dict[str, Tensor], cfg: EnvConfig) -> tuple[Tensor, Tensor, Tensor]:
    """``(geodesic distance to the current target, unit direction of the way there, GEs with
    data left)``; the target is the geodesically nearest GE with data, else LA.

    The direction points from the DCU to the centre of the lowest of the 9 cells around it, or
    straight at the target when the DCU's own cell is the lowest (it is there): it follows the
    grid's way, which keeps ``progress_clearance`` from BZs and NFZs.
    """
    field, p = state["geo_field"], state["position"]
    d, pick, near, n_left = _pick_target(state, cfg)
    b, g = field.shape[0], field.shape[1] - 1
    # the 9 cells around the DCU's cell in the picked field
    c = cfg.reward.progress_grid_cell
    h, w = grid_shape(cfg)
    iy = (p[:, 1] / c).floor().long().clamp(0, h - 1)
    ix = (p[:, 0] / c).floor().long().clamp(0, w - 1)
    sy, sx = _cell_steps(p.device)
    ny, nx = iy.unsqueeze(-1) + sy, ix.unsqueeze(-1) + sx  # [B, 9]
    inside = (ny >= 0) & (ny < h) & (nx >= 0) & (nx < w)
    flat = (ny.clamp(0, h - 1) * w + nx.clamp(0, w - 1))
    nb = field.reshape(b, -1).gather(1, pick.unsqueeze(-1) * field.shape[-1] + flat).masked_fill(~inside, math.inf)
    centres = torch.stack(((nx.to(p.dtype) + 0.5) * c, (ny.to(p.dtype) + 0.5) * c), dim=-1)  # [B, 9, 2]
    # the target point: the GE, or the nearest point of LA
    rel_ge = torch.gather(state["ge_pos"], 1, near.view(b, 1, 1).expand(b, 1, 2)).squeeze(1) - p if g > 0 else torch.zeros_like(p)
    rel_la = ph.nearest_point_in_rects(p, state["landing"].unsqueeze(-2)).squeeze(-2) - p
    rel_target = torch.where((n_left > 0).unsqueeze(-1), rel_ge, rel_la)
    # A DCU that came within the clearance heads for the lowest *free* cell around it: the
    # values of blocked cells are only a fill, and following them can cut a zone's corner.
    blocked = _zone_distance(centres, state) <= _wall_distance(cfg)
    near_target = torch.linalg.vector_norm(centres - (p + rel_target).unsqueeze(1), dim=-1) <= c
    blocked &= ~near_target
    nb_free = nb.masked_fill(blocked, math.inf)
    any_free = nb_free.isfinite().any(-1, keepdim=True)
    best = torch.where(any_free, nb_free, nb).argmin(-1)
    centre = torch.gather(centres, 1, best.view(b, 1, 1).expand(b, 1, 2)).squeeze(1)
    rel = torch.where((best == 0).unsqueeze(-1), rel_target, centre - p)
    unit = rel / torch.linalg.vector_norm(rel, dim=-1, keepdim=True).clamp_min(1e-6)
    return d, unit, n_left
