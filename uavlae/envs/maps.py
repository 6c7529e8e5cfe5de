"""Rasterised maps centred on the DCU, the observation of the ``theile`` baseline (``env.maps``).

:func:`dcu_maps` turns the raw state into two square maps ``[B, C, S, S]``: a local fine one
(``maps.local_size`` cells of ``maps.local_cell`` m) and a global coarse one (``maps.global_size``
cells of ``maps.global_cell`` m; by default twice the area's side, so the whole area is on it
wherever the DCU is). Pure dense torch over the batch, no data-dependent branch: it runs inside
the (compiled) env step.

Axes, the convention the D4 actions of :mod:`uavlae.algos.theile` rely on: ``map[b, c, i, j]``
is the cell whose centre lies at ``position + ((j + 0.5 - S/2) c, (i + 0.5 - S/2) c)``: the last
axis ``j`` runs east (+x), the one before it ``i`` north (+y); row 0 is the southern edge. With
S even, the DCU sits on the corner shared by the four central cells, so a rotation by 90° about
the DCU or a reflection through it maps cells onto cells: rotating the world by R rotates the
maps by R exactly (the areas of rectangles; a point's cell, up to points on a cell edge).

Channels (:data:`MAP_CHANNELS`), each in [0, 1] per cell except ``ge_data``:

- ``area``: the fraction of the cell inside the area [0, X] x [0, Y] (0 outside: where a step
  leaves the area);
- ``bz``, ``nfz``, ``rz``: the fraction of the cell covered by the zones of that kind (summed
  over the zones, at most 1: BZs and NFZs never overlap, RZs may);
- ``ge_data``: the data left at the GEs whose position falls in the cell, / ``ge.data_max``;
- ``ou``: the number of other UAVs within the perception radius whose position falls in the cell;
- ``landing``: the fraction of the cell inside LA.
"""

from __future__ import annotations

import torch
from torch import Tensor

from uavlae.envs.config import EnvConfig

MAP_CHANNELS = ("area", "bz", "nfz", "rz", "ge_data", "ou", "landing")


def _edges(centre: Tensor, size: int, cell: float) -> Tensor:
    """Lower cell edges along one axis, ``[B, size]``, for a grid centred on ``centre`` ``[B]``."""
    k = torch.arange(size, device=centre.device, dtype=centre.dtype)
    return centre.unsqueeze(-1) + (k - size / 2) * cell


def _rect_cover(rects: Tensor, mask: Tensor, lo_x: Tensor, lo_y: Tensor, cell: float) -> Tensor:
    """Fraction of every cell covered by the present rectangles ``[B, Z, 4]``: ``[B, S, S]``.

    A cell's overlap with an axis-aligned rectangle is the product of the overlaps of their
    intervals on each axis, so one outer product per rectangle gives it exactly."""
    lo_x, lo_y = lo_x.unsqueeze(-2), lo_y.unsqueeze(-2)  # [B, 1, S]
    x0, y0, x1, y1 = (rects[..., k].unsqueeze(-1) for k in range(4))  # [B, Z, 1]
    ox = (torch.minimum(x1, lo_x + cell) - torch.maximum(x0, lo_x)).clamp(min=0) / cell
    oy = (torch.minimum(y1, lo_y + cell) - torch.maximum(y0, lo_y)).clamp(min=0) / cell
    ox = ox * mask.unsqueeze(-1).to(ox.dtype)
    return torch.einsum("bzi,bzj->bij", oy, ox).clamp(max=1.0)


def _point_deposit(points: Tensor, values: Tensor, p: Tensor, size: int, cell: float) -> Tensor:
    """``values`` ``[B, N]`` summed into the cell of each point ``[B, N, 2]``: ``[B, S, S]``
    (points off the map add nothing)."""
    k = torch.arange(size, device=p.device)
    idx = torch.floor((points - p.unsqueeze(-2)) / cell + size / 2).to(torch.int64)  # [B, N, 2]: (col, row)
    col = (idx[..., 0].unsqueeze(-1) == k).to(values.dtype)  # [B, N, S]
    row = (idx[..., 1].unsqueeze(-1) == k).to(values.dtype)
    return torch.einsum("bni,bnj->bij", row * values.unsqueeze(-1), col)


def _one_map(s: dict[str, Tensor], cfg: EnvConfig, size: int, cell: float) -> Tensor:
    p = s["position"]
    lo_x, lo_y = _edges(p[..., 0], size, cell), _edges(p[..., 1], size, cell)
    a = cfg.area
    ones = torch.ones(p.shape[:-1] + (1,), dtype=torch.bool, device=p.device)
    area = torch.tensor([0.0, 0.0, a.x_size, a.y_size], dtype=p.dtype, device=p.device).expand(p.shape[:-1] + (1, 4))
    ou_rel = s["ou_pos"] - p.unsqueeze(-2)
    ou_seen = s["ou_mask"] & (torch.linalg.vector_norm(ou_rel, dim=-1) <= cfg.safety.perception_radius)
    channels = {
        "area": _rect_cover(area, ones, lo_x, lo_y, cell),
        "bz": _rect_cover(s["bz"], s["bz_mask"], lo_x, lo_y, cell),
        "nfz": _rect_cover(s["nfz"], s["nfz_mask"], lo_x, lo_y, cell),
        "rz": _rect_cover(s["rz"], s["rz_mask"], lo_x, lo_y, cell),
        "ge_data": _point_deposit(s["ge_pos"], s["ge_remaining"] / cfg.ge.data_max, p, size, cell),
        "ou": _point_deposit(s["ou_pos"], ou_seen.to(p.dtype), p, size, cell),
        "landing": _rect_cover(s["landing"].unsqueeze(-2), ones, lo_x, lo_y, cell),
    }
    return torch.stack([channels[c] for c in MAP_CHANNELS], dim=-3)


def dcu_maps(s: dict[str, Tensor], cfg: EnvConfig) -> tuple[Tensor, Tensor]:
    """The local and the global map of the raw state ``s``: ``([B, C, L, L], [B, C, G, G])``
    with C = ``len(MAP_CHANNELS)``, L = ``maps.local_size``, G = ``maps.global_size`` (axes: the
    module doc)."""
    m = cfg.maps
    return _one_map(s, cfg, m.local_size, m.local_cell), _one_map(s, cfg, m.global_size, m.global_cell)
