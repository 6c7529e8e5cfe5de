"""Scenarios: batched sampling, validity checks and a file format (docs/model.md §1).

A batched scenario is a :class:`TensorDict` of batch size ``[B]`` laid out as in
``docs/env_contract.md``. :func:`sample_scenarios` draws valid ones in batch:

* rectangles are placed one slot at a time, each from a batch of candidates per scenario (the
  first valid candidate wins), because drawing a whole layout at once and rejecting it accepts
  only ~0.4 % of draws at 3 BZ + 3 NFZ;
* GEs and OUs are placed the same way, all slots at once (they do not constrain each other);
* connectivity is a flood fill on an occupancy grid, run for all scenarios together. The grid
  is bit-packed along the batch (64 scenarios per int64 word: 4096 scenarios on a 100 x 100
  grid are 640 k words), and each pass spreads along whole free runs by doubling shifts, so a
  fill takes about one pass per turn of the path instead of one step per cell;
* scenarios that fail (no valid candidate, or disconnected) are resampled, just those rows,
  for at most ``sampling.layout_tries`` rounds; the entity counts of a row are drawn once and
  kept through its retries, so counts stay uniform in {min..max}.

A :class:`Scenario` is one scenario as plain Python lists, for hand-made layouts and fixed
evaluation sets; :func:`stack_scenarios` / :func:`unstack_scenarios` convert exactly, and
:func:`save_scenarios` / :func:`load_scenarios` keep a list of them in a JSON file.
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import torch
from tensordict import TensorDict, TensorDictBase
from torch import Tensor

from uavlae.envs.config import EnvConfig
from uavlae.files import dump_json

__all__ = [
    "SCENARIO_KEYS",
    "Scenario",
    "sample_scenarios",
    "validate_scenarios",
    "scenario_violations",
    "check_connectivity",
    "stack_scenarios",
    "unstack_scenarios",
    "save_scenarios",
    "load_scenarios",
]

SCENARIO_KEYS = (
    "nfz", "nfz_mask", "rz", "rz_mask", "bz", "bz_mask",
    "ge_pos", "ge_data", "ge_mask", "ou_pos", "ou_vel", "ou_mask", "start",
)  # fmt: skip
_ZONES = ("nfz", "rz", "bz")
_DTYPE = torch.float32
# first batch of candidates per slot; slots still empty draw the rest of their tries at once.
# Almost every slot is filled by the first batch, which keeps the point checks small.
_FIRST_TRIES = 4
_WORD = 64  # scenarios per packed int64 word of the occupancy grid


# ----------------------------------------------------------------------------- geometry
def _rect_gap(a: Tensor, b: Tensor) -> Tensor:
    # Euclidean distance between two closed rectangles; 0 when they touch or overlap
    dx = torch.maximum(b[..., 0] - a[..., 2], a[..., 0] - b[..., 2]).clamp_min(0.0)
    dy = torch.maximum(b[..., 1] - a[..., 3], a[..., 1] - b[..., 3]).clamp_min(0.0)
    return torch.hypot(dx, dy)


def _rects_overlap(a: Tensor, b: Tensor) -> Tensor:
    # open interiors intersect: touching edges are not an overlap
    return (a[..., 0] < b[..., 2]) & (b[..., 0] < a[..., 2]) & (a[..., 1] < b[..., 3]) & (b[..., 1] < a[..., 3])


def _point_in_rect(p: Tensor, r: Tensor) -> Tensor:
    return (p[..., 0] >= r[..., 0]) & (p[..., 0] <= r[..., 2]) & (p[..., 1] >= r[..., 1]) & (p[..., 1] <= r[..., 3])


def _clear_of(p: Tensor, rects: Tensor, mask: Tensor, margin: float) -> Tensor:
    """p [N, T, 2] against rects [N, Z, 4] (mask [N, Z]) -> [N, T]: outside all, >= margin."""
    if rects.shape[-2] == 0:
        return torch.ones(p.shape[:-1], dtype=torch.bool, device=p.device)
    px, py = p[..., 0].unsqueeze(-1), p[..., 1].unsqueeze(-1)  # [N, T, 1]
    r = rects.unsqueeze(-3)  # [N, 1, Z, 4]
    dx = torch.maximum(r[..., 0] - px, px - r[..., 2]).clamp_min_(0.0)
    dy = torch.maximum(r[..., 1] - py, py - r[..., 3]).clamp_min_(0.0)
    d2 = dx.mul_(dx).add_(dy.mul_(dy))  # squared distance: cheaper than hypot, same order
    ok = d2 >= margin * margin if margin > 0 else d2 > 0
    return (ok | ~mask.unsqueeze(-2)).all(-1)


def _area_rect(cfg: EnvConfig, device: torch.device) -> Tensor:
    return torch.tensor([0.0, 0.0, cfg.area.x_size, cfg.area.y_size], dtype=_DTYPE, device=device)


def _ta_la(cfg: EnvConfig, device: torch.device) -> Tensor:
    return torch.tensor([cfg.area.takeoff, cfg.area.landing], dtype=_DTYPE, device=device)  # [2, 4]


# ----------------------------------------------------------------------- occupancy grid
@dataclass(frozen=True)
class _Grid:
    nx: int
    ny: int
    cell_x: float
    cell_y: float

    @staticmethod
    def of(cfg: EnvConfig) -> "_Grid":
        # cells of at most sampling.grid_cell that tile the area exactly
        c = cfg.sampling.grid_cell
        nx = max(1, math.ceil(cfg.area.x_size / c - 1e-9))
        ny = max(1, math.ceil(cfg.area.y_size / c - 1e-9))
        return _Grid(nx, ny, cfg.area.x_size / nx, cfg.area.y_size / ny)

    def centres(self, device: torch.device) -> tuple[Tensor, Tensor]:
        cx = (torch.arange(self.nx, device=device, dtype=torch.float64) + 0.5) * self.cell_x
        cy = (torch.arange(self.ny, device=device, dtype=torch.float64) + 0.5) * self.cell_y
        return cx.to(_DTYPE), cy.to(_DTYPE)

    def cell_of(self, p: Tensor) -> Tensor:
        """Flat cell index j * nx + i of points p [..., 2] (clipped into the grid)."""
        p = torch.nan_to_num(p, nan=0.0, posinf=0.0, neginf=0.0)
        i = torch.floor(p[..., 0] / self.cell_x).clamp(0, self.nx - 1).long()
        j = torch.floor(p[..., 1] / self.cell_y).clamp(0, self.ny - 1).long()
        return j * self.nx + i


def _pack(x: Tensor) -> Tensor:
    """bool [B, *S] -> int64 [ceil(B/64), *S]; scenario b is bit b % 64 of word b // 64."""
    B, shape = x.shape[0], x.shape[1:]
    nb = -(-B // _WORD)
    flat = x.reshape(B, -1)
    if nb * _WORD != B:
        flat = torch.cat((flat, flat.new_zeros(nb * _WORD - B, flat.shape[1])))
    u = flat.view(nb, 8, 8, -1).to(torch.uint8)  # scenario 64 w + 8 a + c
    byte = u[:, :, 0].clone()
    for c in range(1, 8):
        byte |= u[:, :, c] << c
    word = byte[:, 0].long()
    for a in range(1, 8):
        word |= byte[:, a].long() << (8 * a)
    return word.view(nb, *shape)


def _bits_at(packed: Tensor, b: Tensor, flat_idx: Tensor) -> Tensor:
    """Bit of scenario b at flat cell index flat_idx of packed [nb, ny, nx] (same shapes)."""
    words = packed.view(packed.shape[0], -1)[b // _WORD, flat_idx]
    return ((words >> (b % _WORD)) & 1).bool()


def _point_bits(grid: _Grid, nb: int, b: Tensor, flat_idx: Tensor, present: Tensor) -> Tensor:
    """Packed grid with the bits of the given cells set; one cell per scenario per call."""
    out = torch.zeros(nb * grid.ny * grid.nx, dtype=torch.int64, device=b.device)
    val = torch.where(present, torch.ones_like(b) << (b % _WORD), torch.zeros_like(b))
    # one cell per scenario: different scenarios own different bits, so a sum is a bitwise or
    out.index_add_(0, (b // _WORD) * (grid.ny * grid.nx) + flat_idx, val)
    return out.view(nb, grid.ny, grid.nx)


def _blocked(cfg: EnvConfig, grid: _Grid, rects: Tensor, mask: Tensor) -> Tensor:
    """Packed cells whose centre lies within d_min of a rectangle (or inside it).

    The inflated rectangle is split into row bands that share one blocked column set: the rows
    level with the rectangle (columns within d_min) and each corner row above / below it
    (columns within sqrt(d_min^2 - dy^2)). A band is a (rows, columns) product, so it packs as
    two small bit vectors and one broadcast and.
    """
    n, R = mask.shape
    dev = rects.device
    d = cfg.safety.d_min
    cx, cy = grid.centres(dev)
    x0, y0, x1, y1 = rects.unbind(-1)  # [n, R]
    dx = torch.maximum(x0.unsqueeze(-1) - cx, cx - x1.unsqueeze(-1)).clamp_min(0.0)  # [n, R, nx]
    dy = torch.maximum(y0.unsqueeze(-1) - cy, cy - y1.unsqueeze(-1)).clamp_min(0.0)  # [n, R, ny]
    rows = [(dy == 0) & mask.unsqueeze(-1)]
    cols = [(dx < d) | (dx == 0)]
    k_max = math.ceil(d / grid.cell_y)
    if k_max > 0:
        above = torch.searchsorted(cy, y1.contiguous(), right=True)  # first row centre > y1
        below = torch.searchsorted(cy, y0.contiguous(), right=False) - 1  # last row centre < y0
        jr = torch.arange(grid.ny, device=dev)
        for k in range(k_max):
            for j in (above + k, below - k):
                inside = (j >= 0) & (j < grid.ny)
                jc = j.clamp(0, grid.ny - 1)
                dyk = torch.gather(dy, 2, jc.unsqueeze(-1)).squeeze(-1)  # [n, R]
                e2 = d * d - dyk * dyk  # squared half-width of the band beyond the edges
                rows.append((jr == jc.unsqueeze(-1)) & (inside & (dyk > 0) & (e2 > 0) & mask).unsqueeze(-1))
                cols.append(dx * dx < e2.unsqueeze(-1))
    prow = _pack(torch.stack(rows, 2))  # [nb, R, L, ny]
    pcol = _pack(torch.stack(cols, 2))  # [nb, R, L, nx]
    nb = prow.shape[0]
    prow, pcol = prow.view(nb, -1, grid.ny), pcol.view(nb, -1, grid.nx)
    out = torch.zeros(nb, grid.ny, grid.nx, dtype=torch.int64, device=dev)
    for t in range(prow.shape[1]):
        out |= prow[:, t, :, None] & pcol[:, t, None, :]
    return out


def _runs_free(free: Tensor, dim: int) -> list[tuple[int, Tensor]]:
    """Per shift s = 1, 2, 4, ...: bit set where the s cells ending here along ``dim`` are all free."""
    out, p, s = [], free, 1
    n = free.shape[dim]
    while s < n:
        out.append((s, p))
        nxt = p.clone()
        nxt.narrow(dim, 0, s).zero_()
        nxt.narrow(dim, s, n - s).bitwise_and_(p.narrow(dim, 0, n - s))
        p, s = nxt, 2 * s
    return out


def _sweep(r: Tensor, runs: dict[int, list[tuple[int, Tensor]]]) -> None:
    """One flood pass in place along +x, -x, +y, -y, each carried across a whole free run.

    Kogge-Stone doubling: after shifts 1, 2, 4, ... a reached cell has spread along its free
    run by up to 2^k - 1 cells, so a pass costs log2(side) ops per direction and a path needs
    about one pass per turn, not one dilation step per cell.
    """
    for dim in (2, 1):
        n = r.shape[dim]
        for s, p in runs[dim]:  # towards higher index: r[x] |= r[x - s] & free(x-s, x]
            r.narrow(dim, s, n - s).bitwise_or_(r.narrow(dim, 0, n - s) & p.narrow(dim, s, n - s))
        for s, p in runs[dim]:  # towards lower index: r[x] |= r[x + s] & free[x, x+s)
            r.narrow(dim, 0, n - s).bitwise_or_(r.narrow(dim, s, n - s) & p.narrow(dim, s - 1, n - s))


def _connected(cfg: EnvConfig, obst: Tensor, obst_mask: Tensor, start: Tensor, targets: Tensor, target_mask: Tensor) -> Tensor:
    """Do start [n, 2] and every present target [n, T, 2] share one free-space component?

    Occupancy: BZ ∪ NFZ (obst [n, R, 4]) inflated by d_min. The cells of the start and the
    targets count as free (they are placed >= d_min from every zone, but their cell centre may
    be closer). Flood fill from the start over 4-neighbour free cells, until nothing changes
    or all targets are reached.
    """
    n = start.shape[0]
    dev = start.device
    if n == 0:
        return torch.ones(0, dtype=torch.bool, device=dev)
    grid = _Grid.of(cfg)
    b = torch.arange(n, device=dev)
    seed_idx = grid.cell_of(start)
    t_idx = grid.cell_of(targets)  # [n, T]
    always = torch.ones(n, dtype=torch.bool, device=dev)
    free = ~_blocked(cfg, grid, obst, obst_mask)
    nb = free.shape[0]
    seed = _point_bits(grid, nb, b, seed_idx, always)
    free |= seed
    for t in range(targets.shape[1]):
        free |= _point_bits(grid, nb, b, t_idx[:, t], target_mask[:, t])
    bt = b.unsqueeze(-1).expand_as(t_idx)

    def all_reached(r: Tensor) -> Tensor:
        return (_bits_at(r, bt, t_idx) | ~target_mask).all(-1)

    runs = {dim: _runs_free(free, dim) for dim in (1, 2)}
    reached = seed.clone()
    for _ in range(grid.nx * grid.ny):
        before = reached.clone()
        _sweep(reached, runs)
        if torch.equal(reached, before) or bool(all_reached(reached).all()):
            break
    return all_reached(reached)


def _targets(cfg: EnvConfig, ge_pos: Tensor, ge_mask: Tensor) -> tuple[Tensor, Tensor]:
    n = ge_pos.shape[0]
    la = cfg.area.landing
    la_c = torch.tensor([(la[0] + la[2]) / 2, (la[1] + la[3]) / 2], dtype=_DTYPE, device=ge_pos.device)
    pts = torch.cat((la_c.expand(n, 1, 2), ge_pos), 1)
    m = torch.cat((torch.ones(n, 1, dtype=torch.bool, device=ge_pos.device), ge_mask), 1)
    return pts, m


def check_connectivity(cfg: EnvConfig, td: TensorDictBase) -> Tensor:
    """bool [B]: SL, the LA centre and every present GE lie in one free-space component of the
    occupancy grid (BZ ∪ NFZ inflated by ``safety.d_min``, cells <= ``sampling.grid_cell``)."""
    obst = torch.cat((td["bz"], td["nfz"]), 1).to(_DTYPE)
    om = torch.cat((td["bz_mask"], td["nfz_mask"]), 1)
    pts, pm = _targets(cfg, td["ge_pos"].to(_DTYPE), td["ge_mask"])
    return _connected(cfg, obst, om, td["start"].to(_DTYPE), pts, pm)


# ----------------------------------------------------------------------------- sampling
_FAIL_HINTS = {
    "bz": "a building zone (BZ) found no place clear of the other BZ/NFZ and >= safety.d_safe from TA/LA "
    "in sampling.rect_tries candidates; loosen zones.n_bz / zones.n_nfz, zones.side_min / zones.side_max, "
    "safety.d_safe or the area size, or raise sampling.rect_tries",
    "nfz": "a no-fly zone (NFZ) found no place clear of the other BZ/NFZ and >= safety.d_safe from TA/LA "
    "in sampling.rect_tries candidates; loosen zones.n_nfz / zones.n_bz, zones.side_min / zones.side_max, "
    "safety.d_safe or the area size, or raise sampling.rect_tries",
    "rz": "a residential zone (RZ) found no place off TA/LA in sampling.rect_tries candidates; "
    "shrink zones.side_min or area.takeoff / area.landing, or raise sampling.rect_tries",
    "ge": "a ground equipment (GE) found no free spot >= safety.d_min from every zone and off TA/LA in "
    "sampling.point_tries candidates; use fewer or smaller zones (zones.*), a smaller safety.d_min, "
    "or raise sampling.point_tries",
    "ou": "another UAV (OU) found no spot >= safety.d_min from every BZ/NFZ and >= safety.d_safe from "
    "the start in sampling.point_tries candidates; use fewer or smaller BZ/NFZ, a smaller safety.d_safe, "
    "or raise sampling.point_tries",
    "connectivity": "the start, LA and all GEs were never in one free-space component (BZ ∪ NFZ inflated "
    "by safety.d_min); use fewer or smaller BZ/NFZ (zones.n_bz, zones.n_nfz, zones.side_max), a smaller "
    "safety.d_min, or raise sampling.layout_tries",
}
_FAIL_CODES = {name: i + 1 for i, name in enumerate(_FAIL_HINTS)}
_SLOT_STRIDE = 1 << 16  # failure = code * stride + rectangle slot


def _first_valid(
    n: int,
    tries: int,
    draw: Callable[[int, int], Tensor],
    valid: Callable[[Tensor, Tensor], Tensor],
    width: int,
    device: torch.device,
) -> tuple[Tensor, Tensor]:
    """For each of n rows, the first valid of up to ``tries`` candidates.

    draw(m, k) -> [m, k, width] candidates for m rows; valid(rows, cand) -> bool [m, k]. A first batch of ``_FIRST_TRIES`` candidates goes to every row;
    rows still empty draw their remaining tries at once. Returns (values [n, width], found
    bool [n])."""
    out = torch.zeros(n, width, dtype=_DTYPE, device=device)
    found = torch.zeros(n, dtype=torch.bool, device=device)
    rows = torch.arange(n, device=device)
    for k in (min(tries, _FIRST_TRIES), tries - min(tries, _FIRST_TRIES)):
        if k == 0 or rows.numel() == 0:
            continue
        cand = draw(rows.numel(), k)
        ok = valid(rows, cand)
        has = ok.any(1)
        first = ok.to(torch.uint8).argmax(1)  # argmax returns the first maximal index
        pick = cand[torch.arange(rows.numel(), device=device), first]
        out[rows[has]] = pick[has]
        found[rows[has]] = True
        rows = rows[~has]
    return out, found


def _rand(g: torch.Generator, *shape: int) -> Tensor:
    return torch.rand(*shape, generator=g, device=g.device, dtype=_DTYPE)


def _draw_counts(cr: Any, n: int, g: torch.Generator) -> Tensor:
    return torch.randint(cr.min, cr.max + 1, (n,), generator=g, device=g.device)


class _Layout:
    """One layout attempt for each row of ``counts`` (:func:`_sample_layouts`), placed kind by
    kind in a fixed order (the draws from ``g`` come in that order: a seed gives one layout);
    ``fail`` holds each row's failure code (0 = ok) and ``fail_slot`` the BZ / NFZ slot."""

    def __init__(self, cfg: EnvConfig, counts: dict[str, Tensor], g: torch.Generator):
        self.cfg, self.counts, self.g = cfg, counts, g
        self.dev = g.device
        self.n = counts["bz"].shape[0]
        self.fail = torch.zeros(self.n, dtype=torch.long, device=self.dev)
        self.fail_slot = torch.zeros(self.n, dtype=torch.long, device=self.dev)
        self.tala = _ta_la(cfg, self.dev)
        self.pads = {"bz": cfg.zones.n_bz, "nfz": cfg.zones.n_nfz, "rz": cfg.zones.n_rz}
        self.out: dict[str, Tensor] = {}

    def draw_rect(self, m: int, k: int) -> Tensor:
        z, a = self.cfg.zones, self.cfg.area
        u = _rand(self.g, m, k, 4)
        w = z.side_min + (z.side_max - z.side_min) * u[..., 0]
        h = z.side_min + (z.side_max - z.side_min) * u[..., 1]
        x0 = u[..., 2] * (a.x_size - w)
        y0 = u[..., 3] * (a.y_size - h)
        return torch.stack((x0, y0, (x0 + w).clamp(max=a.x_size), (y0 + h).clamp(max=a.y_size)), -1)

    def draw_point(self, m: int, k: int) -> Tensor:
        u = _rand(self.g, m, k, 2)
        return u * torch.tensor([self.cfg.area.x_size, self.cfg.area.y_size], dtype=_DTYPE, device=self.dev)

    def place_obstacles(self) -> None:
        """BZ and NFZ: one slot at a time, clear of the already placed ones and of TA/LA by d_safe."""
        z, s, dev, n = self.cfg.zones, self.cfg.safety, self.dev, self.n
        self.obst = torch.zeros(n, z.n_bz.max + z.n_nfz.max, 4, dtype=_DTYPE, device=dev)
        self.obst_m = torch.zeros(n, z.n_bz.max + z.n_nfz.max, dtype=torch.bool, device=dev)
        slot = 0
        for kind in ("bz", "nfz"):
            rects = torch.zeros(n, self.pads[kind].padded, 4, dtype=_DTYPE, device=dev)
            for k in range(self.pads[kind].max):
                rows = torch.nonzero((self.counts[kind] > k) & (self.fail == 0)).squeeze(-1)
                placed, placed_m = self.obst[rows, :slot], self.obst_m[rows, :slot]

                def ok_obst(r: Tensor, c: Tensor, placed: Tensor = placed, placed_m: Tensor = placed_m,
                            slot: int = slot) -> Tensor:
                    clear = (_rect_gap(c.unsqueeze(-2), self.tala) >= s.d_safe).all(-1)  # [m, k]
                    if slot:
                        hit = _rects_overlap(c.unsqueeze(-2), placed[r].unsqueeze(-3)) & placed_m[r].unsqueeze(-2)
                        clear &= ~hit.any(-1)
                    return clear

                val, found = _first_valid(rows.numel(), self.cfg.sampling.rect_tries, self.draw_rect, ok_obst, 4, dev)
                rects[rows, k] = val
                self.obst[rows, slot] = val
                self.obst_m[rows, slot] = found
                self.fail[rows[~found]] = _FAIL_CODES[kind]
                self.fail_slot[rows[~found]] = k
                slot += 1
            self.out[kind] = rects

    def place_rz(self) -> None:
        """RZ: only kept off TA and LA, so all slots are independent and placed at once."""
        z, dev = self.cfg.zones, self.dev
        rz = torch.zeros(self.n, z.n_rz.padded, 4, dtype=_DTYPE, device=dev)
        rz_m = torch.arange(z.n_rz.padded, device=dev) < self.counts["rz"].unsqueeze(-1)
        pairs = torch.nonzero(rz_m & (self.fail == 0).unsqueeze(-1))
        val, found = _first_valid(
            pairs.shape[0], self.cfg.sampling.rect_tries, self.draw_rect,
            lambda r, c: ~_rects_overlap(c.unsqueeze(-2), self.tala).any(-1), 4, dev,
        )  # fmt: skip
        rz[pairs[:, 0], pairs[:, 1]] = val
        self.fail[pairs[~found, 0]] = _FAIL_CODES["rz"]
        self.out["rz"] = rz
        self.masks = {k: torch.arange(self.pads[k].padded, device=dev) < self.counts[k].unsqueeze(-1) for k in self.pads}

    def place_ges(self) -> None:
        """GE: outside every zone by >= d_min, outside TA/LA; data uniform in [data_min, data_max]."""
        cfg, dev, out, masks = self.cfg, self.dev, self.out, self.masks
        zones = torch.cat((out["bz"], out["nfz"], out["rz"]), 1)
        zones_m = torch.cat((masks["bz"], masks["nfz"], masks["rz"]), 1)
        ge_m = torch.arange(cfg.ge.count.padded, device=dev) < self.counts["ge"].unsqueeze(-1)
        pairs = torch.nonzero(ge_m & (self.fail == 0).unsqueeze(-1))

        def ok_ge(r: Tensor, c: Tensor) -> Tensor:
            b = pairs[r, 0]
            off_tala = ~_point_in_rect(c.unsqueeze(-2), self.tala).any(-1)
            return off_tala & _clear_of(c, zones[b], zones_m[b], cfg.safety.d_min)

        val, found = _first_valid(pairs.shape[0], cfg.sampling.point_tries, self.draw_point, ok_ge, 2, dev)
        ge_pos = torch.zeros(self.n, cfg.ge.count.padded, 2, dtype=_DTYPE, device=dev)
        ge_pos[pairs[:, 0], pairs[:, 1]] = val
        self.fail[pairs[~found, 0]] = _FAIL_CODES["ge"]
        dv = cfg.ge.data_min + (cfg.ge.data_max - cfg.ge.data_min) * torch.rand(
            self.n, cfg.ge.count.padded, generator=self.g, device=dev, dtype=_DTYPE
        )
        out["ge_pos"], out["ge_data"], out["ge_mask"] = ge_pos, torch.where(ge_m, dv, 0.0), ge_m

    def place_ous(self) -> None:
        """OU: outside BZ/NFZ by >= d_min, >= d_safe from the start; speed and heading uniform."""
        cfg, dev, s = self.cfg, self.dev, self.cfg.safety
        start = torch.tensor(cfg.area.start_xy, dtype=_DTYPE, device=dev)
        ou_m = torch.arange(cfg.ou.count.padded, device=dev) < self.counts["ou"].unsqueeze(-1)
        pairs = torch.nonzero(ou_m & (self.fail == 0).unsqueeze(-1))

        def ok_ou(r: Tensor, c: Tensor) -> Tensor:
            b = pairs[r, 0]
            far = torch.linalg.vector_norm(c - start, dim=-1) >= s.d_safe
            return far & _clear_of(c, self.obst[b], self.obst_m[b], s.d_min)

        val, found = _first_valid(pairs.shape[0], cfg.sampling.point_tries, self.draw_point, ok_ou, 2, dev)
        ou_pos = torch.zeros(self.n, cfg.ou.count.padded, 2, dtype=_DTYPE, device=dev)
        ou_pos[pairs[:, 0], pairs[:, 1]] = val
        self.fail[pairs[~found, 0]] = _FAIL_CODES["ou"]
        u = torch.rand(self.n, cfg.ou.count.padded, 2, generator=self.g, device=dev, dtype=_DTYPE)
        speed = cfg.motion.v_max * u[..., 0]  # |v| ~ U[0, v_max]
        heading = 2 * math.pi * u[..., 1]  # heading ~ U[0, 2π)
        vel = torch.stack((speed * torch.cos(heading), speed * torch.sin(heading)), -1)
        self.out["ou_pos"], self.out["ou_vel"], self.out["ou_mask"] = ou_pos, torch.where(ou_m.unsqueeze(-1), vel, 0.0), ou_m
        for k in self.pads:
            self.out[f"{k}_mask"] = self.masks[k]
        self.out["start"] = start.expand(self.n, 2).clone()

    def check_connected(self) -> None:
        """Connectivity, for the rows still alive."""
        rows = torch.nonzero(self.fail == 0).squeeze(-1)
        if rows.numel():
            pts, pm = _targets(self.cfg, self.out["ge_pos"][rows], self.out["ge_mask"][rows])
            ok = _connected(self.cfg, self.obst[rows], self.obst_m[rows], self.out["start"][rows], pts, pm)
            self.fail[rows[~ok]] = _FAIL_CODES["connectivity"]


def _sample_layouts(cfg: EnvConfig, counts: dict[str, Tensor], g: torch.Generator) -> tuple[dict[str, Tensor], Tensor]:
    """One layout attempt for each row of ``counts``; returns (fields, fail code [n], 0 = ok)."""
    layout = _Layout(cfg, counts, g)
    layout.place_obstacles()
    layout.place_rz()
    layout.place_ges()
    layout.place_ous()
    layout.check_connected()
    return layout.out, layout.fail * _SLOT_STRIDE + layout.fail_slot


def sample_scenarios(
    cfg: EnvConfig, batch_size: int, generator: torch.Generator, device: torch.device | str | None = None
) -> TensorDict:
    """Draw ``batch_size`` valid scenarios (SPEC §1) as a TensorDict of batch size ``[B]``.

    All randomness comes from ``generator`` (sampling runs on its device, the result is moved
    to ``device``, default that same device); equal seeds give equal scenarios. Raises
    ``RuntimeError`` naming what could not be placed when some rows are still invalid after
    ``cfg.sampling.layout_tries`` rounds.
    """
    if batch_size < 1:
        raise ValueError(f"batch_size must be >= 1, got {batch_size}")
    g = generator
    dev = g.device
    counts = {
        "nfz": _draw_counts(cfg.zones.n_nfz, batch_size, g),
        "rz": _draw_counts(cfg.zones.n_rz, batch_size, g),
        "bz": _draw_counts(cfg.zones.n_bz, batch_size, g),
        "ge": _draw_counts(cfg.ge.count, batch_size, g),
        "ou": _draw_counts(cfg.ou.count, batch_size, g),
    }
    result: dict[str, Tensor] | None = None
    pending = torch.arange(batch_size, device=dev)
    fail = torch.zeros(batch_size, dtype=torch.long, device=dev)
    for _ in range(cfg.sampling.layout_tries):
        fields, f = _sample_layouts(cfg, {k: c[pending] for k, c in counts.items()}, g)
        if result is None:
            result = fields
        else:
            done = f == 0
            for k, v in fields.items():
                result[k][pending[done]] = v[done]
        fail[pending] = f
        pending = pending[f != 0]
        if pending.numel() == 0:
            break
    if pending.numel():
        names = {code: name for name, code in _FAIL_CODES.items()}
        codes, freq = torch.unique(fail[pending], return_counts=True)
        lines = []
        for code, c in zip(codes.tolist(), freq.tolist()):
            name = names[code // _SLOT_STRIDE]
            at = f" at {name.upper()} #{code % _SLOT_STRIDE + 1}" if name in ("bz", "nfz") else ""
            lines.append(f"{c} row(s){at}: {_FAIL_HINTS[name]}")
        reasons = "\n  ".join(lines)
        raise RuntimeError(
            f"could not sample {pending.numel()} of {batch_size} scenarios within "
            f"sampling.layout_tries={cfg.sampling.layout_tries} rounds (last failure per row):\n  {reasons}"
        )
    assert result is not None
    td = TensorDict({k: result[k] for k in SCENARIO_KEYS}, batch_size=[batch_size], device=dev)
    return td if device is None else td.to(device)


# --------------------------------------------------------------------------- validation
def _check_layout(td: TensorDictBase) -> None:
    missing = [k for k in SCENARIO_KEYS if k not in td.keys()]
    if missing:
        raise ValueError(f"scenario TensorDict lacks key(s) {missing}")
    B = td.batch_size[0]
    for k in _ZONES:
        if td[k].shape[-1] != 4 or td[k].shape[:-1] != td[f"{k}_mask"].shape:
            raise ValueError(f"{k} must be [B, P, 4] with {k}_mask [B, P]; got {tuple(td[k].shape)}")
    for k, m in (("ge_pos", "ge_mask"), ("ou_pos", "ou_mask"), ("ou_vel", "ou_mask")):
        if td[k].shape[-1] != 2 or td[k].shape[:-1] != td[m].shape:
            raise ValueError(f"{k} must be [B, N, 2] with {m} [B, N]; got {tuple(td[k].shape)}")
    if td["ge_data"].shape != td["ge_mask"].shape or tuple(td["start"].shape) != (B, 2):
        raise ValueError("ge_data must be [B, G] like ge_mask and start [B, 2]")


def scenario_violations(cfg: EnvConfig, td: TensorDictBase, check_ranges: bool = False) -> list[list[str]]:
    """For each row of a batched scenario, the list of SPEC §1 rules it breaks ([] if valid).

    ``check_ranges`` also checks what sampling guarantees beyond validity: counts in
    {min..max}, sides in [side_min, side_max], GE data in [data_min, data_max], start = SL.
    """
    _check_layout(td)
    td = td.to("cpu") if td.device is None or td.device.type != "cpu" else td
    f = {k: td[k].to(_DTYPE) if td[k].is_floating_point() else td[k] for k in SCENARIO_KEYS}
    B = td.batch_size[0]
    rules: dict[str, Tensor] = {}
    for part in (_layout_violations, _ge_violations, _ou_violations, *((_range_violations,) if check_ranges else ())):
        rules.update({name: bad.reshape(B) for name, bad in part(cfg, f).items()})
    rules["SL, LA and the GEs are not connected in free space"] = ~check_connectivity(cfg, td)
    bad_rows = torch.stack(list(rules.values()), -1)  # [B, n_rules]
    names = list(rules)
    out: list[list[str]] = [[] for _ in range(B)]
    for b, r in torch.nonzero(bad_rows).tolist():
        out[b].append(names[r])
    return out


def _layout_violations(cfg: EnvConfig, f: dict[str, Tensor]) -> dict[str, Tensor]:
    """Numbers, masks and the zones' rectangles (SPEC §1)."""
    s, a = cfg.safety, cfg.area
    B = f["start"].shape[0]
    tala = _ta_la(cfg, torch.device("cpu"))
    out: dict[str, Tensor] = {}
    finite = torch.ones(B, dtype=torch.bool)
    for v in f.values():
        if v.is_floating_point():
            finite &= torch.isfinite(v).reshape(B, -1).all(-1)
    out["non-finite numbers"] = ~finite
    for k in ("nfz_mask", "rz_mask", "bz_mask", "ge_mask", "ou_mask"):
        m = f[k]
        out[f"{k} is not present-entries-first"] = (m[:, 1:] & ~m[:, :-1]).any(-1)
    for k in _ZONES:
        r, m = f[k], f[f"{k}_mask"]
        bad = (r[..., 2] <= r[..., 0]) | (r[..., 3] <= r[..., 1])
        bad |= (r[..., 0] < 0) | (r[..., 1] < 0) | (r[..., 2] > a.x_size) | (r[..., 3] > a.y_size)
        out[f"{k} rectangle malformed or outside the area"] = (bad & m).any(-1)
    obst = torch.cat((f["bz"], f["nfz"]), 1)
    om = torch.cat((f["bz_mask"], f["nfz_mask"]), 1)
    pair = _rects_overlap(obst.unsqueeze(2), obst.unsqueeze(1)) & om.unsqueeze(2) & om.unsqueeze(1)
    pair &= ~torch.eye(obst.shape[1], dtype=torch.bool).unsqueeze(0)
    out["BZ/NFZ rectangles overlap"] = pair.any(-1).any(-1)
    near = (_rect_gap(obst.unsqueeze(-2), tala) < s.d_safe).any(-1) & om
    out["BZ/NFZ closer than safety.d_safe to TA/LA"] = near.any(-1)
    out["RZ overlaps TA/LA"] = (_rects_overlap(f["rz"].unsqueeze(-2), tala).any(-1) & f["rz_mask"]).any(-1)
    out["start outside the area"] = ~_point_in_rect(f["start"], _area_rect(cfg, torch.device("cpu")))
    return out


def _ge_violations(cfg: EnvConfig, f: dict[str, Tensor]) -> dict[str, Tensor]:
    """Where the ground equipment lies and what it holds (SPEC §1)."""
    s = cfg.safety
    gp, gm = f["ge_pos"], f["ge_mask"]
    zones = torch.cat((f["bz"], f["nfz"], f["rz"]), 1)
    zm = torch.cat((f["bz_mask"], f["nfz_mask"], f["rz_mask"]), 1)
    return {
        "GE outside the area": (~_point_in_rect(gp, _area_rect(cfg, torch.device("cpu"))) & gm).any(-1),
        "GE inside a zone or closer than safety.d_min to one": (~_clear_of(gp, zones, zm, s.d_min) & gm).any(-1),
        "GE inside TA/LA": (_point_in_rect(gp.unsqueeze(-2), _ta_la(cfg, torch.device("cpu"))).any(-1) & gm).any(-1),
        "GE data negative": ((f["ge_data"] < 0) & gm).any(-1),
    }


def _ou_violations(cfg: EnvConfig, f: dict[str, Tensor]) -> dict[str, Tensor]:
    """Where the other UAVs start and how fast they fly (SPEC §1, §2)."""
    s = cfg.safety
    op, omk = f["ou_pos"], f["ou_mask"]
    obst = torch.cat((f["bz"], f["nfz"]), 1)
    om = torch.cat((f["bz_mask"], f["nfz_mask"]), 1)
    far = torch.linalg.vector_norm(op - f["start"].unsqueeze(1), dim=-1) >= s.d_safe
    v_tol = cfg.motion.v_max * 1e-5  # float32 rounding of speed * (cos, sin)
    fast = torch.linalg.vector_norm(f["ou_vel"], dim=-1) > cfg.motion.v_max + v_tol
    return {
        "OU outside the area": (~_point_in_rect(op, _area_rect(cfg, torch.device("cpu"))) & omk).any(-1),
        "OU inside a BZ/NFZ or closer than safety.d_min to one": (~_clear_of(op, obst, om, s.d_min) & omk).any(-1),
        "OU closer than safety.d_safe to the start": (~far & omk).any(-1),
        "OU faster than motion.v_max": (fast & omk).any(-1),
    }


def _range_violations(cfg: EnvConfig, f: dict[str, Tensor]) -> dict[str, Tensor]:
    """What sampling guarantees beyond validity (counts, sides, data, the start)."""
    a, z = cfg.area, cfg.zones
    out: dict[str, Tensor] = {}
    tol = 1e-4 * max(a.x_size, a.y_size)  # float32 rounding of stored corners
    for k, cr in (("nfz", z.n_nfz), ("rz", z.n_rz), ("bz", z.n_bz), ("ge", cfg.ge.count), ("ou", cfg.ou.count)):
        c = f[f"{k}_mask"].sum(-1)
        out[f"{k} count outside [{cr.min}, {cr.max}]"] = (c < cr.min) | (c > cr.max)
    for k in _ZONES:
        r, m = f[k], f[f"{k}_mask"]
        side = torch.stack((r[..., 2] - r[..., 0], r[..., 3] - r[..., 1]), -1)
        bad = ((side < z.side_min - tol) | (side > z.side_max + tol)).any(-1) & m
        out[f"{k} side outside [zones.side_min, zones.side_max]"] = bad.any(-1)
    dv, gm = f["ge_data"], f["ge_mask"]
    out["GE data outside [ge.data_min, ge.data_max]"] = (((dv < cfg.ge.data_min) | (dv > cfg.ge.data_max)) & gm).any(-1)
    out["start differs from area.start_xy"] = (f["start"] != torch.tensor(a.start_xy, dtype=_DTYPE)).any(-1)
    return out


def validate_scenarios(cfg: EnvConfig, td: TensorDictBase, check_ranges: bool = False) -> Tensor:
    """bool [B] (on td's device): which rows satisfy every SPEC §1 validity rule."""
    viol = scenario_violations(cfg, td, check_ranges)
    return torch.tensor([not v for v in viol], dtype=torch.bool, device=td.device)


# ------------------------------------------------------------------ one scenario, files
Rect4 = tuple[float, float, float, float]
XY = tuple[float, float]
_RECT_LIST_KEYS = ("nfz", "rz", "bz")
_XY_LIST_KEYS = ("ge_pos", "ou_pos", "ou_vel")
_DICT_KEYS = ("nfz", "rz", "bz", "ge_pos", "ge_data", "ou_pos", "ou_vel", "start")


def _num(v: Any, where: str) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise ValueError(f"{where}: expected a number, got {v!r}")
    x = float(v)
    if not math.isfinite(x):
        raise ValueError(f"{where}: number must be finite, got {v!r}")
    return x


def _tuple(v: Any, n: int, where: str) -> tuple[float, ...]:
    if not isinstance(v, (list, tuple)) or len(v) != n:
        raise ValueError(f"{where}: expected a list of {n} numbers, got {v!r}")
    return tuple(_num(x, f"{where}[{i}]") for i, x in enumerate(v))


def _list(v: Any, where: str) -> list[Any]:
    if not isinstance(v, (list, tuple)):
        raise ValueError(f"{where}: expected a list, got {type(v).__name__}")
    return list(v)


@dataclass
class Scenario:
    """One scenario as plain Python data; rectangles are (x0, y0, x1, y1) in metres."""

    nfz: list[Rect4] = field(default_factory=list)
    rz: list[Rect4] = field(default_factory=list)
    bz: list[Rect4] = field(default_factory=list)
    ge_pos: list[XY] = field(default_factory=list)
    ge_data: list[float] = field(default_factory=list)
    ou_pos: list[XY] = field(default_factory=list)
    ou_vel: list[XY] = field(default_factory=list)
    start: XY = (0.0, 0.0)

    def to_dict(self) -> dict[str, Any]:
        d: dict[str, Any] = {k: [list(map(float, r)) for r in getattr(self, k)] for k in _RECT_LIST_KEYS + _XY_LIST_KEYS}
        d["ge_data"] = [float(x) for x in self.ge_data]
        d["start"] = [float(x) for x in self.start]
        return {k: d[k] for k in _DICT_KEYS}

    @classmethod
    def from_dict(cls, d: Any) -> "Scenario":
        """Checked construction: ValueError on missing / extra keys, bad shapes, non-finite numbers."""
        if not isinstance(d, dict):
            raise ValueError(f"a scenario must be a JSON object, got {type(d).__name__}")
        missing = [k for k in _DICT_KEYS if k not in d]
        extra = sorted(set(d) - set(_DICT_KEYS), key=str)
        if missing or extra:
            raise ValueError(f"scenario keys: missing {missing}, unexpected {extra}; expected exactly {list(_DICT_KEYS)}")
        kw: dict[str, Any] = {}
        for k in _RECT_LIST_KEYS:
            rects = [_tuple(r, 4, f"{k}[{i}]") for i, r in enumerate(_list(d[k], k))]
            for i, r in enumerate(rects):
                if not (r[2] > r[0] and r[3] > r[1]):
                    raise ValueError(f"{k}[{i}] = {list(r)} must be (x0, y0, x1, y1) with x1 > x0 and y1 > y0")
            kw[k] = rects
        for k in _XY_LIST_KEYS:
            kw[k] = [_tuple(p, 2, f"{k}[{i}]") for i, p in enumerate(_list(d[k], k))]
        kw["ge_data"] = [_num(x, f"ge_data[{i}]") for i, x in enumerate(_list(d["ge_data"], "ge_data"))]
        kw["start"] = _tuple(d["start"], 2, "start")
        if len(kw["ge_data"]) != len(kw["ge_pos"]):
            raise ValueError(f"ge_data has {len(kw['ge_data'])} entries but ge_pos has {len(kw['ge_pos'])}")
        if len(kw["ou_vel"]) != len(kw["ou_pos"]):
            raise ValueError(f"ou_vel has {len(kw['ou_vel'])} entries but ou_pos has {len(kw['ou_pos'])}")
        return cls(**kw)

    def to_json(self, path: str | os.PathLike[str]) -> None:
        dump_json(path, self.to_dict(), indent=None, allow_nan=False)

    @classmethod
    def from_json(cls, path: str | os.PathLike[str]) -> "Scenario":
        return cls.from_dict(_read_json(path))


def _read_json(path: str | os.PathLike[str]) -> Any:
    try:
        with open(path, encoding="utf-8") as fh:
            return json.load(fh, parse_constant=_reject_constant)
    except json.JSONDecodeError as e:
        raise ValueError(f"{path}: not valid JSON ({e})") from None


def _reject_constant(name: str) -> float:
    raise ValueError(f"non-finite number {name} in scenario JSON")


def stack_scenarios(scenarios: Sequence[Scenario], cfg: EnvConfig, device: torch.device | str | None = None) -> TensorDict:
    """Batch scenarios into the contract TensorDict, padded to ``cfg``'s padded maxima."""
    scenarios = list(scenarios)
    if not scenarios:
        raise ValueError("stack_scenarios needs at least one Scenario")
    B = len(scenarios)
    pads = {
        "nfz": ("zones.n_nfz", cfg.zones.n_nfz.padded),
        "rz": ("zones.n_rz", cfg.zones.n_rz.padded),
        "bz": ("zones.n_bz", cfg.zones.n_bz.padded),
        "ge_pos": ("ge.count", cfg.ge.count.padded),
        "ou_pos": ("ou.count", cfg.ou.count.padded),
    }
    for i, sc in enumerate(scenarios):
        if len(sc.ge_data) != len(sc.ge_pos) or len(sc.ou_vel) != len(sc.ou_pos):
            raise ValueError(f"scenario {i}: ge_data / ou_vel must have as many entries as ge_pos / ou_pos")
        for k, (name, p) in pads.items():
            if len(getattr(sc, k)) > p:
                raise ValueError(f"scenario {i} has {len(getattr(sc, k))} {k.split('_')[0]} entries but {name} pads to {p}")

    def fill(key: str, width: int, pad: int) -> tuple[Tensor, Tensor]:
        t = torch.zeros(B, pad, width, dtype=_DTYPE)
        m = torch.zeros(B, pad, dtype=torch.bool)
        for i, sc in enumerate(scenarios):
            rows = getattr(sc, key)
            if rows:
                t[i, : len(rows)] = torch.tensor([list(r) for r in rows], dtype=_DTYPE)
                m[i, : len(rows)] = True
        return t, m

    data: dict[str, Tensor] = {}
    for k in _ZONES:
        data[k], data[f"{k}_mask"] = fill(k, 4, pads[k][1])
    data["ge_pos"], data["ge_mask"] = fill("ge_pos", 2, pads["ge_pos"][1])
    dv = torch.zeros(B, pads["ge_pos"][1], dtype=_DTYPE)
    for i, sc in enumerate(scenarios):
        if sc.ge_data:
            dv[i, : len(sc.ge_data)] = torch.tensor(sc.ge_data, dtype=_DTYPE)
    data["ge_data"] = dv
    data["ou_pos"], data["ou_mask"] = fill("ou_pos", 2, pads["ou_pos"][1])
    data["ou_vel"], _ = fill("ou_vel", 2, pads["ou_pos"][1])
    data["start"] = torch.tensor([list(sc.start) for sc in scenarios], dtype=_DTYPE)
    td = TensorDict({k: data[k] for k in SCENARIO_KEYS}, batch_size=[B])
    return td if device is None else td.to(device)


def unstack_scenarios(td: TensorDictBase) -> list[Scenario]:
    """The rows of a batched scenario as :class:`Scenario` objects (present entries only)."""
    _check_layout(td)
    c = {k: td[k].detach().cpu() for k in SCENARIO_KEYS}
    out = []
    for b in range(td.batch_size[0]):

        def rows(key: str, mask: str, b: int = b) -> list[tuple[float, ...]]:
            return [tuple(r) for r in c[key][b][c[mask][b]].tolist()]

        out.append(
            Scenario(
                nfz=rows("nfz", "nfz_mask"),
                rz=rows("rz", "rz_mask"),
                bz=rows("bz", "bz_mask"),
                ge_pos=rows("ge_pos", "ge_mask"),
                ge_data=c["ge_data"][b][c["ge_mask"][b]].tolist(),
                ou_pos=rows("ou_pos", "ou_mask"),
                ou_vel=rows("ou_vel", "ou_mask"),
                start=tuple(c["start"][b].tolist()),
            )
        )
    return out


def save_scenarios(path: str | os.PathLike[str], scenarios: Sequence[Scenario]) -> None:
    """Write a list of scenarios (an evaluation set) as one JSON list, atomically."""
    dump_json(path, [sc.to_dict() for sc in scenarios], indent=None, allow_nan=False)


def load_scenarios(path: str | os.PathLike[str], cfg: EnvConfig | None = None) -> list[Scenario]:
    """The scenarios of a file; with ``cfg``, each checked against the world's rules (SPEC §1:
    zones inside the area, BZ/NFZ apart, GEs clear of zones, data not negative, ...): a file
    that breaks one is an error naming the file, the scenario and every rule it breaks."""
    data = _read_json(path)
    if not isinstance(data, list):
        raise ValueError(f"{path}: expected a JSON list of scenarios, got {type(data).__name__}")
    out = []
    for i, d in enumerate(data):
        try:
            out.append(Scenario.from_dict(d))
        except ValueError as e:
            raise ValueError(f"{path}: scenario {i}: {e}") from None
    if cfg is not None and out:
        bad = [(i, v) for i, v in enumerate(scenario_violations(cfg, stack_scenarios(out, cfg))) if v]
        if bad:
            raise ValueError(f"{path}: " + "; ".join(f"scenario {i} breaks: {', '.join(v)}" for i, v in bad[:5])
                             + (f"; and {len(bad) - 5} more scenarios" if len(bad) > 5 else ""))
    return out
