"""The C kernels of the compiled CPU step (uavlae/envs/ckernels.py) against hand-computed values
and against the torch physics they replace."""

import ctypes
import math
import os
import subprocess
import sys

import pytest
import torch

from uavlae.envs import ckernels
from uavlae.envs import physics as ph
from uavlae.envs.config import EnvConfig

pytestmark = pytest.mark.skipif(not ckernels.load(), reason="no C compiler: the compiled step keeps its torch code")

CFG = EnvConfig()
M, OU = CFG.motion, CFG.ou


def _ou_c(pos, vel, mask, blocked, bmask, noise):
    cos, sin = torch.cos(noise["heading"]), torch.sin(noise["heading"])
    return ckernels.ou_step_cpu(pos, vel, mask, blocked, bmask, noise["turn"], noise["speed"], cos, sin,
                                        noise["retry_heading"], 500.0, 500.0, M.t_fly)


def _noise(b, k, turn=False, retry=(0.0, math.pi / 2, math.pi, 1.5 * math.pi)):
    return {
        "turn": torch.full((b, k), turn), "speed": torch.zeros(b, k), "heading": torch.zeros(b, k),
        "retry_heading": torch.tensor(retry).reshape(-1, 1, 1).expand(-1, b, k).contiguous(),
    }


def test_ou_retry_hover_and_absent_by_hand():
    # OU 0 flies east into a building 5 m ahead: heading 0 is blocked, pi/2 (north) is free.
    # OU 1 sits in a 1 m gap between two buildings and the area's corner: every retry is blocked.
    # OU 2 is absent: it keeps its position and velocity.
    pos = torch.tensor([[[100.0, 100.0], [495.0, 495.0], [10.0, 10.0]]])
    vel = torch.tensor([[[10.0, 0.0], [10.0, 0.0], [3.0, 4.0]]])
    mask = torch.tensor([[True, True, False]])
    blocked = torch.tensor([[[105.0, 90.0, 120.0, 110.0], [480.0, 480.0, 490.0, 500.0], [480.0, 480.0, 500.0, 490.0]]])
    bmask = torch.ones(1, 3, dtype=torch.bool)
    new_pos, new_vel = _ou_c(pos, vel, mask, blocked, bmask, _noise(1, 3))
    # OU 0: same speed 10 at heading pi/2 -> (10 cos(pi/2), 10 sin(pi/2)) = (-4.4e-7, 10)
    torch.testing.assert_close(new_vel[0, 0], torch.tensor([10.0 * math.cos(math.pi / 2), 10.0]))
    torch.testing.assert_close(new_pos[0, 0], torch.tensor([100.0, 110.0]))
    # OU 1: east leaves the area, north too, west and south meet the buildings: it hovers
    assert new_vel[0, 1].tolist() == [0.0, 0.0] and new_pos[0, 1].tolist() == [495.0, 495.0]
    assert new_pos[0, 2].tolist() == [10.0, 10.0] and new_vel[0, 2].tolist() == [3.0, 4.0]
    # the torch reference gives the same
    ref_pos, ref_vel = ph.ou_step(pos, vel, mask, blocked, bmask, 500.0, 500.0, OU, M, noise=_noise(1, 3))
    torch.testing.assert_close(new_pos, ref_pos)
    torch.testing.assert_close(new_vel, ref_vel)


@pytest.mark.parametrize("seed", [0, 1])
def test_ou_step_matches_the_torch_reference(seed):
    g = torch.Generator().manual_seed(seed)
    b, k, z = 512, 7, 6
    pos = torch.rand(b, k, 2, generator=g) * 500
    vel = (torch.rand(b, k, 2, generator=g) * 2 - 1) * 10
    mask = torch.rand(b, k, generator=g) < 0.8
    lo = torch.rand(b, z, 2, generator=g) * 450
    blocked = torch.cat([lo, lo + 20 + torch.rand(b, z, 2, generator=g) * 150], -1)
    bmask = torch.rand(b, z, generator=g) < 0.7
    noise = ph.ou_noise((b, k), OU, M, g)
    ref_pos, ref_vel = ph.ou_step(pos, vel, mask, blocked, bmask, 500.0, 500.0, OU, M, noise=noise)
    new_pos, new_vel = _ou_c(pos, vel, mask, blocked, bmask, noise)
    hover_ref, hover_new = (ref_vel == 0).all(-1) & mask, (new_vel == 0).all(-1) & mask
    assert hover_ref.sum() > 0 and torch.equal(hover_ref, hover_new)  # the same OUs found no heading
    moved = ~torch.isclose(ref_vel, vel).all(-1) & mask
    assert moved.sum() > 0.05 * mask.sum()  # turns and retries happened
    torch.testing.assert_close(new_pos, ref_pos, rtol=1e-6, atol=1e-4)
    torch.testing.assert_close(new_vel, ref_vel, rtol=1e-6, atol=1e-5)


def _serve_c(p, ge, rem, mask, tie):
    ch = CFG.channel
    return ckernels.serve_cpu(p, ge, rem, mask, tie, CFG.area.altitude, CFG.ge.tx_power, ch.alpha,
                                      ch.noise, ch.snr_threshold, M.t_hover)


def test_serve_by_hand():
    # SNR at ground distance r: TP·α/(r² + H²)/N = 0.01·0.36/(r² + 100)/1e-6; rate = log2(1 + SNR)
    # TD = min(DV, B·t_hover), t_hover = 1: the data left (3.0), else the rate
    # r = 0: SNR 36, rate log2(37) = 5.2095; r = 10: SNR 18, rate log2(19) = 4.2479; r = 31: SNR 3.42 < 3.6
    p = torch.zeros(4, 2)
    ge = torch.tensor([[0.0, 0.0], [10.0, 0.0], [31.0, 0.0]]).expand(4, 3, 2).contiguous()
    rem = torch.tensor([[3.0, 2.0, 1.0], [6.0, 2.0, 1.0], [0.0, 5.0, 1.0], [0.0, 0.0, 1.0]])
    mask = torch.ones(4, 3, dtype=torch.bool)
    td, served, left = _serve_c(p, ge, rem, mask, torch.rand(4, 3))
    assert served.tolist() == [0, 0, 1, -1]
    torch.testing.assert_close(td, torch.tensor([3.0, math.log2(37.0), math.log2(19.0), 0.0]))
    torch.testing.assert_close(left, torch.tensor([[0.0, 2.0, 1.0], [6.0 - math.log2(37.0), 2.0, 1.0],
                                                   [0.0, 5.0 - math.log2(19.0), 1.0], [0.0, 0.0, 1.0]]))


def test_serve_breaks_exact_ties_by_the_noise_and_matches_the_torch_reference():
    p = torch.zeros(2, 2)
    ge = torch.tensor([[5.0, 0.0], [0.0, 5.0], [-5.0, 0.0]]).expand(2, 3, 2).contiguous()  # three at 5 m
    rem, mask = torch.ones(2, 3), torch.ones(2, 3, dtype=torch.bool)
    tie = torch.tensor([[0.2, 0.9, 0.5], [0.7, 0.1, 0.7]])
    _, served, _ = _serve_c(p, ge, rem, mask, tie)
    assert served.tolist() == [1, 0]  # the largest noise; on equal noise the first
    g = torch.Generator().manual_seed(0)
    b, n = 2048, 15
    p = torch.rand(b, 2, generator=g) * 500
    ge = (p.unsqueeze(1) + (torch.rand(b, n, 2, generator=g) * 2 - 1) * 40).contiguous()
    rem = torch.rand(b, n, generator=g) * 3 * (torch.rand(b, n, generator=g) < 0.7)
    mask = torch.rand(b, n, generator=g) < 0.9
    tie = torch.rand(b, n, generator=g)
    snr, rate = ph.channel(p, ge, CFG.area.altitude, CFG.ge.tx_power, CFG.channel)
    td_ref, served_ref, left_ref = ph.serve_ge(snr, rate, rem, mask, CFG.channel.snr_threshold, M.t_hover, tie)
    td, served, left = _serve_c(p, ge, rem, mask, tie)
    assert (served_ref >= 0).sum() > b // 4 and torch.equal(served, served_ref)
    torch.testing.assert_close(td, td_ref)
    torch.testing.assert_close(left, left_ref)


def test_bad_input_names_the_tensor():
    pos = torch.zeros(2, 3, 2)
    with pytest.raises(ValueError, match="blocked_mask must be a 2-d CPU torch.bool"):
        ckernels.ou_step_cpu(pos, pos, torch.ones(2, 3, dtype=torch.bool), torch.zeros(2, 1, 4),
                                     torch.ones(2, 1), torch.zeros(2, 3, dtype=torch.bool), torch.zeros(2, 3),
                                     torch.zeros(2, 3), torch.zeros(2, 3), torch.zeros(4, 2, 3), 500.0, 500.0, 1.0)
    with pytest.raises(ValueError, match="ge_pos must be a CPU torch.float32 tensor of shape \\[2, 3, 2\\]"):
        _serve_c(torch.zeros(2, 2), torch.zeros(2, 4, 2), torch.zeros(2, 3), torch.ones(2, 3, dtype=torch.bool), torch.zeros(2, 3))


def _load_in_subprocess(env_update: dict, cache) -> subprocess.CompletedProcess:
    env = {**os.environ, "UAVLAE_CACHE_DIR": str(cache), **env_update}
    code = "import warnings; warnings.simplefilter('always'); from uavlae.envs import ckernels; print(ckernels.load())"
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=120)


def test_a_failed_build_warns_falls_back_and_leaves_nothing_behind(tmp_path):
    out = _load_in_subprocess({"CC": "/bin/false"}, tmp_path)
    assert out.stdout.strip() == "False"
    assert "could not be built" in out.stderr and "/bin/false exited with 1" in out.stderr
    assert list((tmp_path / "ckernels").iterdir()) == []  # no library, no half-built temporary
    out = _load_in_subprocess({"UAVLAE_C_KERNELS": "0"}, tmp_path)
    assert out.stdout.strip() == "False" and out.stderr == ""
    out = _load_in_subprocess({}, tmp_path)  # a real build into the fresh cache
    assert out.stdout.strip() == "True"
    assert [p.suffix for p in (tmp_path / "ckernels").iterdir()] == [".so"]


def test_a_compiler_without_openmp_gets_the_one_thread_build(tmp_path):
    cc = tmp_path / "cc-no-openmp"
    cc.write_text('#!/bin/sh\ncase " $* " in *" -fopenmp "*) echo "no OpenMP here" >&2; exit 1;; esac\nexec cc "$@"\n')
    cc.chmod(0o755)
    cache = tmp_path / "cache"
    out = _load_in_subprocess({"CC": str(cc)}, cache)
    assert out.stdout.strip() == "True" and out.stderr == ""
    built = list((cache / "ckernels").iterdir())
    assert [p.name.endswith("_serial.so") for p in built] == [True]


def _obs_c(p, ge, rem, gm, zones, zmask, ou_pos, ou_vel, ou_mask):
    """obs_cpu with the zones split into NFZs, RZs and BZs and every divisor 1."""
    b, n = zones.shape[:2]
    z, zm = [zones[:, i::3].contiguous() for i in range(3)], [zmask[:, i::3].contiguous() for i in range(3)]
    d = torch.rand(b, generator=torch.Generator().manual_seed(0)) * 80
    rects = zones[:, 0].contiguous()  # a TA and an LA
    width = ckernels.obs_width(ge.shape[1], *(m.shape[1] for m in zm), ou_mask.shape[1], extra=True)
    return ckernels.obs_cpu(ge, rem, gm, z[0], zm[0], z[1], zm[1], z[2], zm[2], ou_pos, ou_vel, ou_mask, p, p * 0.1,
                            d, d, rects, rects, d, d - 10, d, d, d, torch.ones(width), 30.0, True, 50.0)


def test_row_ranges_on_two_threads_give_the_one_thread_result():
    g = torch.Generator().manual_seed(3)
    b, k, z = 2048, 7, 6
    pos, vel = torch.rand(b, k, 2, generator=g) * 500, (torch.rand(b, k, 2, generator=g) * 2 - 1) * 10
    mask = torch.rand(b, k, generator=g) < 0.8
    lo = torch.rand(b, z, 2, generator=g) * 450
    blocked = torch.cat([lo, lo + 20 + torch.rand(b, z, 2, generator=g) * 150], -1)
    bmask = torch.rand(b, z, generator=g) < 0.7
    noise = ph.ou_noise((b, k), OU, M, g)
    ge = (pos[:, :1] + torch.rand(b, 15, 2, generator=g) * 40 - 20).contiguous()
    rem, gm, tie = torch.rand(b, 15, generator=g) * 3, torch.ones(b, 15, dtype=torch.bool), torch.rand(b, 15, generator=g)
    threads = torch.get_num_threads()
    try:
        results = []
        for n in (1, 2):
            torch.set_num_threads(n)
            results.append((*_ou_c(pos, vel, mask, blocked, bmask, noise), *_serve_c(pos[:, 0], ge, rem, gm, tie),
                            _obs_c(pos[:, 0], ge, rem, gm, blocked, bmask, pos, vel, mask)))
    finally:
        torch.set_num_threads(threads)
    assert all(torch.equal(x, y) for x, y in zip(*results))
    assert (results[0][0] != pos).any()  # the OUs moved


def test_the_mt19937_replay_gives_the_standard_10000th_number():
    # The C++ standard ([rand.predef]) fixes the 10000th output of mt19937 seeded with 5489 at
    # 4123659995; torch.rand keeps its low 24 bits: 4123659995 = 0xF5CA_0EDB -> 0xCA0EDB = 13242075.
    g = torch.Generator().manual_seed(5489)
    u = ckernels.uniform(g, 10000)
    assert u[-1].item() == 13242075 / 2**24
    # and the first: 3499211612 = 0xD091_BB5C -> 0x91BB5C = 9550684
    assert u[0].item() == 9550684 / 2**24


@pytest.mark.parametrize("n", [ckernels.MT_MIN_DRAWS, 624 * 7 + 5, 100_003])
def test_the_mt19937_replay_is_torch_rand_bit_for_bit(n):
    assert ckernels._STATE["mt"]  # load() checked the replay against torch and turned it on
    g, h = torch.Generator().manual_seed(11), torch.Generator().manual_seed(11)
    torch.rand(333, generator=g), torch.rand(333, generator=h)  # a used generator: mid-block
    want, got = torch.rand(n, generator=g), ckernels.uniform(h, n)
    assert torch.equal(want, got)
    assert torch.equal(g.get_state(), h.get_state())  # left as torch leaves it
    assert torch.equal(torch.rand(1000, generator=g), torch.rand(1000, generator=h))


def test_the_mt19937_replay_refuses_a_state_it_does_not_know_and_falls_back(monkeypatch):
    st = torch.Generator().manual_seed(1).get_state()
    bad = st.clone()
    bad[8:12] = 0  # left = 0: no torch generator is ever in that state
    out = torch.full((4,), -1.0)
    one_run = ((ctypes.c_int64 * 1)(4), (ctypes.c_int * 1)(0), (ctypes.c_float * 1)(1.0), (ctypes.c_void_p * 1)(out.data_ptr()))
    assert ckernels._STATE["lib"].uavlae_mt_runs(bad.data_ptr(), 1, *one_run) == 1
    assert out.tolist() == [-1.0] * 4 and torch.equal(bad[12:], st[12:])  # nothing written
    monkeypatch.setattr(ckernels, "_MT_STATE_BYTES", 1)  # as if torch's state layout changed
    assert not ckernels._mt_self_check()
    g, h = torch.Generator().manual_seed(2), torch.Generator().manual_seed(2)
    assert torch.equal(ckernels.uniform(g, 5000), torch.rand(5000, generator=h))  # torch.rand itself


def test_uniform_runs_transform_the_stream_by_hand_and_as_torch_does():
    # seed 5489: the first output gives u0 = 9550684 / 2^24 = 0.56926..., the 10000th
    # 13242075 / 2^24 (the C++ standard's value, see above)
    runs = [(torch.Size([1]), "<", 0.57), (torch.Size([9998]), "*", 1.0), (torch.Size([1]), "*", 2.0)]
    g = torch.Generator().manual_seed(5489)
    first, middle, last = ckernels.uniform_runs(g, runs)
    assert first.dtype == torch.bool and first.tolist() == [True]  # 0.56926 < 0.57
    assert last.item() == 2 * 13242075 / 2**24  # a power-of-two scale: exact
    h = torch.Generator().manual_seed(5489)
    assert not ckernels.uniform_runs(h, [(torch.Size([1]), "<", 0.569), *runs[1:]])[0].item()  # 0.56926 >= 0.569
    # against torch.rand and torch's ops, from a used generator, with the generator left as torch leaves it
    g, h = torch.Generator().manual_seed(8), torch.Generator().manual_seed(8)
    torch.rand(100, generator=g), torch.rand(100, generator=h)
    runs = [(torch.Size([300, 7]), "<", 0.05), (torch.Size([300, 7]), "*", 10.0), (torch.Size([4, 300, 7]), "*", 6.283185307179586)]
    got = ckernels.uniform_runs(g, runs)
    want = [torch.rand(s, generator=h) < p if op == "<" else torch.rand(s, generator=h) * p for s, op, p in runs]
    assert all(torch.equal(a, b) for a, b in zip(got, want))
    assert torch.equal(g.get_state(), h.get_state())
    assert ckernels.uniform_runs(g, [(torch.Size([100]), "*", 1.0)]) is None  # too few numbers: torch.rand
    with pytest.raises(ValueError, match="op must be"):
        ckernels.uniform_runs(g, [(torch.Size([4096]), "+", 1.0)])


def test_draw_noise_draws_the_same_numbers_through_the_replay(monkeypatch):
    from uavlae.envs import UAVEnv
    from uavlae.envs.world import draw_noise

    env = UAVEnv(batch_size=[512], seed=0)
    td = env.reset()
    state = {k: td["state", k] for k in env.raw_state_keys}
    fast = draw_noise(state, env.cfg, torch.Generator().manual_seed(4))
    monkeypatch.setitem(ckernels._STATE, "mt", False)
    slow = draw_noise(state, env.cfg, torch.Generator().manual_seed(4))
    assert sorted(fast) == sorted(slow) == ["ge_tie", "heading", "retry_heading", "speed", "turn"]
    assert all(torch.equal(fast[k], slow[k]) for k in fast)
    assert fast["retry_heading"].shape == (CFG.ou.heading_tries, 512, env.layout.n_ou)


def _grid_bits(*patterns):
    """int64 [1, ny, nx]: bit s of each cell from patterns[s] (rows of '1' free / '0' blocked)."""
    rows = [[sum(1 << s for s, p in enumerate(patterns) if p[y][x] == "1") for x in range(len(patterns[0][0]))]
            for y in range(len(patterns[0]))]
    return torch.tensor([rows], dtype=torch.int64)


def test_flood_follows_a_spiral_and_stops_at_a_wall():
    spiral = ["11111", "00001", "11101", "10001", "11111"]  # one corridor, four turns against the raster
    wall = ["11011", "11011", "11011", "11011", "11011"]  # column x = 2 blocked
    free = _grid_bits(spiral, wall)
    seed = _grid_bits(["10000"] + ["00000"] * 4, ["10000"] + ["00000"] * 4)
    reached = ckernels.flood(free, seed)
    left_of_wall = ["11000"] * 5
    assert torch.equal(reached, _grid_bits(spiral, left_of_wall))  # every spiral cell; only x < 2
    assert torch.equal(seed, _grid_bits(["10000"] + ["00000"] * 4, ["10000"] + ["00000"] * 4))  # not written
    assert ckernels.flood(free.int(), seed.int()) is None  # not int64: the torch flood


def test_connectivity_check_gives_the_torch_flood_s_answer(monkeypatch):
    from uavlae.envs import scenario as sc

    g = torch.Generator().manual_seed(0)
    td = sc.sample_scenarios(CFG, 256, g)
    lo = torch.rand(256, td["bz"].shape[1], 2, generator=g) * 400  # big random buildings: many cut off
    td["bz"] = torch.cat([lo, lo + torch.rand(256, td["bz"].shape[1], 2, generator=g) * 200], -1).clamp(max=500)
    td["bz_mask"] = torch.ones_like(td["bz_mask"])
    fast = sc.check_connectivity(CFG, td)
    monkeypatch.setitem(ckernels._STATE, "lib", None)
    slow = sc.check_connectivity(CFG, td)
    assert 0.1 < fast.float().mean() < 0.9 and torch.equal(fast, slow)


def _blocked_cells(free):
    """(row, column) of the cells blocked for scenario 0 of a packed free grid."""
    return {(int(j), int(i)) for j, i in ((free[0] & 1) == 0).nonzero().tolist()}


def test_free_grid_inflates_a_building_by_hand():
    # 5 m cells (centres 2.5, 7.5, ...), building [10, 20] x [10, 20], d_min = 9 m, so 2 rows above
    # and below. Level rows 1..4 (centres 7.5..22.5): columns with dx < 9, centres 2.5..27.5 (dx 7.5),
    # i = 0..5. Rows 0 and 5 (dy = 7.5): dx^2 < 81 - 56.25 = 24.75, so dx = 2.5 only, i = 1..4.
    from uavlae.envs import scenario as sc

    cfg = EnvConfig.model_validate({"safety": {"d_min": 9.0}})
    grid = sc._Grid.of(cfg)
    cx, cy = grid.centres(torch.device("cpu"))
    rects = torch.tensor([[[10.0, 10.0, 20.0, 20.0], [300.0, 300.0, 400.0, 400.0]]])
    rmask = torch.tensor([[True, False]])  # the second building is absent
    cells = torch.tensor([[0, 3 * grid.nx + 3]])  # the seed (cell 0) and a target inside the building
    free, seed = ckernels.free_grid(rects, rmask, cx, cy, 9.0, 2, cells, torch.tensor([[True, True]]))
    want = {(j, i) for j in range(1, 5) for i in range(6)} | {(j, i) for j in (0, 5) for i in range(1, 5)}
    assert _blocked_cells(free) == want - {(3, 3)}  # the target's cell is set free
    assert (seed[0] & 1).nonzero().tolist() == [[0, 0]]
    target = sc._point_bits(grid, 1, torch.zeros(1, dtype=torch.long), cells[:, 1], torch.tensor([True]))
    assert torch.equal(free, ~sc._blocked(cfg, grid, rects, rmask) | target)  # the torch grid, bit for bit


@pytest.mark.parametrize("d_min,cell", [(5.0, 5.0), (7.3, 3.3), (0.1, 2.5), (12.5, 4.9)])
def test_free_grid_gives_the_torch_grids(d_min, cell):
    from uavlae.envs import scenario as sc

    cfg = EnvConfig.model_validate({"safety": {"d_min": d_min, "d_safe": max(15.0, d_min)},
                                    "sampling": {"grid_cell": cell}})
    grid = sc._Grid.of(cfg)
    cx, cy = grid.centres(torch.device("cpu"))
    g = torch.Generator().manual_seed(1)
    for n in (1, 64, 130):  # one word, a full word, a partial third word
        u = torch.rand(n, 6, 4, generator=g) * 500
        u[: n // 2] = (u[: n // 2] / 2.5).round() * 2.5  # edges on cell centres and cell borders
        lo, hi = torch.minimum(u[..., :2], u[..., 2:]), torch.maximum(u[..., :2], u[..., 2:])
        rects, rmask = torch.cat([lo, hi], -1), torch.rand(n, 6, generator=g) < 0.7
        cells = torch.randint(0, grid.nx * grid.ny, (n, 4), generator=g)
        cmask = torch.rand(n, 4, generator=g) < 0.8
        cmask[:, 0] = True
        free, seed = ckernels.free_grid(rects, rmask, cx, cy, d_min, math.ceil(d_min / grid.cell_y), cells, cmask)
        b, nb = torch.arange(n), free.shape[0]
        want_seed = sc._point_bits(grid, nb, b, cells[:, 0], cmask[:, 0])
        want = ~sc._blocked(cfg, grid, rects, rmask)
        for t in range(4):
            want |= sc._point_bits(grid, nb, b, cells[:, t], cmask[:, t])
        assert torch.equal(free, want) and torch.equal(seed, want_seed)


def test_first_clear_by_hand():
    # one building [10, 20] x [10, 20]; margin 5: (24, 15) is 4 m away, (26, 15) 6 m, (0, 0) far
    rects, rmask = torch.tensor([[[10.0, 10.0, 20.0, 20.0]]]), torch.tensor([[True]])
    pts = torch.tensor([[[24.0, 15.0], [26.0, 15.0], [0.0, 0.0]],
                        [[15.0, 15.0], [24.0, 15.0], [12.0, 19.0]],
                        [[24.0, 15.0], [26.0, 15.0], [0.0, 0.0]]])
    pre = torch.tensor([[True, True, True], [True, True, True], [True, False, True]])
    row = torch.zeros(3, dtype=torch.long)
    assert ckernels.first_clear(pts, pre, row, rects, rmask, 5.0).tolist() == [1, -1, 2]
    # margin 0: only points outside the closed rectangle; (20, 15) lies on its edge
    edge = torch.tensor([[[20.0, 15.0], [20.5, 15.0]]])
    assert ckernels.first_clear(edge, torch.ones(1, 2, dtype=torch.bool), row[:1], rects, rmask, 0.0).tolist() == [1]
    # rectangles: open interiors; touching the edge x = 20 is not an overlap
    cand = torch.tensor([[[15.0, 0.0, 25.0, 12.0], [20.0, 0.0, 30.0, 30.0], [0.0, 0.0, 5.0, 5.0]]])
    assert ckernels.first_clear(cand, torch.ones(1, 3, dtype=torch.bool), row[:1], rects, rmask).tolist() == [1]
    assert ckernels.first_clear(cand, torch.ones(1, 3, dtype=torch.bool), row[:1], rects, ~rmask).tolist() == [0]
    with pytest.raises(ValueError, match="row must index"):
        ckernels.first_clear(pts, pre, row + 1, rects, rmask, 5.0)


def test_sampler_with_the_kernels_draws_the_torch_scenarios(monkeypatch):
    # the C grid, scans and draws in the sampler: the same scenarios and the same generator state
    from uavlae.envs import scenario as sc

    cfg = EnvConfig.model_validate({"zones": {"n_bz": {"min": 2, "max": 4}}, "safety": {"d_min": 7.3}})
    g = torch.Generator().manual_seed(3)
    fast = sc.sample_scenarios(cfg, 300, g)
    fast_state = g.get_state()
    monkeypatch.setitem(ckernels._STATE, "lib", None)
    monkeypatch.setitem(ckernels._STATE, "mt", False)
    g = torch.Generator().manual_seed(3)
    slow = sc.sample_scenarios(cfg, 300, g)
    assert all(torch.equal(fast[k], slow[k]) for k in sc.SCENARIO_KEYS)
    assert torch.equal(fast_state, g.get_state())


def _obs_row_inputs():
    """Two hand-made rows for obs_cpu: 1 GE, one zone of each type, 3 OUs."""
    t = torch.tensor
    inf = math.inf
    return dict(
        ge_pos=t([[[100.0, 200.0]], [[0.0, 0.0]]]), ge_remaining=t([[5.0], [0.0]]),
        ge_mask=t([[True], [False]]),
        nfz=t([[[10.0, 20.0, 40.0, 60.0]], [[0.0, 0.0, 0.0, 0.0]]]), nfz_mask=t([[True], [False]]),
        rz=t([[[0.0, 0.0, 0.0, 0.0]], [[-5.0, -5.0, 5.0, 5.0]]]), rz_mask=t([[False], [True]]),
        bz=t([[[100.0, 100.0, 110.0, 130.0]], [[0.0, 0.0, 0.0, 0.0]]]), bz_mask=t([[True], [False]]),
        # row 0 from (50, 50): 20 m, 5 m, 40 m (beyond the 30 m radius); row 1 from (0, 0): an
        # absent OU 10 m west, then two present ones at exactly 10 m
        ou_pos=t([[[70.0, 50.0], [53.0, 54.0], [90.0, 50.0]], [[-10.0, 0.0], [0.0, 10.0], [10.0, 0.0]]]),
        ou_vel=t([[[1.0, 2.0], [3.0, 4.0], [5.0, 6.0]], [[-1.0, -1.0], [7.0, 8.0], [9.0, 10.0]]]),
        ou_mask=t([[True, True, True], [False, True, True]]),
        position=t([[50.0, 50.0], [0.0, 0.0]]), velocity=t([[2.0, -4.0], [0.0, 0.0]]),
        energy_left=t([1000.0, 8.0]), slot_data=t([3.0, 0.0]),
        takeoff=t([[0.0, 0.0, 20.0, 20.0], [0.0, 0.0, 20.0, 20.0]]),
        landing=t([[480.0, 480.0, 500.0, 500.0], [480.0, 480.0, 500.0, 500.0]]),
        d_bz=t([70.0, inf]), d_nfz=t([10.0, inf]), d_rz=t([inf, 0.0]), d_boundary=t([50.0, 0.0]),
        d_la=t([300.0, 678.0]),
    )


def test_obs_by_hand():
    x = _obs_row_inputs()
    width = ckernels.obs_width(1, 1, 1, 1, 3, extra=True)
    assert width == 5 * 7 + 14 + 6
    obs = ckernels.obs_cpu(*x.values(), torch.full((width,), 2.0), 30.0, True, 50.0)
    row0 = [
        50, 100, 2.5, 0.5, 0.5,  # GE at (100, 200) with 5 left, present: /2
        5, 10, 15, 20, 0.5,  # NFZ [10, 20, 40, 60]: corner (10, 20), 30 x 40
        0, 0, 0, 0, 0,  # no RZ
        50, 50, 5, 15, 0.5,  # BZ [100, 100, 110, 130]
        1.5, 2, 10, 0, 0, 0,  # OUs nearest first: (3, 4) at 5 m, (20, 0) at 20 m, the one at 40 m hidden
        1.5, 2, 0.5, 1, 0, 0,  # their velocities (3, 4), (1, 2), hidden: 0
        0.5, 0.5, 0,  # visibility
        25, 25, 1, -2, 500, 1.5, 0, 0, 10, 10, 240, 240, 250, 250,  # p, v, energy, slot data, TA, LA
        25, 5, 25, 25, 150, 0,  # d_bz 70 -> 50, d_nfz 10, d_rz inf -> 50, d_boundary 50, d_la 300, not in RZ
    ]
    assert obs[0].tolist() == row0
    row1 = obs[1].tolist()
    # the tie at 10 m keeps index order: (0, 10) then (10, 0); the absent OU goes last
    assert row1[20:35] == [0, 5, 5, 0, 0, 0, 3.5, 4, 4.5, 5, 0, 0, 0.5, 0.5, 0]
    assert math.copysign(1.0, row1[24]) == -1.0 and math.copysign(1.0, row1[30]) == -1.0  # -10 * 0 = -0
    assert row1[10:15] == [-2.5, -2.5, 5, 5, 0.5] and row1[-6:] == [25, 25, 0, 0, 339, 0.5]  # in the RZ
    # without the extra features the row stops after LA
    short = ckernels.obs_cpu(*x.values(), torch.full((width - 6,), 2.0), 30.0, False, 50.0)
    assert torch.equal(short, obs[:, :-6])


def test_obs_is_the_layout_s_build_bit_for_bit():
    from uavlae.envs import UAVEnv

    env = UAVEnv(batch_size=[300], seed=4)
    td = env.reset()
    g = torch.Generator().manual_seed(0)
    for _ in range(15):  # OUs move, GEs get served, some rows reset
        td["action"] = torch.rand(300, 2, generator=g) * 2 - 1
        _, td = env.step_and_maybe_reset(td)
    state = {k: td["state", k] for k in env.raw_state_keys}
    lay, cfg = env.layout, env.cfg
    div = lay._divisor.float()[: lay.pre_ego_size]
    obs = ckernels.obs_cpu(*(state[n] for n, _, _ in ckernels.OBS_INPUTS), div, float(cfg.safety.perception_radius),
                           True, float(cfg.obs_distance_scale))
    ref = lay.build(state)
    assert torch.equal(obs, ref) and torch.equal(obs.signbit(), ref.signbit())
    assert (ref[:, 5 * 15 + 5 * 9 + 4 * 7: 5 * 15 + 5 * 9 + 5 * 7] > 0).any()  # some OUs are visible


def test_obs_bad_input_names_the_tensor():
    x = _obs_row_inputs()
    x["ou_mask"] = x["ou_mask"].float()
    with pytest.raises(ValueError, match=r"ou_mask must be a CPU torch.bool tensor of shape \[2, 3\]"):
        ckernels.obs_cpu(*x.values(), torch.ones(55), 30.0, True, 50.0)
    x = _obs_row_inputs()
    with pytest.raises(ValueError, match=r"divisor must be a CPU torch.float32 tensor of shape \[49\]"):
        ckernels.obs_cpu(*x.values(), torch.ones(55), 30.0, False, 50.0)
