"""Scenario sampling, validity, connectivity and the JSON format (docs/model.md §1).

Validity is checked here with independent pure-Python geometry (float64, a BFS on the grid),
not only through :func:`validate_scenarios`.
"""

from __future__ import annotations

import json
import math
import os
import time
from collections import deque

import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from uavlae.envs.config import EnvConfig, make_env_config
from uavlae.envs.scenario import (
    SCENARIO_KEYS,
    Scenario,
    _pack,
    check_connectivity,
    load_scenarios,
    sample_scenarios,
    save_scenarios,
    scenario_violations,
    stack_scenarios,
    unstack_scenarios,
    validate_scenarios,
)

CFG = EnvConfig()
TOL = 1e-3  # metres: float32 storage vs the float64 checks below
FAST = settings(max_examples=12, deadline=None, suppress_health_check=[HealthCheck.too_slow])


def _sample(cfg: EnvConfig, b: int, seed: int):
    return sample_scenarios(cfg, b, torch.Generator().manual_seed(seed))


# ------------------------------------------------------------ independent reference geometry
def rect_gap(a, b) -> float:
    dx = max(b[0] - a[2], a[0] - b[2], 0.0)
    dy = max(b[1] - a[3], a[1] - b[3], 0.0)
    return math.hypot(dx, dy)


def overlap(a, b) -> bool:
    return a[0] < b[2] and b[0] < a[2] and a[1] < b[3] and b[1] < a[3]


def point_dist(p, r) -> float:
    dx = max(r[0] - p[0], p[0] - r[2], 0.0)
    dy = max(r[1] - p[1], p[1] - r[3], 0.0)
    return math.hypot(dx, dy)


def inside(p, r) -> bool:
    return r[0] <= p[0] <= r[2] and r[1] <= p[1] <= r[3]


def bfs_connected(cfg: EnvConfig, sc: Scenario) -> bool:
    """Reference: 4-neighbour BFS over cells whose centre is not within d_min of a BZ/NFZ."""
    X, Y, c, d = cfg.area.x_size, cfg.area.y_size, cfg.sampling.grid_cell, cfg.safety.d_min
    nx, ny = max(1, math.ceil(X / c - 1e-9)), max(1, math.ceil(Y / c - 1e-9))
    cw, ch = X / nx, Y / ny
    obst = list(sc.bz) + list(sc.nfz)

    def blocked(i: int, j: int) -> bool:
        x, y = (i + 0.5) * cw, (j + 0.5) * ch
        for r in obst:
            dx = max(r[0] - x, x - r[2], 0.0)
            dy = max(r[1] - y, y - r[3], 0.0)
            if dx * dx + dy * dy < d * d or (dx == 0 and dy == 0):
                return True
        return False

    def cell(p) -> tuple[int, int]:
        return min(max(int(math.floor(p[0] / cw)), 0), nx - 1), min(max(int(math.floor(p[1] / ch)), 0), ny - 1)

    la = cfg.area.landing
    targets = [cell(((la[0] + la[2]) / 2, (la[1] + la[3]) / 2))] + [cell(p) for p in sc.ge_pos]
    forced = set(targets) | {cell(sc.start)}
    free = [[(i, j) in forced or not blocked(i, j) for j in range(ny)] for i in range(nx)]
    seen = {cell(sc.start)}
    todo = deque(seen)
    while todo:
        i, j = todo.popleft()
        for a, b in ((i + 1, j), (i - 1, j), (i, j + 1), (i, j - 1)):
            if 0 <= a < nx and 0 <= b < ny and free[a][b] and (a, b) not in seen:
                seen.add((a, b))
                todo.append((a, b))
    return all(t in seen for t in targets)


def independent_violations(cfg: EnvConfig, sc: Scenario) -> list[str]:
    X, Y = cfg.area.x_size, cfg.area.y_size
    ta, la = cfg.area.takeoff, cfg.area.landing
    d_min, d_safe = cfg.safety.d_min, cfg.safety.d_safe
    bad = []
    obst = list(sc.bz) + list(sc.nfz)
    for r in obst + list(sc.rz):
        if not (0 <= r[0] < r[2] <= X and 0 <= r[1] < r[3] <= Y):
            bad.append(f"rect {r} outside area")
        sides = (r[2] - r[0], r[3] - r[1])
        if not all(cfg.zones.side_min - TOL <= s <= cfg.zones.side_max + TOL for s in sides):
            bad.append(f"rect {r} side out of range")
    for i, a in enumerate(obst):
        for b in obst[i + 1 :]:
            if overlap(a, b):
                bad.append(f"BZ/NFZ overlap {a} {b}")
        for t in (ta, la):
            if rect_gap(a, t) < d_safe - TOL:
                bad.append(f"BZ/NFZ {a} within d_safe of {t}")
    for r in sc.rz:
        if overlap(r, ta) or overlap(r, la):
            bad.append(f"RZ {r} overlaps TA/LA")
    for p, dv in zip(sc.ge_pos, sc.ge_data):
        if not inside(p, (0, 0, X, Y)):
            bad.append(f"GE {p} outside area")
        if inside(p, ta) or inside(p, la):
            bad.append(f"GE {p} in TA/LA")
        for r in obst + list(sc.rz):
            if inside(p, r) or point_dist(p, r) < d_min - TOL:
                bad.append(f"GE {p} too close to zone {r}")
        if not cfg.ge.data_min <= dv <= cfg.ge.data_max:
            bad.append(f"GE data {dv}")
    for p, v in zip(sc.ou_pos, sc.ou_vel):
        if not inside(p, (0, 0, X, Y)):
            bad.append(f"OU {p} outside area")
        for r in obst:
            if inside(p, r) or point_dist(p, r) < d_min - TOL:
                bad.append(f"OU {p} too close to BZ/NFZ {r}")
        if math.dist(p, sc.start) < d_safe - TOL:
            bad.append(f"OU {p} too close to start")
        if math.hypot(*v) > cfg.motion.v_max * (1 + 1e-5):
            bad.append(f"OU speed {v}")
    if tuple(sc.start) != tuple(cfg.area.start_xy):
        bad.append("start is not SL")
    if not bfs_connected(cfg, sc):
        bad.append("not connected")
    return bad


def check_counts_and_masks(cfg: EnvConfig, td) -> None:
    ranges = {
        "nfz": cfg.zones.n_nfz, "rz": cfg.zones.n_rz, "bz": cfg.zones.n_bz,
        "ge": cfg.ge.count, "ou": cfg.ou.count,
    }  # fmt: skip
    for k, cr in ranges.items():
        m = td[f"{k}_mask"]
        assert m.dtype == torch.bool and m.shape[-1] == cr.padded
        n = m.sum(-1)
        assert ((n >= cr.min) & (n <= cr.max)).all(), k
        # present entries first
        assert torch.equal(m, torch.arange(cr.padded) < n.unsqueeze(-1)), k
    for k in ("nfz", "rz", "bz"):
        assert (td[k][~td[f"{k}_mask"]] == 0).all()
    assert (td["ge_pos"][~td["ge_mask"]] == 0).all() and (td["ge_data"][~td["ge_mask"]] == 0).all()
    assert (td["ou_pos"][~td["ou_mask"]] == 0).all() and (td["ou_vel"][~td["ou_mask"]] == 0).all()


# ----------------------------------------------------------------------------------- layout
def test_contract_layout():
    td = _sample(CFG, 5, 0)
    assert set(td.keys()) == set(SCENARIO_KEYS)
    assert td.batch_size == torch.Size([5])
    z = CFG.zones
    shapes = {
        "nfz": (5, z.n_nfz.padded, 4), "rz": (5, z.n_rz.padded, 4), "bz": (5, z.n_bz.padded, 4),
        "ge_pos": (5, CFG.ge.count.padded, 2), "ge_data": (5, CFG.ge.count.padded),
        "ou_pos": (5, CFG.ou.count.padded, 2), "ou_vel": (5, CFG.ou.count.padded, 2), "start": (5, 2),
    }  # fmt: skip
    for k, s in shapes.items():
        assert tuple(td[k].shape) == s and td[k].dtype == torch.float32, k
    for k in ("nfz_mask", "rz_mask", "bz_mask", "ge_mask", "ou_mask"):
        assert td[k].dtype == torch.bool
    assert torch.equal(td["start"], torch.tensor([CFG.area.start_xy] * 5, dtype=torch.float32))


@FAST
@given(seed=st.integers(0, 2**31 - 1), b=st.integers(1, 6))
def test_sampled_scenarios_are_valid(seed, b):
    td = _sample(CFG, b, seed)
    check_counts_and_masks(CFG, td)
    for sc in unstack_scenarios(td):
        assert independent_violations(CFG, sc) == []
    assert validate_scenarios(CFG, td, check_ranges=True).all()


def test_large_batch_valid_and_covers_counts():
    td = _sample(CFG, 512, 7)
    check_counts_and_masks(CFG, td)
    assert validate_scenarios(CFG, td, check_ranges=True).all()
    for k, cr in (("bz", CFG.zones.n_bz), ("nfz", CFG.zones.n_nfz), ("ge", CFG.ge.count), ("ou", CFG.ou.count)):
        assert set(td[f"{k}_mask"].sum(-1).tolist()) == set(range(cr.min, cr.max + 1)), k
    speed = torch.linalg.vector_norm(td["ou_vel"], dim=-1)[td["ou_mask"]]
    assert speed.max() <= CFG.motion.v_max * (1 + 1e-5) and speed.min() >= 0
    for sc in unstack_scenarios(td[:16]):
        assert independent_violations(CFG, sc) == []


def test_fixed_counts_and_padding():
    cfg = make_env_config(
        zones={"n_bz": {"min": 2, "max": 2}, "n_nfz": {"min": 3, "max": 3}, "n_rz": {"min": 0, "max": 0, "pad": 2}},
        ge={"count": {"min": 12, "max": 12, "pad": 15}},
        ou={"count": {"min": 4, "max": 4}},
    )
    td = _sample(cfg, 32, 3)
    assert (td["bz_mask"].sum(-1) == 2).all() and (td["nfz_mask"].sum(-1) == 3).all()
    assert td["rz"].shape == (32, 2, 4) and not td["rz_mask"].any()
    assert td["ge_pos"].shape == (32, 15, 2) and (td["ge_mask"].sum(-1) == 12).all()
    assert (td["ou_mask"].sum(-1) == 4).all()
    check_counts_and_masks(cfg, td)
    assert validate_scenarios(cfg, td, check_ranges=True).all()


@FAST
@given(seed=st.integers(0, 2**31 - 1))
def test_determinism(seed):
    a, b = _sample(CFG, 4, seed), _sample(CFG, 4, seed)
    for k in SCENARIO_KEYS:
        assert torch.equal(a[k], b[k]), k
    c = _sample(CFG, 4, seed + 1)
    assert not all(torch.equal(a[k], c[k]) for k in ("bz", "ge_pos", "ou_pos"))


def test_device_argument():
    td = sample_scenarios(CFG, 3, torch.Generator().manual_seed(0), device="cpu")
    assert td.device == torch.device("cpu")


# ----------------------------------------------------------------------------- connectivity
def _hand(bz, ge=((250.0, 450.0),), nfz=()) -> Scenario:
    return Scenario(
        nfz=list(nfz), rz=[], bz=list(bz), ge_pos=list(ge), ge_data=[1.0] * len(ge),
        ou_pos=[], ou_vel=[], start=CFG.area.start_xy,
    )  # fmt: skip


def test_wall_cuts_off_landing():
    wall = _hand([(0.0, 200.0, 500.0, 260.0)])
    td = stack_scenarios([wall], CFG)
    assert not check_connectivity(CFG, td).item()
    assert not bfs_connected(CFG, wall)
    assert any("connected" in r for r in scenario_violations(CFG, td)[0])
    assert not validate_scenarios(CFG, td).item()


def test_wall_with_gap_is_connected():
    d, c = CFG.safety.d_min, CFG.sampling.grid_cell
    gap = 2 * d + c + 1.0  # wider than 2 d_min by more than one cell: a free column of centres exists
    wall = _hand([(0.0, 200.0, 240.0, 260.0), (240.0 + gap, 200.0, 500.0, 260.0)])
    td = stack_scenarios([wall], CFG)
    assert check_connectivity(CFG, td).item()
    assert bfs_connected(CFG, wall)
    assert scenario_violations(CFG, td)[0] == []
    # closing the gap to less than 2 d_min cuts it
    shut = _hand([(0.0, 200.0, 240.0, 260.0), (240.0 + 2 * d - 1.0, 200.0, 500.0, 260.0)])
    assert not check_connectivity(CFG, stack_scenarios([shut], CFG)).item()


def test_enclosed_ge_is_disconnected():
    # a GE in a courtyard closed by two BZ and two NFZ
    ring_bz = [(200.0, 200.0, 300.0, 210.0), (200.0, 290.0, 300.0, 300.0)]
    ring_nfz = [(200.0, 210.0, 210.0, 290.0), (290.0, 210.0, 300.0, 290.0)]
    sc = _hand(ring_bz, ge=((250.0, 250.0), (100.0, 100.0)), nfz=ring_nfz)
    assert not check_connectivity(CFG, stack_scenarios([sc], CFG)).item()
    assert not bfs_connected(CFG, sc)
    sc.ge_pos, sc.ge_data = [(100.0, 100.0)], [1.0]
    assert check_connectivity(CFG, stack_scenarios([sc], CFG)).item()


quarter = st.integers(0, 2000).map(lambda v: v / 4)  # exact in float32: no rounding ties


@st.composite
def random_layout(draw):
    rects = []
    for _ in range(draw(st.integers(0, 6))):
        x0, y0 = draw(quarter), draw(quarter)
        w, h = draw(st.integers(4, 1600).map(lambda v: v / 4)), draw(st.integers(4, 1600).map(lambda v: v / 4))
        rects.append((x0, y0, min(x0 + w, 500.0), min(y0 + h, 500.0)))
    rects = [r for r in rects if r[2] > r[0] and r[3] > r[1]]
    ge = [(draw(quarter), draw(quarter)) for _ in range(draw(st.integers(0, 4)))]
    return _hand(rects[:3], ge=ge, nfz=rects[3:])


@pytest.mark.parametrize("d_min, cell", [(5.0, 5.0), (7.5, 3.25), (0.0, 5.0)])
@settings(max_examples=12, deadline=None)
@given(layouts=st.lists(random_layout(), min_size=1, max_size=3))
def test_flood_fill_matches_bfs(d_min, cell, layouts):
    # cell 3.25 and d_min 7.5: several corner rows per rectangle side; d_min 0: no inflation
    cfg = make_env_config(
        zones={"n_bz": {"min": 0, "max": 3}, "n_nfz": {"min": 0, "max": 3}},
        ge={"count": {"min": 0, "max": 4}},
        safety={"d_min": d_min, "d_safe": 15.0},
        sampling={"grid_cell": cell},
    )  # fmt: skip
    got = check_connectivity(cfg, stack_scenarios(layouts, cfg)).tolist()
    assert got == [bfs_connected(cfg, sc) for sc in layouts]


def test_flood_fill_many_rows_and_word_boundaries():
    # 130 rows span three packed words; alternate connected / walled-off rows
    open_, wall = _hand([]), _hand([(0.0, 200.0, 500.0, 260.0)])
    rows = [open_ if i % 3 else wall for i in range(130)]
    got = check_connectivity(CFG, stack_scenarios(rows, CFG))
    assert got.tolist() == [bool(i % 3) for i in range(130)]


def test_pack_bits():
    x = torch.rand(130, 3, 5, generator=torch.Generator().manual_seed(0)) > 0.5
    p = _pack(x)
    assert p.shape == (3, 3, 5)
    b = torch.arange(130).view(-1, 1, 1)
    bits = ((p[b // 64, torch.arange(3).view(1, -1, 1), torch.arange(5).view(1, 1, -1)] >> (b % 64)) & 1).bool()
    assert torch.equal(bits, x)


# ------------------------------------------------------------------------------- validation
def _valid_hand() -> Scenario:
    return Scenario(
        nfz=[(300.0, 300.0, 400.0, 380.0)], rz=[(100.0, 100.0, 200.0, 180.0)], bz=[(100.0, 300.0, 180.0, 400.0)],
        ge_pos=[(250.0, 250.0), (50.0, 50.0)], ge_data=[1.5, 2.0],
        ou_pos=[(450.0, 450.0)], ou_vel=[(3.0, -4.0)], start=CFG.area.start_xy,
    )  # fmt: skip


@pytest.mark.parametrize(
    "edit, reason",
    [
        (lambda s: setattr(s, "ge_pos", [(150.0, 140.0), (50.0, 50.0)]), "GE inside a zone"),
        (lambda s: setattr(s, "ge_pos", [(350.0, 296.0), (50.0, 50.0)]), "GE inside a zone"),
        (lambda s: setattr(s, "ge_pos", [(490.0, 10.0), (50.0, 50.0)]), "GE inside TA/LA"),
        (lambda s: setattr(s, "nfz", [(150.0, 350.0, 250.0, 450.0)]), "overlap"),
        (lambda s: setattr(s, "bz", [(30.0, 400.0, 100.0, 470.0)]), "d_safe to TA/LA"),
        (lambda s: setattr(s, "rz", [(400.0, 0.0, 480.0, 100.0)]), "RZ overlaps TA/LA"),
        (lambda s: setattr(s, "ou_pos", [(20.0, 480.0)]), "d_safe to the start"),
        (lambda s: setattr(s, "ou_pos", [(140.0, 350.0)]), "OU inside a BZ/NFZ"),
        (lambda s: setattr(s, "ou_vel", [(30.0, 0.0)]), "faster than motion.v_max"),
        (lambda s: setattr(s, "bz", [(100.0, 300.0, 180.0, 520.0)]), "outside the area"),
    ],
)
def test_validate_names_the_broken_rule(edit, reason):
    sc = _valid_hand()
    assert scenario_violations(CFG, stack_scenarios([sc], CFG))[0] == []
    edit(sc)
    td = stack_scenarios([sc, _valid_hand()], CFG)
    viol = scenario_violations(CFG, td)
    assert any(reason in r for r in viol[0]), viol[0]
    assert viol[1] == []
    assert validate_scenarios(CFG, td).tolist() == [False, True]


def test_validate_masks_and_ranges():
    td = stack_scenarios([_valid_hand()], CFG)
    td["ge_mask"][0, 0] = False  # a hole before a present entry
    assert any("present-entries-first" in r for r in scenario_violations(CFG, td)[0])
    td = stack_scenarios([_valid_hand()], CFG)
    td["ge_data"][0, 0] = float("nan")
    assert any("non-finite" in r for r in scenario_violations(CFG, td)[0])
    # hand-made layouts need not respect the sampling ranges unless asked
    td = stack_scenarios([_valid_hand()], CFG)
    assert validate_scenarios(CFG, td).item()
    assert any("count outside" in r for r in scenario_violations(CFG, td, check_ranges=True)[0])


# ---------------------------------------------------------------------------------- files
@FAST
@given(seed=st.integers(0, 2**31 - 1), b=st.integers(1, 4))
def test_round_trip_exact(seed, b, tmp_path_factory):
    tmp = tmp_path_factory.mktemp("scen")
    td = _sample(CFG, b, seed)
    scs = unstack_scenarios(td)
    save_scenarios(tmp / "set.json", scs)
    back = stack_scenarios(load_scenarios(tmp / "set.json"), CFG)
    for k in SCENARIO_KEYS:
        assert torch.equal(td[k], back[k]), k
    scs[0].to_json(tmp / "one.json")
    assert Scenario.from_json(tmp / "one.json") == scs[0]
    assert Scenario.from_dict(scs[0].to_dict()) == scs[0]
    assert sorted(os.listdir(tmp)) == ["one.json", "set.json"]  # no temp files left


def test_to_json_replaces_atomically(tmp_path):
    p = tmp_path / "s.json"
    _valid_hand().to_json(p)
    sc = _valid_hand()
    sc.ge_data = [3.0, 3.0]
    sc.to_json(p)
    assert Scenario.from_json(p).ge_data == [3.0, 3.0]
    assert os.listdir(tmp_path) == ["s.json"]


def _bad(**changes):
    d = _valid_hand().to_dict()
    d.update(changes)
    return d


@pytest.mark.parametrize(
    "data, match",
    [
        ({k: v for k, v in _valid_hand().to_dict().items() if k != "bz"}, r"missing \['bz'\]"),
        (_bad(colour="red"), r"unexpected \['colour'\]"),
        (_bad(bz=[[1.0, 2.0, 3.0]]), r"bz\[0\]: expected a list of 4"),
        (_bad(start=[1.0]), r"start: expected a list of 2"),
        (_bad(ge_data=[1.0]), "ge_data has 1 entries but ge_pos has 2"),
        (_bad(ou_vel=[]), "ou_vel has 0 entries"),
        (_bad(nfz=[[10.0, 10.0, 5.0, 20.0]]), r"nfz\[0\].*x1 > x0"),
        (_bad(ge_pos=[[1.0, "a"], [2.0, 3.0]]), r"ge_pos\[0\]\[1\]: expected a number"),
        (_bad(ge_data=[1.0, True]), r"ge_data\[1\]: expected a number"),
        (_bad(rz={"a": 1}), "rz: expected a list"),
        ([1, 2], "JSON object"),
    ],
)
def test_bad_dict_raises_value_error(data, match):
    with pytest.raises(ValueError, match=match):
        Scenario.from_dict(data)


def test_bad_json_files(tmp_path):
    p = tmp_path / "s.json"
    p.write_text(json.dumps(_valid_hand().to_dict()).replace("1.5", "NaN"))
    with pytest.raises(ValueError, match="non-finite"):
        Scenario.from_json(p)
    p.write_text(json.dumps(_valid_hand().to_dict()).replace("1.5", "1e999"))
    with pytest.raises(ValueError, match="finite"):
        Scenario.from_json(p)
    p.write_text("{not json")
    with pytest.raises(ValueError, match="not valid JSON"):
        Scenario.from_json(p)
    p.write_text(json.dumps(_valid_hand().to_dict()))
    with pytest.raises(ValueError, match="expected a JSON list"):
        load_scenarios(p)
    p.write_text(json.dumps([_valid_hand().to_dict(), _bad(extra=1)]))
    with pytest.raises(ValueError, match="scenario 1: .*unexpected"):
        load_scenarios(p)


def test_stack_rejects_too_many_entities():
    sc = _valid_hand()
    sc.bz = [(0.0, 0.0, 1.0, 1.0)] * (CFG.zones.n_bz.padded + 1)
    with pytest.raises(ValueError, match=r"scenario 1 has 4 bz .*zones.n_bz pads to 3"):
        stack_scenarios([_valid_hand(), sc], CFG)
    sc = _valid_hand()
    sc.ou_pos, sc.ou_vel = [(1.0, 1.0)] * 8, [(0.0, 0.0)] * 8
    with pytest.raises(ValueError, match="ou.count pads to 7"):
        stack_scenarios([sc], CFG)
    with pytest.raises(ValueError, match="at least one"):
        stack_scenarios([], CFG)


# ------------------------------------------------------------------------ impossible configs
def test_impossible_config_raises_clear_error():
    cfg = make_env_config(
        area={"x_size": 300.0, "y_size": 300.0, "takeoff": (0.0, 275.0, 25.0, 300.0), "landing": (275.0, 0.0, 300.0, 25.0)},
        zones={"side_min": 200.0, "side_max": 200.0, "n_bz": {"min": 3, "max": 3}, "n_nfz": {"min": 3, "max": 3}},
    )
    t = time.perf_counter()
    with pytest.raises(RuntimeError, match=r"(?s)could not sample 8 of 8.*BZ #2.*building zone \(BZ\).*zones.n_bz"):
        sample_scenarios(cfg, 8, torch.Generator().manual_seed(0))
    assert time.perf_counter() - t < 30


def test_unconnectable_config_names_connectivity():
    # a 500 x 100 strip: every BZ of side 100 spans its full height between TA and LA
    cfg = make_env_config(
        area={"x_size": 500.0, "y_size": 100.0, "takeoff": (0.0, 75.0, 25.0, 100.0), "landing": (475.0, 0.0, 500.0, 25.0)},
        zones={"side_min": 100.0, "side_max": 100.0, "n_bz": {"min": 1, "max": 1}, "n_nfz": {"min": 0, "max": 0},
               "n_rz": {"min": 0, "max": 0}},
        ge={"count": {"min": 0, "max": 0}},
        ou={"count": {"min": 0, "max": 0}},
        sampling={"layout_tries": 3},
    )  # fmt: skip
    with pytest.raises(RuntimeError, match=r"(?s)could not sample 4 of 4.*4 row\(s\): the start, LA and all GEs"):
        sample_scenarios(cfg, 4, torch.Generator().manual_seed(0))
