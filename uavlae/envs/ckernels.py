"""C kernels for the CPU step: the OU step, the GE service and the observation of the compiled
step (``UAVEnv(compile_step=True)``), the random draws of every CPU step, and three parts of the
scenario sampler: the connectivity check's occupancy grid (:func:`free_grid`) and flood fill
(:func:`flood`), and the scan for each slot's first valid candidate (:func:`first_clear`).
They give the same numbers as the torch code they replace (the draws x6, ``sample_scenarios``
with all of them about x2-4; ``benchmarks/ckernels_ab.json``).

Inductor's C++ for the step runs scalar loops over the tiny entity dimensions (7 OUs x 6
blocked rectangles x 2 coordinates); the OU move check and its heading retries were the
largest part of the compiled step. This kernel does the same work one OU at a time: a
branch-free bounding-box screen over the scenario's rectangles, the exact segment test only
when a box is near, and the retries only for the OUs that are blocked (about 2.5%). It runs
the operations of :func:`uavlae.envs.physics.ou_step` in the same order, in float32, with no
fused multiply-add, so decisions and positions match the torch version; the retried
velocities may differ in the last bit (``cosf``/``sinf``/``sqrtf`` against ATen's).

:func:`uniform` is ``torch.rand(n, generator=g)`` for a CPU generator, bit for bit, with the
generator left in the state torch would leave it in: a replay of ATen's mt19937 on the
generator's ``get_state()`` bytes, whose twist and tempering vectorise (ATen draws one number at
a time); :func:`uniform_runs` writes several such runs already transformed (``u * p``,
``u < p``), as ``world.draw_noise`` needs them. :func:`load` checks the replay against
``torch.rand`` and leaves it off, with a warning, if they differ (a torch whose generator is
laid out differently).

The torch functions in :mod:`uavlae.envs.physics` stay the reference: the eager env always
uses them, and ``tests/test_ckernels.py`` checks these kernels against them. The kernels are
built on first use with the C compiler (``$CC``, else ``cc``/``gcc``, the one Inductor needs
anyway) into ``$UAVLAE_CACHE_DIR`` (default ``~/.cache/uavlae``), atomically; without a
compiler, with ``UAVLAE_C_KERNELS=0``, or when the build fails (a warning names the cause), the
step keeps its torch code. The OU, service and observation kernels are registered as torch
custom ops (:data:`ou_step_cpu`, :data:`serve_cpu`, :data:`obs_cpu`) so that ``torch.compile``
calls them from inside its graph; batches below :data:`MIN_BATCH` keep the torch code.

:data:`obs_cpu` writes the observation's columns (all but the ego-centric ones, which stay
torch) one row at a time; Inductor wrote them in a loop over the batch per part. Without them
Inductor's largest kernel took 2.3 instead of 4.5 ms, and this kernel takes about 1.2 ms (B =
4096, one thread, scratch profiles). It gives Inductor's numbers bit for bit.
"""

from __future__ import annotations

import ctypes
import functools
import hashlib
import math
import os
import shutil
import subprocess
import sys
import tempfile
import warnings
from pathlib import Path

import torch
from torch import Tensor

__all__ = [
    "applies", "first_clear", "flood", "free_grid", "uniform_runs", "load", "LOADED", "SOURCE", "obs_cpu", "obs_width",
    "ou_step_cpu", "serve_cpu", "uniform",
]

SOURCE = r"""
#include <math.h>
#include <stdbool.h>
#include <stdint.h>
#include <string.h>

static inline float lo_(float a, float b) { return a < b ? a : b; }
static inline float hi_(float a, float b) { return a > b ? a : b; }

/* physics.segment_meets_rect's separating-axis test, its bounding boxes known to overlap */
static inline bool side_test(float ax, float ay, float bx, float by, const float *r) {
    float dx = bx - ax, dy = by - ay;
    float cy0 = dx * (r[1] - ay), cy1 = dx * (r[3] - ay);
    float cx0 = dy * (r[0] - ax), cx1 = dy * (r[2] - ax);
    float lo = lo_(cy0, cy1) - hi_(cx0, cx1), hi = hi_(cy0, cy1) - lo_(cx0, cx1);
    return lo <= 0 && hi >= 0;
}

/* physics._ou_move_ok for one move: it meets no present rectangle and ends inside A */
static inline bool move_ok(float sx, float sy, float vx, float vy, float t, const float *rects,
                           const bool *rmask, int64_t nz, float xs, float ys) {
    float ex = sx + vx * t, ey = sy + vy * t;
    int outside = (ex < 0) | (ex > xs) | (ey < 0) | (ey > ys);
    float mnx = lo_(sx, ex), mxx = hi_(sx, ex), mny = lo_(sy, ey), mxy = hi_(sy, ey);
    int near = 0;
    for (int64_t z = 0; z < nz; z++) {
        const float *r = rects + 4 * z;
        near |= (mnx <= r[2]) & (mxx >= r[0]) & (mny <= r[3]) & (mxy >= r[1]) & rmask[z];
    }
    if (outside) return false;
    if (!near) return true;
    for (int64_t z = 0; z < nz; z++) {
        const float *r = rects + 4 * z;
        if (rmask[z] && mnx <= r[2] && mxx >= r[0] && mny <= r[3] && mxy >= r[1]
            && side_test(sx, sy, ex, ey, r)) return false;
    }
    return true;
}

/* Rows split over `nth` OpenMP threads: the runtime torch and Inductor's kernels use (one
   libgomp), so its threads are the ones already waiting for the next parallel loop. */
#ifdef _OPENMP
#define ROWS_PARALLEL _Pragma("omp parallel for num_threads(nth) schedule(static) if (nth > 1)")
#else
#define ROWS_PARALLEL
#endif

/* physics.ou_step with its noise given, for [B, K] OUs and [B, Z] blocked rectangles; the
   retry headings of try j start at retry + j * B * K */
void uavlae_ou_step(int64_t nb, int64_t nk, int64_t nz, int64_t nt, int nth, const float *pos,
                    const float *vel, const bool *mask, const float *rects, const bool *rmask,
                    const bool *turn, const float *speed, const float *hcos, const float *hsin,
                    const float *retry, float xs, float ys, float t, float *npos, float *nvel) {
    const int64_t retry_stride = nb * nk;
    ROWS_PARALLEL
    for (int64_t b = 0; b < nb; b++) {
        const float *r = rects + 4 * nz * b;
        const bool *rm = rmask + nz * b;
        for (int64_t k = 0; k < nk; k++) {
            int64_t i = b * nk + k;
            float px = pos[2 * i], py = pos[2 * i + 1], vx = vel[2 * i], vy = vel[2 * i + 1];
            if (!mask[i]) {  /* absent: position and velocity stay */
                npos[2 * i] = px; npos[2 * i + 1] = py; nvel[2 * i] = vx; nvel[2 * i + 1] = vy;
                continue;
            }
            if (turn[i]) { vx = speed[i] * hcos[i]; vy = speed[i] * hsin[i]; }
            if (!move_ok(px, py, vx, vy, t, r, rm, nz, xs, ys)) {
                /* same speed, the first valid retry heading, else hover */
                float s = sqrtf(vx * vx + vy * vy), cx = 0.0f, cy = 0.0f;
                for (int64_t j = 0; j < nt; j++) {
                    float h = retry[j * retry_stride + i];
                    float tx = s * cosf(h), ty = s * sinf(h);
                    if (move_ok(px, py, tx, ty, t, r, rm, nz, xs, ys)) { cx = tx; cy = ty; break; }
                }
                vx = cx; vy = cy;
            }
            npos[2 * i] = px + vx * t; npos[2 * i + 1] = py + vy * t;
            nvel[2 * i] = vx; nvel[2 * i + 1] = vy;
        }
    }
}

/* physics.channel then physics.serve_ge for [B] DCU positions and [B, G] GEs: the rate (a
   log2) is computed only for the eligible GEs, the only ones serve_ge can pick */
void uavlae_serve(int64_t nb, int64_t ng, int nth, const float *p, const float *ge, const float *rem,
                  const bool *mask, const float *tie, float h2, float tx, float alpha,
                  float noise, float thr, float t_hover, float *td, int64_t *served,
                  float *rem_new) {
    ROWS_PARALLEL
    for (int64_t b = 0; b < nb; b++) {
        float rate[ng > 0 ? ng : 1];
        const float *g = ge + 2 * ng * b;
        const float *r = rem + ng * b;
        float *out = rem_new + ng * b;
        float best = -INFINITY;
        unsigned char eligible[ng > 0 ? ng : 1];
        for (int64_t i = 0; i < ng; i++) {
            float dx = p[2 * b] - g[2 * i], dy = p[2 * b + 1] - g[2 * i + 1];
            float d2 = (dx * dx + dy * dy) + h2;
            float snr = (tx * ((1.0f / d2) * alpha)) / noise;
            eligible[i] = mask[ng * b + i] && r[i] > 0 && snr >= thr;
            out[i] = r[i];
            if (eligible[i]) {
                rate[i] = log2f(1.0f + snr);
                if (rate[i] > best) best = rate[i];
            }
        }
        int64_t pick = -1;
        float pick_noise = -1.0f;
        for (int64_t i = 0; i < ng; i++) {  /* exact ties at the best rate: the largest noise, first on equal */
            if (eligible[i] && rate[i] == best && tie[ng * b + i] > pick_noise) { pick = i; pick_noise = tie[ng * b + i]; }
        }
        served[b] = pick;
        if (pick < 0) { td[b] = 0.0f; continue; }
        float dv = r[pick], cap = rate[pick] * t_hover;
        float got = dv < cap ? dv : cap;
        td[b] = got;
        out[pick] = r[pick] - got;
    }
}

/* world.ObservationLayout.build's columns before the ego ones, for [B] rows: each row's raw
   values are written, then a block of rows is divided by the divisors `div` in loops the
   compiler vectorises (float division is exact per lane, so the same numbers as torch's; a row
   divided right after its scalar stores would stall on store forwarding). Per
   row: the GEs' positions, remaining data, presence twice; per zone type (nfz, rz, bz)
   [x0, y0, x1 - x0, y1 - y0], then presence; the OUs nearest first, those present within `pr`
   (by sqrtf(dx dx + dy dy)) before the others and ties in index order (world._stable_order), as
   relative position and velocity times visibility (a hidden OU gives +-0, as x * 0 does in
   torch), then visibility; the DCU's position, velocity, energy left, slot data, TA and LA;
   with `extra`, the extra features: the distances to the nearest BZ, NFZ, RZ and boundary at
   most `scale`, to LA, and whether the DCU is inside an RZ. */
static inline int64_t zone_cols(float *o, int64_t c, const float *r, const bool *m, int64_t n) {
    for (int64_t z = 0; z < n; z++, c += 4) {
        const float *q = r + 4 * z;
        o[c] = q[0]; o[c + 1] = q[1]; o[c + 2] = q[2] - q[0]; o[c + 3] = q[3] - q[1];
    }
    for (int64_t z = 0; z < n; z++, c++) o[c] = (float)m[z];
    return c;
}

void uavlae_obs(int64_t nb, int64_t ng, int64_t nn, int64_t nr, int64_t nz, int64_t nk, int nth,
                const float *ge, const float *rem, const bool *gm, const float *nfz, const bool *nfm,
                const float *rz, const bool *rzm, const float *bz, const bool *bzm, const float *ou,
                const float *ouv, const bool *oum, const float *p, const float *v, const float *el,
                const float *sd, const float *ta, const float *la, float pr, int extra,
                const float *dbz, const float *dnfz, const float *drz, const float *dbd,
                const float *dla, float scale, const float *d, float *obs) {
    const int64_t w = 5 * (ng + nn + nr + nz + nk) + 14 + (extra ? 6 : 0), block = 16;
    ROWS_PARALLEL
    for (int64_t b0 = 0; b0 < nb; b0 += block) {
        const int64_t b1 = b0 + block < nb ? b0 + block : nb;
        for (int64_t b = b0; b < b1; b++) {
            float *restrict o = obs + w * b;
            int64_t c = 0;
            const float *g = ge + 2 * ng * b;
            for (int64_t i = 0; i < 2 * ng; i++, c++) o[c] = g[i];
            for (int64_t i = 0; i < ng; i++, c++) o[c] = rem[ng * b + i];
            for (int64_t t = 0; t < 2; t++)
                for (int64_t i = 0; i < ng; i++, c++) o[c] = (float)gm[ng * b + i];
            c = zone_cols(o, c, nfz + 4 * nn * b, nfm + nn * b, nn);
            c = zone_cols(o, c, rz + 4 * nr * b, rzm + nr * b, nr);
            c = zone_cols(o, c, bz + 4 * nz * b, bzm + nz * b, nz);
            const float px = p[2 * b], py = p[2 * b + 1];
            float rx[nk > 0 ? nk : 1], ry[nk > 0 ? nk : 1], key[nk > 0 ? nk : 1];
            int64_t order[nk > 0 ? nk : 1];
            for (int64_t i = 0; i < nk; i++) {
                const int64_t j = nk * b + i;
                rx[i] = ou[2 * j] - px; ry[i] = ou[2 * j + 1] - py;
                const float dist = sqrtf(rx[i] * rx[i] + ry[i] * ry[i]);
                key[i] = (oum[j] && dist <= pr) ? dist : INFINITY;
                int64_t s = i;  /* stable insertion: i goes after every earlier key <= its own */
                while (s > 0 && key[order[s - 1]] > key[i]) { order[s] = order[s - 1]; s--; }
                order[s] = i;
            }
            for (int64_t s = 0; s < nk; s++) {
                const int64_t i = order[s], j = nk * b + i;
                const float vis = (float)(key[i] < INFINITY);
                o[c + 2 * s] = rx[i] * vis; o[c + 2 * s + 1] = ry[i] * vis;
                o[c + 2 * (nk + s)] = ouv[2 * j] * vis; o[c + 2 * (nk + s) + 1] = ouv[2 * j + 1] * vis;
                o[c + 4 * nk + s] = vis;
            }
            c += 5 * nk;
            o[c] = px; o[c + 1] = py; o[c + 2] = v[2 * b]; o[c + 3] = v[2 * b + 1];
            o[c + 4] = el[b]; o[c + 5] = sd[b];
            c += 6;
            for (int64_t i = 0; i < 4; i++, c++) o[c] = ta[4 * b + i];
            for (int64_t i = 0; i < 4; i++, c++) o[c] = la[4 * b + i];
            if (extra) {
                const float near[4] = {dbz[b], dnfz[b], drz[b], dbd[b]};
                for (int64_t i = 0; i < 4; i++, c++) o[c] = near[i] > scale ? scale : near[i];
                o[c] = dla[b]; o[c + 1] = (float)(drz[b] <= 0.0f);
            }
        }
        for (int64_t b = b0; b < b1; b++) {
            float *restrict o = obs + w * b;
            for (int64_t i = 0; i < w; i++) o[i] = o[i] / d[i];
        }
    }
}

/* scenario._connected's flood fill on the packed occupancy grid: `free` and `reached` are
   [nb, ny, nx] words, bit s of a word the cell of scenario 64 w + s. `reached` (the seeds, all
   free) grows to the whole 4-neighbour free component of its seeds: raster passes forward
   (from the west and south neighbours) and backward (east, north) until one changes nothing. */
void uavlae_flood(int64_t nb, int64_t ny, int64_t nx, int nth, const int64_t *free_, int64_t *reached) {
    ROWS_PARALLEL
    for (int64_t w = 0; w < nb; w++) {
        const uint64_t *f = (const uint64_t *)free_ + w * ny * nx;
        uint64_t *r = (uint64_t *)reached + w * ny * nx;
        for (int changed = 1; changed;) {
            changed = 0;
            for (int64_t y = 0; y < ny; y++) {
                for (int64_t x = 0; x < nx; x++) {
                    int64_t i = y * nx + x;
                    uint64_t v = r[i] | (x > 0 ? r[i - 1] : 0) | (y > 0 ? r[i - nx] : 0);
                    v &= f[i];
                    if (v != r[i]) { r[i] |= v; changed = 1; }
                }
            }
            for (int64_t y = ny - 1; y >= 0; y--) {
                for (int64_t x = nx - 1; x >= 0; x--) {
                    int64_t i = y * nx + x;
                    uint64_t v = r[i] | (x < nx - 1 ? r[i + 1] : 0) | (y < ny - 1 ? r[i + nx] : 0);
                    v &= f[i];
                    if (v != r[i]) { r[i] |= v; changed = 1; }
                }
            }
        }
    }
}

/* scenario._connected's grids: `free` [nb, ny, nx] words (bit s of a word: scenario 64 w + s)
   holds the cells whose centre is neither inside nor within d of a present rectangle
   (scenario._blocked's rule: the rows level with a rectangle, columns within d or inside; the
   kmax rows above and below it, columns with dx^2 < d^2 - dy^2), then the cells of each
   scenario's np points (flat index, where present) set free; `seed` gets the bit of each
   scenario's first point. Padding scenarios (64 nb > n) are free everywhere, as _pack pads. */
void uavlae_free_grid(int64_t n, int64_t nr, int64_t ny, int64_t nx, int64_t kmax, int nth,
                      const float *rects, const bool *rmask, const float *cx, const float *cy,
                      float d, float d2, int64_t np, const int64_t *cells, const bool *cmask,
                      int64_t *free_, int64_t *seed_) {
    const int64_t nb = (n + 63) / 64, plane = ny * nx;
    ROWS_PARALLEL
    for (int64_t w = 0; w < nb; w++) {
        uint64_t *g = (uint64_t *)free_ + w * plane, *sd = (uint64_t *)seed_ + w * plane;
        float dx[nx > 0 ? nx : 1], dy[ny > 0 ? ny : 1];
        memset(g, 0, (size_t)plane * 8);
        memset(sd, 0, (size_t)plane * 8);
        for (int64_t s = 0; s < 64 && 64 * w + s < n; s++) {
            const int64_t b = 64 * w + s;
            const uint64_t bit = (uint64_t)1 << s;
            for (int64_t r = 0; r < nr; r++) {
                if (!rmask[b * nr + r]) continue;
                const float *q = rects + 4 * (b * nr + r);
                int64_t lo = nx, hi = -1, above = 0, below = -1;
                for (int64_t i = 0; i < nx; i++) {
                    float v = hi_(q[0] - cx[i], cx[i] - q[2]);
                    dx[i] = v > 0.0f ? v : 0.0f;
                    if (dx[i] < d || dx[i] == 0.0f) { if (lo == nx) lo = i; hi = i; }
                }
                for (int64_t j = 0; j < ny; j++) {
                    float v = hi_(q[1] - cy[j], cy[j] - q[3]);
                    dy[j] = v > 0.0f ? v : 0.0f;
                    above += cy[j] <= q[3];  /* searchsorted(cy, y1, right=True) */
                    below += cy[j] < q[1];   /* searchsorted(cy, y0) - 1 */
                }
                for (int64_t j = 0; j < ny; j++) {
                    if (dy[j] != 0.0f) continue;
                    uint64_t *row = g + j * nx;
                    for (int64_t i = lo; i <= hi; i++)
                        if (dx[i] < d || dx[i] == 0.0f) row[i] |= bit;
                }
                for (int64_t k = 0; k < kmax; k++) {
                    for (int e = 0; e < 2; e++) {
                        int64_t j = e ? below - k : above + k;
                        if (j < 0 || j >= ny) continue;
                        float dyk = dy[j], e2 = d2 - dyk * dyk;
                        if (!(dyk > 0.0f && e2 > 0.0f)) continue;
                        uint64_t *row = g + j * nx;
                        for (int64_t i = 0; i < nx; i++)
                            if (dx[i] * dx[i] < e2) row[i] |= bit;
                    }
                }
            }
        }
        for (int64_t c = 0; c < plane; c++) g[c] = ~g[c];
        for (int64_t s = 0; s < 64 && 64 * w + s < n; s++) {
            const int64_t b = 64 * w + s;
            const uint64_t bit = (uint64_t)1 << s;
            for (int64_t t = 0; t < np; t++) {
                if (!cmask[b * np + t]) continue;
                g[cells[b * np + t]] |= bit;
                if (t == 0) sd[cells[b * np]] |= bit;
            }
        }
    }
}

/* scenario._first_valid's scan, for m rows of k candidates: the index of the first candidate
   that `pre` [m, k] admits and that keeps clear of every present rectangle of its row's table
   (rects[row[i]], [nz, 4], rmask[row[i]]); -1 when none does. Points [m, k, 2] keep clear as in
   scenario._clear_of: squared distance dx^2 + dy^2 >= margin2 (> 0 when `strict`).
   Rectangles [m, k, 4] as in scenario._rects_overlap: open interiors that do not meet. */
void uavlae_first_clear(int64_t m, int64_t k, int64_t nz, int nth, int rect, const float *cand,
                        const bool *pre, const int64_t *row, const float *rects, const bool *rmask,
                        float margin2, int strict, int64_t *first) {
    const int64_t w = rect ? 4 : 2;
    ROWS_PARALLEL
    for (int64_t i = 0; i < m; i++) {
        const float *r = rects + 4 * nz * row[i];
        const bool *rm = rmask + nz * row[i];
        first[i] = -1;
        for (int64_t j = 0; j < k; j++) {
            if (!pre[i * k + j]) continue;
            const float *c = cand + w * (i * k + j);
            bool ok = true;
            for (int64_t z = 0; z < nz && ok; z++) {
                if (!rm[z]) continue;
                const float *q = r + 4 * z;
                if (rect) {
                    ok = !(c[0] < q[2] && q[0] < c[2] && c[1] < q[3] && q[1] < c[3]);
                } else {
                    float dx = hi_(q[0] - c[0], c[0] - q[2]), dy = hi_(q[1] - c[1], c[1] - q[3]);
                    dx = dx > 0.0f ? dx : 0.0f; dy = dy > 0.0f ? dy : 0.0f;
                    float d2 = dx * dx + dy * dy;
                    ok = strict ? d2 > 0.0f : d2 >= margin2;
                }
            }
            if (ok) { first[i] = j; break; }
        }
    }
}

/* torch.rand(n, generator=g) for a CPU generator, replayed: ATen's mt19937 (the engine behind
   torch.Generator on CPU) and its float32 uniform, (y & (2^24 - 1)) * 2^-24. `st` is the
   generator's get_state() bytes: seed (int64), left (int32), seeded (int32), next (uint64),
   then the 624 state words, one per uint64; uavlae_mt_runs advances it in place, as torch
   advances it. The same numbers, several times faster: the twist and the tempering run as plain
   loops the compiler vectorises, where ATen draws one number at a time. uavlae_mt_runs returns
   1 on a state it does not know (nothing written), 0 otherwise. */
#define MT_N 624
#define MT_M 397
static inline uint32_t mt_twist(uint32_t u, uint32_t v) {
    return (((u & 0x80000000u) | (v & 0x7fffffffu)) >> 1) ^ ((v & 1u) ? 0x9908b0dfu : 0u);
}

static int mt_load(const unsigned char *st, uint32_t *s, int32_t *left, uint64_t *next) {
    int32_t seeded;
    memcpy(left, st + 8, 4); memcpy(&seeded, st + 12, 4); memcpy(next, st + 16, 8);
    if (!seeded || *left < 1 || *left > MT_N || *next > MT_N) return 1;
    for (int i = 0; i < MT_N; i++) { uint64_t w; memcpy(&w, st + 24 + 8 * i, 8); s[i] = (uint32_t)w; }
    return 0;
}

static void mt_store(unsigned char *st, const uint32_t *s, int32_t left, uint64_t next) {
    memcpy(st + 8, &left, 4); memcpy(st + 16, &next, 8);
    for (int i = 0; i < MT_N; i++) { uint64_t w = s[i]; memcpy(st + 24 + 8 * i, &w, 8); }
}

/* the next n numbers of the stream into out */
static void mt_fill(uint32_t *s, int32_t *left, uint64_t *next, float *out, int64_t n) {
    for (int64_t done = 0; done < n;) {
        if (*left == 1) {  /* ATen's next_state(); then left = 625 - next as after each draw */
            int i = 0;
            for (; i < MT_N - MT_M; i++) s[i] = s[i + MT_M] ^ mt_twist(s[i], s[i + 1]);
            for (; i < MT_N - 1; i++) s[i] = s[i + MT_M - MT_N] ^ mt_twist(s[i], s[i + 1]);
            s[MT_N - 1] = s[MT_M - 1] ^ mt_twist(s[MT_N - 1], s[0]);
            *left = MT_N + 1; *next = 0;
        }
        int64_t take = *left - 1 < n - done ? *left - 1 : n - done;
        const uint32_t *src = s + *next;
        float *dst = out + done;
        for (int64_t j = 0; j < take; j++) {
            uint32_t y = src[j];
            y ^= y >> 11; y ^= (y << 7) & 0x9d2c5680u; y ^= (y << 15) & 0xefc60000u; y ^= y >> 18;
            dst[j] = (float)(y & 0xffffffu) * (1.0f / 16777216.0f);
        }
        done += take; *next += (uint64_t)take; *left -= (int32_t)take;
    }
}

/* nr consecutive runs of torch.rand numbers, each written as torch would transform it: run r
   is count[r] numbers u, out[r][i] = u * param[r] (float32; param 1: u itself) or, where
   less[r], the bool u < param[r]. */
int uavlae_mt_runs(unsigned char *st, int64_t nr, const int64_t *count, const int *less,
                   const float *param, void **out) {
    uint32_t s[MT_N];
    int32_t left;
    uint64_t next;
    if (mt_load(st, s, &left, &next)) return 1;
    for (int64_t r = 0; r < nr; r++) {
        const float p = param[r];
        if (less[r]) {
            bool *o = (bool *)out[r];
            float buf[1024];
            for (int64_t i = 0; i < count[r]; i += 1024) {
                int64_t c = count[r] - i < 1024 ? count[r] - i : 1024;
                mt_fill(s, &left, &next, buf, c);
                for (int64_t j = 0; j < c; j++) o[i + j] = buf[j] < p;
            }
        } else {
            float *o = (float *)out[r];
            mt_fill(s, &left, &next, o, count[r]);
            if (p != 1.0f) for (int64_t j = 0; j < count[r]; j++) o[j] = o[j] * p;
        }
    }
    mt_store(st, s, left, next);
    return 0;
}
"""

# -ffp-contract=off: no fused multiply-add, so every product rounds as torch's does
FLAGS = ("-O3", "-ffp-contract=off", "-fno-math-errno", "-shared", "-fPIC")
# OpenMP (the libgomp torch loads, found by its soname) when the compiler has it, else one thread
OPENMP_FLAGS = ("-fopenmp",)

LOADED = False  # read by physics.ou_step while torch.compile traces (a constant it guards on)
_TRIED = False
# Below this many scenarios the custom ops' fixed cost per call (about 70 us each at B = 8, timed
# by hand: 30 us of dispatch, 40 us of Python checks and the ctypes call) outweighs what the
# kernels save: smaller compiled batches keep the torch code (B = 64: x0.96 with the kernels).
MIN_BATCH = 256
# The library and the ops of this source, kept on ``sys`` so that importing this module again
# (benchmarks/env_ab.py imports two source trees in one process) reuses them instead of
# registering the same op name twice; ops of another source get other names.
_KEY = hashlib.sha256("\0".join((SOURCE, *FLAGS, *OPENMP_FLAGS)).encode()).hexdigest()[:12]
_STATE = sys.__dict__.setdefault("_uavlae_ckernels", {}).setdefault(_KEY, {"lib": None, "ops": None, "mt": False})


def applies(x: Tensor) -> bool:
    """Whether the step being traced runs the kernels: inside a CPU torch.compile graph, float32,
    at least :data:`MIN_BATCH` scenarios (``x``: any ``[B, ...]`` tensor of the step), and
    :func:`load` succeeded. Elsewhere the torch code beside each call runs: it stays the
    reference, and the path on every other device."""
    return (
        LOADED and torch.compiler.is_compiling() and x.device.type == "cpu" and x.dtype == torch.float32
        and x.shape[0] >= MIN_BATCH
    )


def _cache_dir() -> Path:
    return Path(os.environ.get("UAVLAE_CACHE_DIR", "~/.cache/uavlae")).expanduser() / "ckernels"


def _build(cc: str) -> Path:
    """The shared library for SOURCE and FLAGS, with OpenMP if the compiler has it, built once per
    source, flags and compiler and moved into place atomically (a concurrent or interrupted build
    leaves nothing half-written)."""
    stem = _cache_dir() / f"uavlae_kernels_{_KEY}_{hashlib.sha256(cc.encode()).hexdigest()[:8]}"
    variants = [(Path(f"{stem}.so"), (*FLAGS, *OPENMP_FLAGS)), (Path(f"{stem}_serial.so"), FLAGS)]
    for target, _ in variants:
        if target.exists():
            return target
    stem.parent.mkdir(parents=True, exist_ok=True)
    error = ""
    for target, flags in variants:
        with tempfile.TemporaryDirectory(dir=stem.parent, prefix=".build-") as tmp:
            src, out = Path(tmp) / "uavlae_kernels.c", Path(tmp) / "uavlae_kernels.so"
            src.write_text(SOURCE)
            proc = subprocess.run([cc, *flags, str(src), "-o", str(out), "-lm"], capture_output=True, text=True, timeout=120)
            if proc.returncode == 0:
                os.replace(out, target)
                return target
            error = f"{cc} exited with {proc.returncode}: {proc.stderr.strip()[:500]}"
    raise RuntimeError(error)


def load() -> bool:
    """Build (once) and load the kernels; ``True`` when :data:`ou_step_cpu`, :data:`serve_cpu`,
    :data:`obs_cpu`, :func:`flood`, :func:`free_grid` and :func:`first_clear` can run (:func:`uniform` also needs
    its check against ``torch.rand`` to pass).
    Never raises: a missing compiler or a failed build warns and returns ``False``."""
    global LOADED, _TRIED
    if _TRIED:
        return LOADED
    _TRIED = True
    if _STATE["lib"] is not None:
        LOADED = True
        return True
    if os.environ.get("UAVLAE_C_KERNELS", "1") == "0":
        return False
    cc = os.environ.get("CC") or shutil.which("cc") or shutil.which("gcc")
    if not cc:
        warnings.warn("uavlae: no C compiler found ($CC, cc, gcc); the CPU step keeps its torch code")
        return False
    try:
        lib = ctypes.CDLL(str(_build(cc)))
    except Exception as exc:  # a build or load failure only costs speed
        warnings.warn(f"uavlae: the C kernels could not be built ({exc}); the CPU step keeps its torch code")
        return False
    p, i64, f32 = ctypes.c_void_p, ctypes.c_int64, ctypes.c_float
    lib.uavlae_ou_step.argtypes = [i64, i64, i64, i64, ctypes.c_int, *([p] * 10), f32, f32, f32, p, p]
    lib.uavlae_ou_step.restype = None
    lib.uavlae_serve.argtypes = [i64, i64, ctypes.c_int, *([p] * 5), *([f32] * 6), p, p, p]
    lib.uavlae_serve.restype = None
    lib.uavlae_obs.argtypes = [*([i64] * 6), ctypes.c_int, *([p] * 18), f32, ctypes.c_int, *([p] * 5), f32, p, p]
    lib.uavlae_obs.restype = None
    lib.uavlae_flood.argtypes = [i64, i64, i64, ctypes.c_int, p, p]
    lib.uavlae_flood.restype = None
    lib.uavlae_free_grid.argtypes = [i64, i64, i64, i64, i64, ctypes.c_int, *([p] * 4), f32, f32, i64, p, p, p, p]
    lib.uavlae_free_grid.restype = None
    lib.uavlae_first_clear.argtypes = [i64, i64, i64, ctypes.c_int, ctypes.c_int, *([p] * 5), f32, ctypes.c_int, p]
    lib.uavlae_first_clear.restype = None
    lib.uavlae_mt_runs.argtypes = [p, i64, p, p, p, p]
    lib.uavlae_mt_runs.restype = ctypes.c_int
    _STATE["lib"], LOADED = lib, True
    _STATE["mt"] = _mt_self_check()
    if not _STATE["mt"]:
        warnings.warn("uavlae: torch's CPU generator is not the mt19937 state that the C replay knows "
                      "(a new torch?); the random draws stay torch.rand")
    return True


# Below this many numbers get_state/set_state and the call cost more than ATen's draws save.
MT_MIN_DRAWS = 2048
_MT_STATE_BYTES = 5056  # sizeof(at::CPUGeneratorImplState) in torch 2.x; anything else: torch.rand


def _mt_runs(generator: torch.Generator, runs: list[tuple[torch.Size, str, float]]) -> list[Tensor] | None:
    """:func:`uniform_runs` without its conditions: ``None`` for a state the replay does not know."""
    if any(op not in ("*", "<") for _, op, _ in runs):
        raise ValueError(f"uniform_runs: op must be '*' or '<', got {[op for _, op, _ in runs]}")
    st = generator.get_state()
    if st.numel() != _MT_STATE_BYTES:
        return None
    outs = [torch.empty(shape, dtype=torch.bool if op == "<" else torch.float32) for shape, op, _ in runs]
    k = len(runs)
    code = _STATE["lib"].uavlae_mt_runs(
        st.data_ptr(), k, (ctypes.c_int64 * k)(*[t.numel() for t in outs]),
        (ctypes.c_int * k)(*[op == "<" for _, op, _ in runs]), (ctypes.c_float * k)(*[p for _, _, p in runs]),
        (ctypes.c_void_p * k)(*[t.data_ptr() for t in outs]),
    )
    if code != 0:
        return None
    generator.set_state(st)
    return outs


def _mt_uniform(generator: torch.Generator, n: int) -> Tensor | None:
    out = _mt_runs(generator, [(torch.Size([n]), "*", 1.0)])
    return None if out is None else out[0]


def _mt_self_check() -> bool:
    """Whether the replay gives torch.rand's numbers and leaves the generator as torch does, over
    draws that cross the 624-word twists, from a fresh and a used generator."""
    for seed in (0, 2**40 + 7):
        g, h = torch.Generator().manual_seed(seed), torch.Generator().manual_seed(seed)
        for n in (1, 5, 623, 624, 625, 1500, 2):
            want, got = torch.rand(n, generator=g), _mt_uniform(h, n)
            if got is None or not torch.equal(want, got):
                return False
        if not torch.equal(g.get_state(), h.get_state()):
            return False
    return True


def _mt_on(generator: torch.Generator, n: int) -> bool:
    """Whether the C replay draws ``n`` numbers from ``generator``: loaded and checked against
    torch.rand (:func:`load`), a CPU generator, and at least :data:`MT_MIN_DRAWS` numbers."""
    return _STATE["mt"] and _STATE["lib"] is not None and generator.device.type == "cpu" and n >= MT_MIN_DRAWS


def uniform(generator: torch.Generator, n: int) -> Tensor:
    """``torch.rand(n, generator=generator)``: the same float32 numbers, and the generator left in
    the same state, drawn several times faster by the C replay of ATen's mt19937 when
    :func:`load` succeeded and checked it (``generator`` on CPU); else torch.rand itself."""
    if _mt_on(generator, n):
        out = _mt_uniform(generator, n)
        if out is not None:
            return out
    return torch.rand(n, generator=generator)


def uniform_runs(generator: torch.Generator, runs: list[tuple[torch.Size, str, float]]) -> list[Tensor] | None:
    """Consecutive ``torch.rand`` draws from ``generator``, each transformed as torch would:
    ``runs`` lists ``(shape, op, param)`` in draw order, ``op`` ``"*"`` (float32 ``u * param``)
    or ``"<"`` (bool ``u < param``). The same tensors as drawing each with ``torch.rand`` and
    applying the op, written by one C pass with no intermediate; ``None`` (do that) unless the
    replay is on (:func:`uniform`), the generator is on the CPU and the runs hold at least
    :data:`MT_MIN_DRAWS` numbers."""
    if not _mt_on(generator, sum(math.prod(shape) for shape, _, _ in runs)):
        return None
    return _mt_runs(generator, runs)


_MIN_ROWS_PER_THREAD = 512  # below this a thread costs more than it saves


def _threads(rows: int, per_thread: int = _MIN_ROWS_PER_THREAD) -> int:
    """How many of torch's intra-op threads the kernels split ``rows`` over."""
    return max(1, min(torch.get_num_threads(), rows // per_thread))


def _require(op: str, specs) -> None:
    """Raises a ValueError naming the first ``(name, tensor, dtype, shape)`` of ``specs`` whose
    tensor is not a CPU tensor of that dtype and shape (the custom ops' check of their inputs)."""
    for name, x, dtype, shape in specs:
        if not (x.is_cpu and x.dtype == dtype and x.shape == shape):
            raise ValueError(f"{op}: {name} must be a CPU {dtype} tensor of shape {list(shape)}, "
                             f"got {x.device.type} {x.dtype} {list(x.shape)}")


def _cpu_tensors(*specs: tuple[Tensor, torch.dtype, int]) -> bool:
    """Whether the kernels are loaded and every ``(tensor, dtype, dim)`` is a CPU tensor of that
    dtype and number of dimensions: the inputs the C functions take (else: the torch code)."""
    return _STATE["lib"] is not None and all(
        t.is_cpu and t.dtype == dtype and t.dim() == dim for t, dtype, dim in specs
    )


def flood(free: Tensor, seed: Tensor) -> Tensor | None:
    """The 4-neighbour component of ``seed`` in ``free`` (both int64 ``[nb, ny, nx]``, 64
    scenarios per word, seed bits free), as ``scenario._connected``'s flood fill reaches it;
    ``None`` (flood with torch) unless the kernels are loaded and both are CPU int64 tensors of
    that shape."""
    lib = _STATE["lib"]
    if not _cpu_tensors((free, torch.int64, 3), (seed, torch.int64, 3)) or seed.shape != free.shape:
        return None
    free, reached = free.contiguous(), seed.clone(memory_format=torch.contiguous_format)
    lib.uavlae_flood(*free.shape, _threads(free.shape[0], 1), free.data_ptr(), reached.data_ptr())
    return reached


def free_grid(rects: Tensor, rmask: Tensor, cx: Tensor, cy: Tensor, d: float, kmax: int, cells: Tensor,
              cmask: Tensor) -> tuple[Tensor, Tensor] | None:
    """``scenario._connected``'s packed grids, ``(free, seed)`` int64 ``[ceil(n / 64), ny, nx]``:
    free is ``~scenario._blocked(rects [n, R, 4], rmask [n, R])`` (cell centres ``cx`` [nx],
    ``cy`` [ny], inflation ``d``, ``kmax`` rows above and below) with the cells ``cells``
    [n, P] (flat index ``j * nx + i``, where ``cmask`` [n, P]) set free, and seed holds the cell
    of each scenario's first point. The same bits as the torch code; ``None`` (use it) unless the
    kernels are loaded and every tensor is on the CPU with the expected dtype."""
    lib = _STATE["lib"]
    if not _cpu_tensors((rects, torch.float32, 3), (rmask, torch.bool, 2), (cx, torch.float32, 1),
                        (cy, torch.float32, 1), (cells, torch.int64, 2), (cmask, torch.bool, 2)):
        return None
    n, nr = rmask.shape
    ny, nx, np_ = cy.shape[0], cx.shape[0], cells.shape[1]
    if rects.shape != (n, nr, 4) or cells.shape[0] != n or cmask.shape != cells.shape or n == 0 or np_ == 0:
        return None
    if bool(((cells < 0) | (cells >= ny * nx)).any()):
        raise ValueError(f"free_grid: cells must index the {ny} x {nx} grid")
    c = [t.contiguous() for t in (rects, rmask, cx, cy, cells, cmask)]
    nb = -(-n // 64)
    free, seed = torch.empty(nb, ny, nx, dtype=torch.int64), torch.empty(nb, ny, nx, dtype=torch.int64)
    lib.uavlae_free_grid(n, nr, ny, nx, kmax, _threads(nb, 1), *(t.data_ptr() for t in c[:4]), d, d * d,
                         np_, c[4].data_ptr(), c[5].data_ptr(), free.data_ptr(), seed.data_ptr())
    return free, seed


def first_clear(cand: Tensor, pre: Tensor, row: Tensor, rects: Tensor, rmask: Tensor,
                margin: float | None = None) -> Tensor | None:
    """``scenario._first_valid``'s scan: for each of the m rows of ``cand`` (points [m, k, 2] or,
    with ``margin=None``, rectangles [m, k, 4]), the index of the first candidate that ``pre``
    [m, k] admits and that keeps clear of every present rectangle of ``rects[row]`` ([n, Z, 4],
    ``rmask`` [n, Z]): a point by ``margin`` (``scenario._clear_of``), a rectangle by not
    overlapping (``scenario._rects_overlap``); -1 when none does. int64 [m]; ``None`` (use the
    torch code) unless the kernels are loaded and the tensors are CPU float32/bool/int64."""
    lib = _STATE["lib"]
    if not _cpu_tensors((cand, torch.float32, 3), (pre, torch.bool, 2), (row, torch.int64, 1),
                        (rects, torch.float32, 3), (rmask, torch.bool, 2)):
        return None
    m, k, w = cand.shape
    n, nz = rmask.shape
    if w != (2 if margin is not None else 4) or pre.shape != (m, k) or row.shape != (m,) or rects.shape != (n, nz, 4):
        raise ValueError(f"first_clear: shapes cand {tuple(cand.shape)}, pre {tuple(pre.shape)}, row "
                         f"{tuple(row.shape)}, rects {tuple(rects.shape)}, rmask {tuple(rmask.shape)} do not fit")
    if m and bool(((row < 0) | (row >= n)).any()):
        raise ValueError(f"first_clear: row must index the {n} tables")
    first = torch.empty(m, dtype=torch.int64)
    if m == 0:
        return first
    c = [t.contiguous() for t in (cand, pre, row, rects, rmask)]
    margin2, strict = (0.0, 0) if margin is None else (margin * margin, int(margin <= 0))
    lib.uavlae_first_clear(m, k, nz, _threads(m), int(margin is None), *(t.data_ptr() for t in c), margin2, strict,
                           first.data_ptr())
    return first


_F32 = {"pos": 3, "vel": 3, "blocked": 3, "speed": 2, "heading_cos": 2, "heading_sin": 2, "retry_heading": 3}
_BOOL = {"mask": 2, "blocked_mask": 2, "turn": 2}


def _ou_step_impl(
    pos: Tensor, vel: Tensor, mask: Tensor, blocked: Tensor, blocked_mask: Tensor, turn: Tensor,
    speed: Tensor, heading_cos: Tensor, heading_sin: Tensor, retry_heading: Tensor,
    x_size: float, y_size: float, t_fly: float,
) -> tuple[Tensor, Tensor]:
    """``physics.ou_step`` for ``pos``/``vel`` ``[B, K, 2]``, ``blocked`` ``[B, Z, 4]`` and the
    slot's noise (``retry_heading`` ``[T, B, K]``), on CPU float32: ``(new_pos, new_vel)``."""
    lib = _STATE["lib"]
    if lib is None:
        raise RuntimeError("ckernels.ou_step_cpu needs the C kernel: call uavlae.envs.ckernels.load() first")
    args = dict(pos=pos, vel=vel, mask=mask, blocked=blocked, blocked_mask=blocked_mask, turn=turn,
                speed=speed, heading_cos=heading_cos, heading_sin=heading_sin, retry_heading=retry_heading)
    for name, x in args.items():
        want = torch.float32 if name in _F32 else torch.bool
        dim = _F32.get(name) or _BOOL[name]
        if not x.is_cpu or x.dtype != want or x.dim() != dim:
            raise ValueError(f"ou_step_cpu: {name} must be a {dim}-d CPU {want} tensor, got {x.dim()}-d {x.device.type} {x.dtype}")
    b, k = mask.shape
    z, t = blocked.shape[1], retry_heading.shape[0]
    if pos.shape != (b, k, 2) or vel.shape != (b, k, 2) or blocked.shape != (b, z, 4) or blocked_mask.shape != (b, z) \
            or retry_heading.shape != (t, b, k) or any(args[n].shape != (b, k) for n in ("turn", "speed", "heading_cos", "heading_sin")):
        raise ValueError("ou_step_cpu: shapes must be pos/vel [B, K, 2], mask/turn/speed/heading_* [B, K], "
                         f"blocked [B, Z, 4], blocked_mask [B, Z], retry_heading [T, B, K]; got {[tuple(x.shape) for x in args.values()]}")
    c = {n: x.contiguous() for n, x in args.items()}
    new_pos, new_vel = torch.empty((b, k, 2)), torch.empty((b, k, 2))
    order = ("pos", "vel", "mask", "blocked", "blocked_mask", "turn", "speed", "heading_cos", "heading_sin",
             "retry_heading", "new_pos", "new_vel")
    c.update(new_pos=new_pos, new_vel=new_vel)

    ptr = [c[n].data_ptr() for n in order]
    lib.uavlae_ou_step(b, k, z, t, _threads(b), *ptr[:10], x_size, y_size, t_fly, *ptr[10:])
    return new_pos, new_vel


def _ou_step_fake(pos, vel, mask, blocked, blocked_mask, turn, speed, heading_cos, heading_sin, retry_heading, x_size, y_size, t_fly):
    return torch.empty_like(pos), torch.empty_like(vel)


def _serve_impl(
    p: Tensor, ge_pos: Tensor, remaining: Tensor, mask: Tensor, tie_noise: Tensor,
    altitude: float, tx_power: float, alpha: float, noise: float, threshold: float, t_hover: float,
) -> tuple[Tensor, Tensor, Tensor]:
    """``physics.channel`` then ``physics.serve_ge`` for DCU positions ``p`` ``[B, 2]`` and GEs
    ``ge_pos`` ``[B, G, 2]`` on CPU float32: ``(slot data [B], served GE [B] (-1: none),
    remaining data [B, G])``."""
    lib = _STATE["lib"]
    if lib is None:
        raise RuntimeError("ckernels.serve_cpu needs the C kernel: call uavlae.envs.ckernels.load() first")
    b, g = mask.shape
    args = (p, ge_pos, remaining, mask, tie_noise)
    _require("serve_cpu", zip(("p", "ge_pos", "remaining", "mask", "tie_noise"), args,
                              (torch.float32, torch.float32, torch.float32, torch.bool, torch.float32),
                              ((b, 2), (b, g, 2), (b, g), (b, g), (b, g))))
    c = [x.contiguous() for x in args]
    td, served, rem = torch.empty(b), torch.empty(b, dtype=torch.int64), torch.empty(b, g)
    outs = [td, served, rem]

    ptr = [x.data_ptr() for x in (*c, *outs)]
    lib.uavlae_serve(b, g, _threads(b), *ptr[:5], altitude * altitude, tx_power, alpha, noise, threshold, t_hover, *ptr[5:])
    return td, served, rem


def _serve_fake(p, ge_pos, remaining, mask, tie_noise, altitude, tx_power, alpha, noise, threshold, t_hover):
    b = p.shape[0]
    return p.new_empty(b), p.new_empty(b, dtype=torch.int64), torch.empty_like(remaining)


# the entries of the observation's base columns, in the C function's order: name, dtype, shape
# in terms of B, G, the three zone maxima (N, R, Z) and K
OBS_INPUTS = (
    ("ge_pos", torch.float32, "BG2"), ("ge_remaining", torch.float32, "BG"), ("ge_mask", torch.bool, "BG"),
    ("nfz", torch.float32, "BN4"), ("nfz_mask", torch.bool, "BN"), ("rz", torch.float32, "BR4"),
    ("rz_mask", torch.bool, "BR"), ("bz", torch.float32, "BZ4"), ("bz_mask", torch.bool, "BZ"),
    ("ou_pos", torch.float32, "BK2"), ("ou_vel", torch.float32, "BK2"), ("ou_mask", torch.bool, "BK"),
    ("position", torch.float32, "B2"), ("velocity", torch.float32, "B2"), ("energy_left", torch.float32, "B"),
    ("slot_data", torch.float32, "B"), ("takeoff", torch.float32, "B4"), ("landing", torch.float32, "B4"),
    ("d_bz", torch.float32, "B"), ("d_nfz", torch.float32, "B"), ("d_rz", torch.float32, "B"),
    ("d_boundary", torch.float32, "B"), ("d_la", torch.float32, "B"),
)


def obs_width(g: int, n: int, r: int, z: int, k: int, extra: bool = False) -> int:
    """The number of observation columns before the ego features for G GEs, N/R/Z zones and K
    OUs, with or without the extra features."""
    return 5 * (g + n + r + z + k) + 14 + (6 if extra else 0)


@functools.lru_cache(maxsize=16)
def _obs_shapes(b: int, counts: tuple[int, ...], width: int) -> tuple[tuple[int, ...], ...]:
    """The shapes OBS_INPUTS (then the divisor) must have for B rows and (G, N, R, Z, K)."""
    sizes = {"B": b, **dict(zip("GNRZK", counts)), "2": 2, "4": 4}
    return (*(tuple(sizes[c] for c in dims) for _, _, dims in OBS_INPUTS), (width,))


def _obs_impl(
    ge_pos: Tensor, ge_remaining: Tensor, ge_mask: Tensor, nfz: Tensor, nfz_mask: Tensor, rz: Tensor,
    rz_mask: Tensor, bz: Tensor, bz_mask: Tensor, ou_pos: Tensor, ou_vel: Tensor, ou_mask: Tensor,
    position: Tensor, velocity: Tensor, energy_left: Tensor, slot_data: Tensor, takeoff: Tensor,
    landing: Tensor, d_bz: Tensor, d_nfz: Tensor, d_rz: Tensor, d_boundary: Tensor, d_la: Tensor,
    divisor: Tensor, perception_radius: float, extra: bool, distance_scale: float,
) -> Tensor:
    """``world.ObservationLayout.build``'s columns before the ego features (with the extra ones
    if ``extra``; the ``d_*`` are read only then) on CPU float32:
    ``[B, obs_width(G, N, R, Z, K, extra)]``, column j divided by ``divisor[j]``."""
    lib = _STATE["lib"]
    if lib is None:
        raise RuntimeError("ckernels.obs_cpu needs the C kernel: call uavlae.envs.ckernels.load() first")
    args = (ge_pos, ge_remaining, ge_mask, nfz, nfz_mask, rz, rz_mask, bz, bz_mask, ou_pos, ou_vel, ou_mask,
            position, velocity, energy_left, slot_data, takeoff, landing, d_bz, d_nfz, d_rz, d_boundary, d_la)
    b = position.shape[0] if position.dim() else -1
    counts = tuple(m.shape[-1] if m.dim() else -1 for m in (ge_mask, nfz_mask, rz_mask, bz_mask, ou_mask))
    width = obs_width(*counts, extra)
    _require("obs_cpu", zip((*(n for n, _, _ in OBS_INPUTS), "divisor"), (*args, divisor),
                            (*(d for _, d, _ in OBS_INPUTS), torch.float32), _obs_shapes(b, counts, width)))
    c = [x.contiguous() for x in (*args, divisor)]
    out = torch.empty(b, width)
    ptr = [x.data_ptr() for x in c]
    lib.uavlae_obs(b, *counts, _threads(b), *ptr[:18], perception_radius, int(extra), *ptr[18:23], distance_scale,
                   ptr[23], out.data_ptr())
    return out


def _obs_fake(ge_pos, ge_remaining, ge_mask, nfz, nfz_mask, rz, rz_mask, bz, bz_mask, ou_pos, ou_vel, ou_mask,
              position, velocity, energy_left, slot_data, takeoff, landing, d_bz, d_nfz, d_rz, d_boundary, d_la,
              divisor, perception_radius, extra, distance_scale):
    counts = [m.shape[-1] for m in (ge_mask, nfz_mask, rz_mask, bz_mask, ou_mask)]
    return position.new_empty(position.shape[0], obs_width(*counts, extra))


def _register():
    if _STATE["ops"] is None:
        ou = torch.library.custom_op(f"uavlae::ou_step_cpu_{_KEY}", _ou_step_impl, mutates_args=())
        ou.register_fake(_ou_step_fake)
        serve = torch.library.custom_op(f"uavlae::serve_cpu_{_KEY}", _serve_impl, mutates_args=())
        serve.register_fake(_serve_fake)
        obs = torch.library.custom_op(f"uavlae::obs_cpu_{_KEY}", _obs_impl, mutates_args=())
        obs.register_fake(_obs_fake)
        _STATE["ops"] = (ou, serve, obs)
    return _STATE["ops"]


ou_step_cpu, serve_cpu, obs_cpu = _register()
