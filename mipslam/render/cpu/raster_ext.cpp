// mipslam CPU rasterizer: tile binning, depth sort, SIMD footprint evaluation and front-to-back
// compositing of projected Gaussians, forward and hand-written backward, and the fused projection of
// projection.h (docs/renderer_cpu.md). A plain C++ shared library with a C interface (end of this file),
// loaded with ctypes by mipslam/render/cpu/library.py; it uses no torch or Python headers, so it compiles
// in seconds and the package builds without torch (mipslam/render/cpu/build.py).
//
// Parallelism: OpenMP over 16x16 tiles (dynamic schedule). Each (Gaussian, tile) pair writes its
// gradient to its own record; records are summed per Gaussian in a fixed (tile) order afterwards, so
// the backward has no atomics and its result does not depend on the thread count or the schedule.
// SIMD: inside a tile a Gaussian is evaluated on the 8-pixel row segments its pixel box touches
// (vectors of simd_math.h; the channel count C is a template parameter, never a runtime loop bound in
// the pixel loop).
#include "check.h"

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <limits>
#include <memory>
#include <vector>

#include "direct_align.h"
#include "feature_match.h"
#include "footprint_simd.h"
#include "projection.h"
#include "rgbd_loss.h"
#include "simd_math.h"
#include "ssim_loss.h"

#ifdef _OPENMP
#include <omp.h>
#endif

namespace mipslam_cpu {

constexpr int TILE = 16;
constexpr int BLOCKS_PER_ROW = TILE / LANES;
constexpr int NV = TILE * BLOCKS_PER_ROW;  // vectors per tile

// The drawn Gaussians in depth order (index m), and the (tile, Gaussian) pairs.
struct Scene {
    int width, height, tiles_x, tiles_y, channels;
    Settings settings;
    const Gauss* gauss;           // [M] depth-sorted (stable), so a tile's list reads them in increasing order
    const float* colors;          // [M, C] same order
    const int32_t* tile_offsets;  // [tiles + 1]
    const int32_t* isect_ids;     // [P] sorted index m of each pair, tile-major, front to back within a tile
};

// ---------------------------------------------------------------------------------------------
// Per-Gaussian set-up and pixel box
// ---------------------------------------------------------------------------------------------
static bool pixel_range(double centre, double ext, int size, int32_t* lo, int32_t* hi) {
    const double a = std::ceil(centre - ext), b = std::floor(centre + ext);
    if (!(b >= 0.0) || !(a <= size - 1.0) || !(a <= b)) return false;
    *lo = (int32_t)std::max(a, 0.0);
    *hi = (int32_t)std::min(b, size - 1.0);
    return true;
}

static Gauss setup_gaussian(int mode, float k, const float* mean, const float* cov, float opacity, float depth,
                            int32_t nodes, int width, int height, bool* drawn) {
    Gauss g{};
    g.mx = mean[0];
    g.my = mean[1];
    g.xx = cov[0];
    g.xy = cov[1];
    g.yy = cov[2];
    g.det = cov[3];
    g.opacity = opacity;
    g.depth = depth;
    g.nodes = mode == MODE_EAA ? nodes : 1;
    g.px0 = g.py0 = 0;
    g.px1 = g.py1 = -1;
    *drawn = false;
    const bool finite = std::isfinite(g.mx) && std::isfinite(g.my) && std::isfinite(g.xx) && std::isfinite(g.xy) &&
                        std::isfinite(g.yy) && std::isfinite(g.det) && std::isfinite(opacity) &&
                        std::isfinite(depth);
    // a <= opacity in every mode, so a Gaussian below 1/255 never passes the compositing cut.
    if (!finite || !(opacity >= ALPHA_MIN) || !(g.xx > 0.f) || !(g.yy > 0.f) || !(g.det > 0.f)) return g;
    g.ca = g.yy / g.det;
    g.cb = -g.xy / g.det;
    g.cc = g.xx / g.det;
    g.qa = -0.5f * LOG2E * g.ca;
    g.qb = -0.5f * LOG2E * g.cb;
    g.qc = -0.5f * LOG2E * g.cc;
    g.outer_y = g.yy >= g.xx ? 1 : 0;
    g.var_o = g.outer_y ? g.yy : g.xx;
    const float var_i = g.outer_y ? g.xx : g.yy;
    g.mu_o = g.outer_y ? g.my : g.mx;
    g.mu_i = g.outer_y ? g.mx : g.my;
    g.sigma_o = std::sqrt(g.var_o);
    g.inv_sigma_o = 1.f / g.sigma_o;
    g.slope = g.xy / g.var_o;
    g.s = std::sqrt(g.det / g.var_o);
    g.inv_s = 1.f / g.s;
    g.inner_lim = k * std::sqrt(var_i) + 0.5f;
    if (!(std::isfinite(g.ca) && std::isfinite(g.cb) && std::isfinite(g.cc) && std::isfinite(g.inv_s) &&
          std::isfinite(g.inv_sigma_o) && std::isfinite(g.slope) && g.s > 0.f))
        return g;
    // Conservative pixel box: every pixel outside it has a < 1/255 (or is cut) in the torch reference.
    // Centre sample: a = o exp(-maha/2) and maha >= dx^2 / Sxx, so a >= 1/255 needs dx^2 <= 2 ln(255 o) Sxx.
    // Box modes: a <= o max_pixel G <= o exp(-(|dx| - 1/2)^2 / (2 Sxx)) along each axis.
    const double k_alpha2 = std::max(0.0, 2.0 * std::log(255.0 * (double)opacity));
    double ext_x, ext_y;
    if (mode == MODE_CENTRE || (mode == MODE_EAA && g.nodes <= 1)) {
        const double kk = std::min((double)k * k, k_alpha2) * (1.0 + 1e-4) + 1e-3;
        ext_x = std::sqrt(kk * g.xx);
        ext_y = std::sqrt(kk * g.yy);
    } else if (mode == MODE_EAA) {
        const double k_outer = std::min((double)k, std::sqrt(k_alpha2));
        const double ext_o = k_outer * g.sigma_o + 0.5, ext_i = (double)k * std::sqrt((double)var_i) + 0.5;
        ext_x = g.outer_y ? ext_i : ext_o;
        ext_y = g.outer_y ? ext_o : ext_i;
    } else {
        const double k_box = std::min((double)EXACT_K, std::sqrt(k_alpha2));
        ext_x = k_box * std::sqrt((double)g.xx) + 0.5;
        ext_y = k_box * std::sqrt((double)g.yy) + 0.5;
    }
    ext_x = ext_x * (1.0 + 1e-4) + 1e-3;
    ext_y = ext_y * (1.0 + 1e-4) + 1e-3;
    if (!pixel_range(g.mx, ext_x, width, &g.px0, &g.px1) || !pixel_range(g.my, ext_y, height, &g.py0, &g.py1)) {
        g.px0 = g.py0 = 0;
        g.px1 = g.py1 = -1;
        return g;
    }
    *drawn = true;
    return g;
}

// ---------------------------------------------------------------------------------------------
// Forward
// ---------------------------------------------------------------------------------------------
static inline vf lane_offsets() {
    vf v;
    for (int i = 0; i < LANES; ++i) v[i] = (float)i;
    return v;
}

// The Gaussians of a tile list are scattered over the depth-sorted array (L2 misses): fetch ahead.
constexpr int PREFETCH_DISTANCE = 6;
static inline __attribute__((always_inline)) void prefetch_pair(const Scene& sc, int32_t m, int channels) {
    if (m < 0) return;
    const char* g = reinterpret_cast<const char*>(sc.gauss + m);
    __builtin_prefetch(g);
    __builtin_prefetch(g + 64);
    __builtin_prefetch(sc.colors + (int64_t)m * channels);
}

template <int MODE>
static inline __attribute__((always_inline)) bool uses_centre(const Gauss& g) {
    return MODE == MODE_CENTRE || (MODE == MODE_EAA && g.nodes <= 1);
}

// EAA Gaussians whose outer axis is x are evaluated in column segments (8 consecutive y at one x), where
// the outer quantities are constant along the vector, then transposed 8x8 into the tile's row layout.
template <int MODE>
static inline __attribute__((always_inline)) bool uses_columns(const Gauss& g) {
    return MODE == MODE_EAA && g.nodes >= 2 && g.nodes <= LINE_ROWS && !g.outer_y;
}

// The one traversal of a Gaussian's pixel box inside the tile at (x0, y0), shared by the forward and the
// backward so that both visit the same pixels in the same order. Returns false when the box misses the tile.
//   Row segments (every path but EAA with outer axis x): rows [ra, rb] and 8-pixel blocks [b0, b1] of the
//   box, taken in pairs of rows (two independent pixel vectors per iteration) and an odd last row alone:
//     pair(v0, px, py0, py1, &ready0, &ready1)  segments v0 (row py0) and v0 + BLOCKS_PER_ROW (row py0 + 1)
//     single(v, px, py, &ready)                 the odd last row
//   `ready`: the EAA row state of that image row is set (eval_footprint); px holds the segment's x.
//   Column blocks (EAA with outer axis x, uses_columns): 8x8 blocks of the box,
//     block(R, b, rr0, rr1, cc0, cc1, py_lanes)  rows [rr0, rr1] and columns [cc0, cc1] (tile coordinates)
//     of block row R and block column b; py_lanes = the y of the block's 8 rows.
//   rows_done(ra, rb, b0, b1) is called after the row segments (the forward counts lanes there).
template <int MODE, typename Pair, typename Single, typename Block, typename RowsDone>
static inline __attribute__((always_inline)) bool traverse_box(const Gauss& g, int x0, int y0, vf lane, Pair&& pair,
                                                               Single&& single, Block&& block,
                                                               RowsDone&& rows_done) {
    const int r0 = std::max(g.py0 - y0, 0), r1 = std::min(g.py1 - y0, TILE - 1);
    const int c0 = std::max(g.px0 - x0, 0), c1 = std::min(g.px1 - x0, TILE - 1);
    if (r0 > r1 || c0 > c1) return false;
    if (uses_columns<MODE>(g)) {
        for (int R = r0 / LANES; R <= r1 / LANES; ++R) {
            const int rr0 = std::max(r0, R * LANES), rr1 = std::min(r1, R * LANES + LANES - 1);
            const vf py_lanes = splat((float)(y0 + R * LANES)) + lane;
            for (int b = c0 / LANES; b <= c1 / LANES; ++b) {
                const int cc0 = std::max(c0, b * LANES), cc1 = std::min(c1, b * LANES + LANES - 1);
                block(R, b, rr0, rr1, cc0, cc1, py_lanes);
            }
        }
        return true;
    }
    const int b0 = c0 / LANES, b1 = c1 / LANES;
    int r = r0;
    for (; r < r1; r += 2) {
        const float py0 = (float)(y0 + r), py1 = py0 + 1.f;
        bool ready0 = false, ready1 = false;
        for (int b = b0; b <= b1; ++b)
            pair(r * BLOCKS_PER_ROW + b, splat((float)(x0 + b * LANES)) + lane, py0, py1, &ready0, &ready1);
    }
    if (r == r1) {  // odd last row
        bool ready0 = false;
        for (int b = b0; b <= b1; ++b)
            single(r * BLOCKS_PER_ROW + b, splat((float)(x0 + b * LANES)) + lane, (float)(y0 + r), &ready0);
    }
    rows_done(r0, r1, b0, b1);
    return true;
}

// Footprint of one 8-pixel row segment. `row_ready`: the EAA state already holds this image row's
// constants (set by the first segment of the row the Gaussian evaluates in this tile; the others reuse
// them: EAA with outer axis y).
template <int MODE>
static inline __attribute__((always_inline)) vf eval_footprint(const Gauss& g, const Settings& S, float k2, vf px,
                                                               float py, CentrePixel* cp, EaaPixel* ep,
                                                               ExactPixel* xp, bool* row_ready) {
    if (uses_centre<MODE>(g)) return centre_eval(g, k2, px, py, cp);
    if (MODE == MODE_EAA) {
        if (!g.outer_y) return eaa_eval(g, S, px, py, ep);
        if (!*row_ready) {
            eaa_outer_y_row(g, S, py, ep);
            *row_ready = true;
        }
        return eaa_outer_y_segment(g, S, px, ep);
    }
    return exact_eval(g, S, px, py, xp);
}

// One tile, Gaussian by Gaussian (front to back) over the 8-pixel row segments of its box; the tile's
// transmittance and sums live in small arrays (L1).
template <int C, int MODE>
static int64_t forward_tile(const Scene& sc, int tile, float* out_color, float* out_depth, float* out_alpha,
                            int32_t* out_last) {
    const int x0 = (tile % sc.tiles_x) * TILE, y0 = (tile / sc.tiles_x) * TILE;
    const Settings& S = sc.settings;
    const float k2 = S.k_sigma * S.k_sigma;
    vf T[NV], acc_d[NV], acc_a[NV], acc_c[C][NV];
    vi last[NV];
    for (int v = 0; v < NV; ++v) {
        T[v] = splat(1.f);
        acc_d[v] = acc_a[v] = splat(0.f);
        for (int c = 0; c < C; ++c) acc_c[c][v] = splat(0.f);
        last[v] = splati(0);
    }
    const vf lane = lane_offsets();
    const int32_t begin = sc.tile_offsets[tile], end = sc.tile_offsets[tile + 1];
    int64_t lanes = 0;
    CentrePixel cp0, cp1;
    EaaPixel ep0, ep1;
    ExactPixel xp0, xp1;
    EaaLineState<LINE_ROWS> lp;
    for (int32_t j = begin; j < end; ++j) {
        prefetch_pair(sc, j + PREFETCH_DISTANCE < end ? sc.isect_ids[j + PREFETCH_DISTANCE] : -1, C);
        const int32_t m = sc.isect_ids[j];
        const Gauss& g = sc.gauss[m];
        const vi slot = splati(j - begin + 1);
        vf col[C];
        for (int c = 0; c < C; ++c) col[c] = splat(sc.colors[(int64_t)m * C + c]);
        const vf z = splat(g.depth);
        // alpha = min(0.99, a), skipped below 1/255; a pixel stops at the first Gaussian that would leave
        // T < 1e-4 (that one does not contribute); a stopped pixel keeps T = 0.
        auto composite = [&](int v, vf a) __attribute__((always_inline)) {
            const vi valid = a >= splat(ALPHA_MIN);
            const vf t = T[v];
            const vf w = keep(valid, vmin(a, splat(ALPHA_MAX)) * t);
            const vf tn = t - w;
            const vi ok = tn >= splat(TRANSMITTANCE_MIN);
            const vf wc = keep(ok, w);
            for (int c = 0; c < C; ++c) acc_c[c][v] += wc * col[c];
            acc_d[v] += wc * z;
            acc_a[v] += wc;
            T[v] = select(valid, keep(ok, tn), t);
            last[v] = selecti(valid & ok, slot, last[v]);
        };
        auto pair = [&](int v0, vf px, float py0, float py1, bool* ready0, bool* ready1)
                        __attribute__((always_inline)) {
            const vf a0 = eval_footprint<MODE>(g, S, k2, px, py0, &cp0, &ep0, &xp0, ready0);
            const vf a1 = eval_footprint<MODE>(g, S, k2, px, py1, &cp1, &ep1, &xp1, ready1);
            composite(v0, a0);
            composite(v0 + BLOCKS_PER_ROW, a1);
        };
        auto single = [&](int v, vf px, float py, bool* ready) __attribute__((always_inline)) {
            composite(v, eval_footprint<MODE>(g, S, k2, px, py, &cp0, &ep0, &xp0, ready));
        };
        auto block = [&](int R, int b, int rr0, int rr1, int cc0, int cc1, vf py_lanes)
                         __attribute__((always_inline)) {
            vf cols[LANES], rows[LANES];
            for (int i = 0; i < LANES; ++i) {
                const int cx = b * LANES + i;
                cols[i] = (cx < cc0 || cx > cc1) ? splat(0.f)
                                                 : eaa_eval_outer_y(g, S, py_lanes, (float)(x0 + cx), &lp);
            }
            transpose8(cols, rows);
            for (int r = rr0; r <= rr1; ++r) composite(r * BLOCKS_PER_ROW + b, rows[r - R * LANES]);
            lanes += (int64_t)(cc1 - cc0 + 1) * LANES;
        };
        auto rows_done = [&](int ra, int rb, int b0, int b1) __attribute__((always_inline)) {
            lanes += (int64_t)(rb - ra + 1) * (b1 - b0 + 1) * LANES;
        };
        if (!traverse_box<MODE>(g, x0, y0, lane, pair, single, block, rows_done)) continue;
        if (((j - begin) & 15) == 15) {  // the whole tile saturated: nothing behind can show
            vi alive = splati(0);
            for (int v = 0; v < NV; ++v) alive |= T[v] > splat(0.f);
            if (!any_lane(alive)) break;
        }
    }
    for (int r = 0; r < TILE; ++r) {
        const int y = y0 + r;
        if (y >= sc.height) break;
        for (int b = 0; b < BLOCKS_PER_ROW; ++b) {
            const int v = r * BLOCKS_PER_ROW + b;
            for (int i = 0; i < LANES; ++i) {
                const int x = x0 + b * LANES + i;
                if (x >= sc.width) break;
                const int64_t p = (int64_t)y * sc.width + x;
                for (int c = 0; c < C; ++c) out_color[p * C + c] = acc_c[c][v][i];
                out_depth[p] = acc_d[v][i];
                out_alpha[p] = acc_a[v][i];
                out_last[p] = last[v][i];
            }
        }
    }
    return lanes;
}

// ---------------------------------------------------------------------------------------------
// Backward
// ---------------------------------------------------------------------------------------------
struct GradInputs {
    const float* grad_color;  // [H, W, C]
    const float* grad_depth;  // [H, W]
    const float* grad_alpha;  // [H, W]
    // [H, W, C] or null: a colour gradient that reaches the Gaussians' colours only (an appearance loss whose
    // gradient must not move the geometry); the colours take grad_color + this
    const float* grad_color_appearance;
    const float* color;       // forward outputs
    const float* depth;
    const float* alpha;
    const int32_t* last;      // [H, W] 1 + index (in the tile list) of the last contributing Gaussian
};

template <int MODE, bool GO>
static inline __attribute__((always_inline)) void grad_footprint(const Gauss& g, const Settings& S, float py,
                                                                 const CentrePixel& cp, const EaaPixel& ep,
                                                                 const ExactPixel& xp, vf ga, FootAcc* acc) {
    if (uses_centre<MODE>(g))
        centre_grad<GO>(g, py, cp, ga, acc);
    else if (MODE == MODE_EAA)
        eaa_grad<GO>(g, S, ep, ga, acc);
    else
        exact_grad<GO>(g, S, xp, ga, acc);
}

// Record of one (tile, Gaussian) pair: d/d(mx, my, xx, xy, yy, det, opacity, depth, colour[C]).
template <int C, int MODE, bool GC, bool GO>
static void backward_tile(const Scene& sc, int tile, const GradInputs& gin, float* records) {
    constexpr int REC = 8 + C;
    const int x0 = (tile % sc.tiles_x) * TILE, y0 = (tile / sc.tiles_x) * TILE;
    const Settings& S = sc.settings;
    const float k2 = S.k_sigma * S.k_sigma;
    vf gcol[C][NV], gcol_colors[C][NV], gdep[NV], galp[NV], stot[NV], T[NV], prefix[NV];
    vi last[NV];
    for (int r = 0; r < TILE; ++r) {
        for (int b = 0; b < BLOCKS_PER_ROW; ++b) {
            const int v = r * BLOCKS_PER_ROW + b;
            for (int i = 0; i < LANES; ++i) {
                const int x = x0 + b * LANES + i, y = y0 + r;
                float gd = 0.f, gal = 0.f, st = 0.f, gc[C] = {}, gca[C] = {};
                int32_t la = 0;
                if (x < sc.width && y < sc.height) {
                    const int64_t p = (int64_t)y * sc.width + x;
                    gd = gin.grad_depth[p];
                    gal = gin.grad_alpha[p];
                    st = gd * gin.depth[p] + gal * gin.alpha[p];
                    for (int c = 0; c < C; ++c) {
                        gc[c] = gin.grad_color[p * C + c];
                        st += gc[c] * gin.color[p * C + c];
                    }
                    if (GC && gin.grad_color_appearance != nullptr)
                        for (int c = 0; c < C; ++c) gca[c] = gin.grad_color_appearance[p * C + c];
                    la = gin.last[p];
                    // a pixel without incoming gradient (masked out of the loss) contributes nothing: skip it
                    bool any = gd != 0.f || gal != 0.f;
                    for (int c = 0; c < C; ++c) any = any || gc[c] != 0.f || gca[c] != 0.f;
                    if (!any) la = 0;
                }
                gdep[v][i] = gd;
                galp[v][i] = gal;
                stot[v][i] = st;
                for (int c = 0; c < C; ++c) gcol[c][v][i] = gc[c];
                // without an appearance gradient the colours take grad_color itself (the same bits)
                if (GC)
                    for (int c = 0; c < C; ++c)
                        gcol_colors[c][v][i] = gin.grad_color_appearance != nullptr ? gc[c] + gca[c] : gc[c];
                last[v][i] = la;
            }
            T[v] = splat(1.f);
            prefix[v] = splat(0.f);
        }
    }
    vi lmax = last[0];
    for (int v = 1; v < NV; ++v) lmax = last[v] > lmax ? last[v] : lmax;
    const int32_t begin = sc.tile_offsets[tile], end = sc.tile_offsets[tile + 1];
    const int32_t stop = begin + std::min<int32_t>(hmax_i(lmax), end - begin);
    const vf lane = lane_offsets();
    CentrePixel cp0, cp1;
    EaaPixel ep0, ep1;
    ExactPixel xp0, xp1;
    EaaLineState<LINE_ROWS> lines[LANES];
    for (int32_t j = begin; j < stop; ++j) {
        prefetch_pair(sc, j + PREFETCH_DISTANCE < stop ? sc.isect_ids[j + PREFETCH_DISTANCE] : -1, C);
        const int32_t m = sc.isect_ids[j];
        const Gauss& g = sc.gauss[m];
        const vi slot = splati(j - begin);
        vf col[C];
        for (int c = 0; c < C; ++c) col[c] = splat(sc.colors[(int64_t)m * C + c]);
        const vf z = splat(g.depth);
        FootAcc acc;
        acc.zero();
        vf acc_c[C], acc_d = splat(0.f);
        for (int c = 0; c < C; ++c) acc_c[c] = splat(0.f);
        // Compositing part of the backward for one row segment with footprint a: returns dL/da (0 where the
        // pixel does not take this Gaussian) and advances T and the prefix sum.
        auto composite_grad = [&](int v, vi listed, vf a) __attribute__((always_inline)) {
            const vi valid = listed & (a >= splat(ALPHA_MIN));
            if (!any_lane(valid)) return splat(0.f);
            const vf al = vmin(a, splat(ALPHA_MAX));
            vf s = gdep[v] * z + galp[v];
            for (int c = 0; c < C; ++c) s += gcol[c][v] * col[c];
            const vf t = T[v];
            const vf w = keep(valid, al * t);
            prefix[v] += w * s;
            // d out / d alpha_i = T_i s_i - (sum_{j > i} w_j s_j) / (1 - alpha_i)
            const vf dal = t * s - (stot[v] - prefix[v]) / (splat(1.f) - al);
            T[v] = t - w;
            if (GC)
                for (int c = 0; c < C; ++c) acc_c[c] += w * gcol_colors[c][v];
            acc_d += w * gdep[v];
            return keep(valid & (a <= splat(ALPHA_MAX)), dal);
        };
        auto process = [&](int v, vf px, float py, CentrePixel* cp, EaaPixel* ep, ExactPixel* xp, bool* ready)
                           __attribute__((always_inline)) {
            const vi listed = slot < last[v];
            if (!any_lane(listed)) return;
            const vf a = eval_footprint<MODE>(g, S, k2, px, py, cp, ep, xp, ready);
            const vf ga = composite_grad(v, listed, a);
            if (!any_lane(ga != splat(0.f))) return;
            grad_footprint<MODE, GO>(g, S, py, *cp, *ep, *xp, ga, &acc);
        };
        auto pair = [&](int v0, vf px, float py0, float py1, bool* ready0, bool* ready1)
                        __attribute__((always_inline)) {
            process(v0, px, py0, &cp0, &ep0, &xp0, ready0);
            process(v0 + BLOCKS_PER_ROW, px, py1, &cp1, &ep1, &xp1, ready1);
        };
        auto single = [&](int v, vf px, float py, bool* ready) __attribute__((always_inline)) {
            process(v, px, py, &cp0, &ep0, &xp0, ready);
        };
        auto block = [&](int R, int b, int rr0, int rr1, int cc0, int cc1, vf py_lanes)
                         __attribute__((always_inline)) {
            vi listed_any = splati(0);
            for (int r = rr0; r <= rr1; ++r) listed_any |= slot < last[r * BLOCKS_PER_ROW + b];
            if (!any_lane(listed_any)) return;
            vf cols[LANES], rows[LANES], ga_rows[LANES], ga_cols[LANES];
            for (int i = 0; i < LANES; ++i) {
                const int cx = b * LANES + i;
                cols[i] = (cx < cc0 || cx > cc1) ? splat(0.f)
                                                 : eaa_eval_outer_y(g, S, py_lanes, (float)(x0 + cx), &lines[i]);
            }
            transpose8(cols, rows);
            for (int r = 0; r < LANES; ++r) ga_rows[r] = splat(0.f);
            for (int r = rr0; r <= rr1; ++r) {
                const int v = r * BLOCKS_PER_ROW + b;
                ga_rows[r - R * LANES] = composite_grad(v, slot < last[v], rows[r - R * LANES]);
            }
            transpose8(ga_rows, ga_cols);
            for (int i = cc0 - b * LANES; i <= cc1 - b * LANES; ++i)
                eaa_grad_outer_y<GO>(g, S, lines[i], ga_cols[i], &acc);
        };
        if (!traverse_box<MODE>(g, x0, y0, lane, pair, single, block, [](int, int, int, int) {})) {
            for (int q = 0; q < REC; ++q) records[(int64_t)j * REC + q] = 0.f;
            continue;
        }
        float sums[6] = {hsum(acc.g0), hsum(acc.g1), hsum(acc.g2), hsum(acc.g3), hsum(acc.g4), hsum(acc.go)};
        float* rec = records + (int64_t)j * REC;
        if (uses_centre<MODE>(g))
            centre_finalize(g, sums, rec);
        else
            rows_finalize(g, sums, rec);
        rec[7] = hsum(acc_d);
        for (int c = 0; c < C; ++c) rec[8 + c] = GC ? hsum(acc_c[c]) : 0.f;
    }
    for (int32_t j = stop; j < end; ++j)
        for (int q = 0; q < REC; ++q) records[(int64_t)j * REC + q] = 0.f;
}

// ---------------------------------------------------------------------------------------------
// Host side: binning, depth sort, the OpenMP tile loops and the deterministic gradient reduction
// ---------------------------------------------------------------------------------------------
struct Inputs {
    const float *means2d, *cov, *opacity, *depth, *colors;  // [N, 2] [N, 4] [N] [N] [N, C]
    const int32_t* node_counts;                             // [N]
    int64_t n, channels;
};

// Depth-sorted drawn Gaussians and their colours. order[m] = input index of sorted Gaussian m.
struct Sorted {
    std::unique_ptr<Gauss[]> gauss;  // not zero-filled: every entry is written before it is read
    std::unique_ptr<float[]> colors;
    void allocate(int64_t count, int64_t channels) {
        gauss.reset(new Gauss[(size_t)std::max<int64_t>(count, 1)]);
        colors.reset(new float[(size_t)std::max<int64_t>(count * channels, 1)]);
    }
};

static void setup_all(const Inputs& in, int mode, float k, int width, int height, int threads, Gauss* gs,
                      uint8_t* drawn) {
#pragma omp parallel for schedule(static) num_threads(threads)
    for (int64_t i = 0; i < in.n; ++i) {
        bool d = false;
        gs[i] = setup_gaussian(mode, k, in.means2d + 2 * i, in.cov + 4 * i, in.opacity[i], in.depth[i],
                               in.node_counts[i], width, height, &d);
        drawn[i] = d ? 1 : 0;
    }
}

// Gather the drawn Gaussians (and colours) into depth order: sorted[m] = all[order[m]].
static void gather_sorted(const Inputs& in, const Gauss* all, const int32_t* order, int64_t count, int threads,
                          Sorted* out) {
    out->allocate(count, in.channels);
    Gauss* gs = out->gauss.get();
    float* cs = out->colors.get();
#pragma omp parallel for schedule(static) num_threads(threads)
    for (int64_t m = 0; m < count; ++m) {
        const int64_t i = order[m];
        gs[m] = all[i];
        for (int64_t c = 0; c < in.channels; ++c) cs[m * in.channels + c] = in.colors[i * in.channels + c];
    }
}

// Stable LSD radix sort of (key, value) pairs by the 32-bit key, 8 bits per pass (passes in which every key
// has the same digit are skipped). With the values in increasing order on input, ties stay in that order.
static void radix_sort_pairs(std::vector<uint32_t>* keys, std::vector<int32_t>* values) {
    const size_t n = keys->size();
    if (n < 2) return;
    std::vector<uint32_t> key_tmp(n);
    std::vector<int32_t> value_tmp(n);
    uint32_t *ka = keys->data(), *kb = key_tmp.data();
    int32_t *va = values->data(), *vb = value_tmp.data();
    for (int shift = 0; shift < 32; shift += 8) {
        size_t count[257] = {};
        for (size_t i = 0; i < n; ++i) ++count[((ka[i] >> shift) & 0xffu) + 1];
        if (count[((ka[0] >> shift) & 0xffu) + 1] == n) continue;
        for (int b = 0; b < 256; ++b) count[b + 1] += count[b];
        for (size_t i = 0; i < n; ++i) {
            const size_t d = count[(ka[i] >> shift) & 0xffu]++;
            kb[d] = ka[i];
            vb[d] = va[i];
        }
        std::swap(ka, kb);
        std::swap(va, vb);
    }
    if (ka != keys->data()) {
        std::copy(ka, ka + n, keys->data());
        std::copy(va, va + n, values->data());
    }
}

// The forward between its two calls: the caller learns the sizes (drawn Gaussians, pairs) from
// mipslam_rasterize_bin, allocates the arrays, and mipslam_rasterize_forward fills them and renders.
struct Binning {
    Inputs in;
    int mode, width, height, tiles_x, tiles_y, threads;
    float k_sigma;
    Sorted sorted;
    std::vector<int32_t> order;         // [M] input index of each drawn Gaussian, front to back
    std::vector<int32_t> tile_offsets;  // [tiles + 1]
    std::vector<int32_t> pair_offsets;  // [M + 1] pairs of sorted Gaussian m: isect_pos[pair_offsets[m] ..]
    int64_t pairs = 0;
};

// Depth sort and pair counts (the first half of the binning).
static void bin_gaussians(Binning* b) {
    const Inputs& in = b->in;
    const int64_t n = in.n;
    const int64_t num_tiles = (int64_t)b->tiles_x * b->tiles_y;
    std::unique_ptr<Gauss[]> all(new Gauss[(size_t)std::max<int64_t>(n, 1)]);  // written by setup_all
    std::vector<uint8_t> drawn(n, 0);
    setup_all(in, b->mode, b->k_sigma, b->width, b->height, b->threads, all.get(), drawn.data());
    // Depth order, ties in input order (the torch backend's stable argsort): the depth as an
    // order-preserving unsigned integer, radix-sorted stably with the indices in increasing order.
    // Depths are finite here.
    std::vector<uint32_t> keys;
    std::vector<int32_t>& index = b->order;
    keys.reserve(n);
    index.reserve(n);
    for (int64_t i = 0; i < n; ++i) {
        if (!drawn[i]) continue;
        const float z = in.depth[i] == 0.f ? 0.f : in.depth[i];  // -0 sorts with +0
        uint32_t bits;
        std::memcpy(&bits, &z, sizeof(bits));
        bits = (bits & 0x80000000u) ? ~bits : (bits | 0x80000000u);
        keys.push_back(bits);
        index.push_back((int32_t)i);
    }
    radix_sort_pairs(&keys, &index);
    const int64_t count = (int64_t)index.size();
    gather_sorted(in, all.get(), index.data(), count, b->threads, &b->sorted);
    const Gauss* gs = b->sorted.gauss.get();
    b->pair_offsets.assign(count + 1, 0);
    b->tile_offsets.assign(num_tiles + 1, 0);
    int32_t* poff = b->pair_offsets.data();
    int32_t* toff = b->tile_offsets.data();
    int64_t total = 0;
    for (int64_t m = 0; m < count; ++m) {
        const Gauss& g = gs[m];
        poff[m] = (int32_t)total;
        for (int ty = g.py0 / TILE; ty <= g.py1 / TILE; ++ty)
            for (int tx = g.px0 / TILE; tx <= g.px1 / TILE; ++tx) toff[(int64_t)ty * b->tiles_x + tx + 1] += 1;
        total += (int64_t)(g.px1 / TILE - g.px0 / TILE + 1) * (g.py1 / TILE - g.py0 / TILE + 1);
        MIPSLAM_CHECK(total < (int64_t)std::numeric_limits<int32_t>::max(),
                      "mipslam cpu rasterizer: more than 2^31 (tile, Gaussian) pairs; render at a lower resolution");
    }
    poff[count] = (int32_t)total;
    for (int64_t t = 0; t < num_tiles; ++t) toff[t + 1] += toff[t];
    b->pairs = total;
}

// The tile-major pair list (the second half of the binning): ids [P] sorted index of each pair,
// pos [P] position of each Gaussian's pairs in that list.
static void list_pairs(const Binning& b, int32_t* ids, int32_t* pos) {
    const int64_t count = (int64_t)b.order.size();
    const Gauss* gs = b.sorted.gauss.get();
    std::vector<int32_t> cursor(b.tile_offsets.begin(), b.tile_offsets.end() - 1);
    for (int64_t m = 0; m < count; ++m) {
        const Gauss& g = gs[m];
        int32_t q = b.pair_offsets[m];
        for (int ty = g.py0 / TILE; ty <= g.py1 / TILE; ++ty)
            for (int tx = g.px0 / TILE; tx <= g.px1 / TILE; ++tx) {
                const int32_t p = cursor[(int64_t)ty * b.tiles_x + tx]++;
                ids[p] = (int32_t)m;
                pos[q++] = p;
            }
    }
}

static Settings make_settings(int mode, double k, double eta, double tau, const float* gl_nodes,
                              const float* gl_weights, int64_t exact_order) {
    Settings s;
    s.mode = mode;
    s.k_sigma = (float)k;
    s.eta = (float)eta;
    s.tau = (float)tau;
    s.exact_order = (int)exact_order;
    s.gl_nodes = gl_nodes;
    s.gl_weights = gl_weights;
    return s;
}

static void check_settings(const Inputs& in, int64_t mode, int64_t width, int64_t height) {
    MIPSLAM_CHECK(mode >= 0 && mode <= 2, "mipslam cpu rasterizer: unknown mode ", mode);
    MIPSLAM_CHECK(width >= 1 && height >= 1 && width <= (1 << 24) && height <= (1 << 24),
                  "mipslam cpu rasterizer: image size must be in [1, 2^24]");
    MIPSLAM_CHECK(in.channels == 1 || in.channels == 3 || in.channels == 4,
                  "mipslam cpu rasterizer: colour channels must be 1, 3 or 4, got ", in.channels);
    if (mode == MODE_EAA)
        for (int64_t i = 0; i < in.n; ++i)
            MIPSLAM_CHECK(in.node_counts[i] >= 1 && in.node_counts[i] <= MAX_ROWS,
                          "mipslam cpu rasterizer: EAA node counts must be in [1, ", MAX_ROWS, "]");
}

template <int C>
static int64_t run_forward(const Scene& sc, int threads, float* color, float* depth, float* alpha, int32_t* last) {
    const int num_tiles = sc.tiles_x * sc.tiles_y;
    int64_t lanes = 0;
#pragma omp parallel for schedule(dynamic, 1) num_threads(threads) reduction(+ : lanes)
    for (int t = 0; t < num_tiles; ++t) {
        if (sc.settings.mode == MODE_CENTRE)
            lanes += forward_tile<C, MODE_CENTRE>(sc, t, color, depth, alpha, last);
        else if (sc.settings.mode == MODE_EAA)
            lanes += forward_tile<C, MODE_EAA>(sc, t, color, depth, alpha, last);
        else
            lanes += forward_tile<C, MODE_EXACT>(sc, t, color, depth, alpha, last);
    }
    return lanes;
}

template <int C, int MODE, bool GC, bool GO>
static void run_backward_mode(const Scene& sc, int threads, const GradInputs& gin, float* records) {
    const int num_tiles = sc.tiles_x * sc.tiles_y;
#pragma omp parallel for schedule(dynamic, 1) num_threads(threads)
    for (int t = 0; t < num_tiles; ++t) backward_tile<C, MODE, GC, GO>(sc, t, gin, records);
}

template <int C, bool GC, bool GO>
static void run_backward_flags(const Scene& sc, int threads, const GradInputs& gin, float* records) {
    if (sc.settings.mode == MODE_CENTRE)
        run_backward_mode<C, MODE_CENTRE, GC, GO>(sc, threads, gin, records);
    else if (sc.settings.mode == MODE_EAA)
        run_backward_mode<C, MODE_EAA, GC, GO>(sc, threads, gin, records);
    else
        run_backward_mode<C, MODE_EXACT, GC, GO>(sc, threads, gin, records);
}

template <int C>
static void run_backward(const Scene& sc, int threads, const GradInputs& gin, float* records, bool gc, bool go) {
    if (gc && go)
        run_backward_flags<C, true, true>(sc, threads, gin, records);
    else if (gc)
        run_backward_flags<C, true, false>(sc, threads, gin, records);
    else if (go)
        run_backward_flags<C, false, true>(sc, threads, gin, records);
    else
        run_backward_flags<C, false, false>(sc, threads, gin, records);
}

// C (1, 3 or 4 colour channels, checked by check_settings) as a compile-time constant CH in CALL.
#define MIPSLAM_DISPATCH_CHANNELS(C_VALUE, CALL)          \
    switch (C_VALUE) {                                    \
        case 1: { constexpr int CH = 1; CALL; break; }    \
        case 3: { constexpr int CH = 3; CALL; break; }    \
        case 4: { constexpr int CH = 4; CALL; break; }    \
        default: break;                                   \
    }

static void rasterize_forward(Binning* b, const Settings& settings, int32_t* order, int32_t* tile_offsets,
                              int32_t* isect_ids, int32_t* pair_offsets, int32_t* isect_pos, float* color,
                              float* depth, float* alpha, int32_t* last, int64_t* stats) {
    std::copy(b->order.begin(), b->order.end(), order);
    std::copy(b->tile_offsets.begin(), b->tile_offsets.end(), tile_offsets);
    std::copy(b->pair_offsets.begin(), b->pair_offsets.end(), pair_offsets);
    list_pairs(*b, isect_ids, isect_pos);
    const int C = (int)b->in.channels;
    Scene sc{b->width, b->height, b->tiles_x, b->tiles_y, C, settings, b->sorted.gauss.get(),
             b->sorted.colors.get(), tile_offsets, isect_ids};
    int64_t lanes = 0;
    // every pixel is written by forward_tile
    MIPSLAM_DISPATCH_CHANNELS(C, lanes = run_forward<CH>(sc, b->threads, color, depth, alpha, last));
    stats[0] = lanes;
    stats[1] = b->pairs;
}

// The state the forward returned (ord [M], tile_offsets, isect_ids [P], pair_offsets [M + 1], isect_pos [P],
// last [H, W]) and the incoming gradients -> d/d means2d [N, 2], cov [N, 4], opacity [N], depth [N],
// colors [N, C] (zero-filled by the caller; rows of Gaussians that were not drawn stay zero).
static void rasterize_backward(const Inputs& in, int mode, int width, int height, const Settings& settings,
                               const int32_t* ord, int64_t count, const int32_t* tile_offsets,
                               const int32_t* isect_ids, int64_t total, const int32_t* poff, const int32_t* ip,
                               const GradInputs& gin, bool need_color_grad, bool need_opacity_grad, int threads,
                               float* gm, float* gc, float* go, float* gd, float* gcol) {
    const int64_t n = in.n, C = in.channels;
    const int tiles_x = (width + TILE - 1) / TILE, tiles_y = (height + TILE - 1) / TILE;
    for (int64_t m = 0; m < count; ++m)
        MIPSLAM_CHECK(ord[m] >= 0 && ord[m] < n, "mipslam cpu rasterizer: corrupt backward state (order)");
    Sorted sorted;  // identical to the forward's (same inputs, same arithmetic)
    sorted.allocate(count, C);
    {
        Gauss* gs = sorted.gauss.get();
        float* cs = sorted.colors.get();
#pragma omp parallel for schedule(static) num_threads(threads)
        for (int64_t m = 0; m < count; ++m) {
            const int64_t i = ord[m];
            bool drawn = false;
            gs[m] = setup_gaussian(mode, settings.k_sigma, in.means2d + 2 * i, in.cov + 4 * i, in.opacity[i],
                                   in.depth[i], in.node_counts[i], width, height, &drawn);
            for (int64_t c = 0; c < C; ++c) cs[m * C + c] = in.colors[i * C + c];
        }
    }
    Scene sc{width, height, tiles_x, tiles_y, (int)C, settings, sorted.gauss.get(), sorted.colors.get(),
             tile_offsets, isect_ids};
    const int64_t rec = 8 + C;
    // every record is written by backward_tile (zeros for pairs it skips)
    std::unique_ptr<float[]> records(new float[(size_t)std::max<int64_t>(total * rec, 1)]);
    MIPSLAM_DISPATCH_CHANNELS(C, run_backward<CH>(sc, threads, gin, records.get(), need_color_grad,
                                                  need_opacity_grad));
    // Deterministic reduction: each Gaussian sums its pairs in tile order (no atomics, and the
    // result does not depend on the number of threads or on the schedule).
    const float* rp = records.get();
#pragma omp parallel for schedule(static) num_threads(threads)
    for (int64_t m = 0; m < count; ++m) {
        float acc[8 + 4] = {};
        for (int32_t q = poff[m]; q < poff[m + 1]; ++q) {
            const float* r = rp + (int64_t)ip[q] * rec;
            for (int64_t e = 0; e < rec; ++e) acc[e] += r[e];
        }
        const int64_t i = ord[m];
        gm[2 * i] = acc[0];
        gm[2 * i + 1] = acc[1];
        gc[4 * i] = acc[2];
        gc[4 * i + 1] = acc[3];
        gc[4 * i + 2] = acc[4];
        gc[4 * i + 3] = acc[5];
        go[i] = acc[6];
        gd[i] = acc[7];
        for (int64_t c = 0; c < C; ++c) gcol[i * C + c] = acc[8 + c];
    }
}

}  // namespace mipslam_cpu

// ---------------------------------------------------------------------------------------------
// C interface (loaded with ctypes by mipslam/render/cpu/library.py)
// ---------------------------------------------------------------------------------------------
// Every array is a contiguous CPU array the caller allocated (the Python side checks shapes and dtypes).
// Functions that can fail return 0 on success, MIPSLAM_ERR_VALUE for an invalid value from the caller,
// MIPSLAM_ERR_RUNTIME for another failure and MIPSLAM_ERR_MEMORY when an allocation failed, with the message
// in err[err_len].
#define MIPSLAM_API extern "C" __attribute__((visibility("default")))

namespace {

enum ErrorCode : int { MIPSLAM_OK = 0, MIPSLAM_ERR_VALUE = 1, MIPSLAM_ERR_RUNTIME = 2, MIPSLAM_ERR_MEMORY = 3 };

void write_message(char* err, int64_t err_len, const char* message) {
    if (err == nullptr || err_len <= 0) return;
    std::strncpy(err, message, (size_t)err_len - 1);
    err[err_len - 1] = '\0';
}

template <typename F>
int guarded(char* err, int64_t err_len, F&& body) {
    try {
        body();
        return MIPSLAM_OK;
    } catch (const std::invalid_argument& e) {
        write_message(err, err_len, e.what());
        return MIPSLAM_ERR_VALUE;
    } catch (const std::bad_alloc&) {
        write_message(err, err_len, "mipslam cpu rasterizer: out of memory");
        return MIPSLAM_ERR_MEMORY;
    } catch (const std::exception& e) {
        write_message(err, err_len, e.what());
        return MIPSLAM_ERR_RUNTIME;
    }
}

}  // namespace

#ifndef MIPSLAM_SOURCE_HASH
#define MIPSLAM_SOURCE_HASH "unknown"
#endif

// Bumped whenever a signature below changes (library.py refuses a library of another version).
MIPSLAM_API int mipslam_abi_version(void) { return 8; }

// Hash of the sources and flags the library was built from (mipslam/render/cpu/build.py, source_hash), also
// readable from the file without loading it (the marker).
static const char source_tag[] __attribute__((used)) = "mipslam-source-hash:" MIPSLAM_SOURCE_HASH;
MIPSLAM_API const char* mipslam_source_hash(void) { return source_tag + sizeof("mipslam-source-hash:") - 1; }

MIPSLAM_API const char* mipslam_build_info(void) {
    static const char info[] =
#ifdef __AVX2__
        "avx2 "
#endif
#ifdef __FMA__
        "fma "
#endif
#ifdef __SSE2__
        "sse2 "
#endif
#ifdef _OPENMP
        "openmp";
#else
        "no-openmp";
#endif
    return info;
}

// 1 if this CPU runs AVX2 and FMA code (the loader then prefers the avx2 build of the library).
MIPSLAM_API int mipslam_cpu_supports_avx2_fma(void) {
#if defined(__x86_64__) || defined(__i386__)
    __builtin_cpu_init();
    return __builtin_cpu_supports("avx2") && __builtin_cpu_supports("fma") ? 1 : 0;
#else
    return 0;
#endif
}

// First half of the forward: set-up, depth sort and pair counts. *state receives the binning (release it
// with mipslam_rasterize_release), *count the number of drawn Gaussians M and *pairs the number P of
// (tile, Gaussian) pairs: the sizes of the arrays mipslam_rasterize_forward fills.
MIPSLAM_API int mipslam_rasterize_bin(const float* means2d, const float* cov, const float* opacity,
                                      const float* depth, const float* colors, const int32_t* node_counts,
                                      int64_t n, int64_t channels, int64_t mode, int64_t width, int64_t height,
                                      double k_sigma, int64_t threads, void** state, int64_t* count, int64_t* pairs,
                                      char* err, int64_t err_len) {
    using namespace mipslam_cpu;
    *state = nullptr;
    return guarded(err, err_len, [&] {
        std::unique_ptr<Binning> b(new Binning());
        b->in = Inputs{means2d, cov, opacity, depth, colors, node_counts, n, channels};
        check_settings(b->in, mode, width, height);
        b->mode = (int)mode;
        b->width = (int)width;
        b->height = (int)height;
        b->tiles_x = (int)((width + TILE - 1) / TILE);
        b->tiles_y = (int)((height + TILE - 1) / TILE);
        b->threads = (int)threads;
        b->k_sigma = (float)k_sigma;
        bin_gaussians(b.get());
        *count = (int64_t)b->order.size();
        *pairs = b->pairs;
        *state = b.release();
    });
}

MIPSLAM_API void mipslam_rasterize_release(void* state) { delete static_cast<mipslam_cpu::Binning*>(state); }

// Second half of the forward: order [M], tile_offsets [tiles + 1], isect_ids [P], pair_offsets [M + 1],
// isect_pos [P] (the state the backward needs), color [H, W, C], depth [H, W], alpha [H, W], last [H, W]
// int32 and stats [2] (footprint lanes evaluated, pairs). The inputs given to mipslam_rasterize_bin must
// still be alive. gl_nodes, gl_weights [exact_order]: Gauss-Legendre rule on [-1, 1] (exact mode).
MIPSLAM_API int mipslam_rasterize_forward(void* state, double eta, double tau, const float* gl_nodes,
                                          const float* gl_weights, int64_t exact_order, int32_t* order,
                                          int32_t* tile_offsets, int32_t* isect_ids, int32_t* pair_offsets,
                                          int32_t* isect_pos, float* color, float* depth, float* alpha,
                                          int32_t* last, int64_t* stats, char* err, int64_t err_len) {
    using namespace mipslam_cpu;
    return guarded(err, err_len, [&] {
        MIPSLAM_CHECK(exact_order >= 1 && exact_order <= MAX_ROWS,
                      "mipslam cpu rasterizer: exact order must be in [1, ", MAX_ROWS, "]");
        Binning* b = static_cast<Binning*>(state);
        const Settings settings = make_settings(b->mode, b->k_sigma, eta, tau, gl_nodes, gl_weights, exact_order);
        rasterize_forward(b, settings, order, tile_offsets, isect_ids, pair_offsets, isect_pos, color, depth, alpha,
                          last, stats);
    });
}

// Gradient of sum(grad_color * color + grad_depth * depth + grad_alpha * alpha) with respect to means2d
// [N, 2], cov [N, 4], opacity [N], depth [N], colors [N, C] (g_* zero-filled by the caller), from the
// inputs and the state of the forward. grad_color_appearance [H, W, C] or null: a second colour gradient
// that only g_colors takes (as if the colour image it multiplies were rendered with the geometry held fixed).
MIPSLAM_API int mipslam_rasterize_backward(
    const float* means2d, const float* cov, const float* opacity, const float* depth, const float* colors,
    const int32_t* node_counts, int64_t n, int64_t channels, int64_t mode, int64_t width, int64_t height,
    double k_sigma, double eta, double tau, const float* gl_nodes, const float* gl_weights, int64_t exact_order,
    const int32_t* order, int64_t count, const int32_t* tile_offsets, const int32_t* isect_ids, int64_t pairs,
    const int32_t* pair_offsets, const int32_t* isect_pos, const int32_t* last, const float* color,
    const float* depth_img, const float* alpha_img, const float* grad_color, const float* grad_depth,
    const float* grad_alpha, const float* grad_color_appearance, int64_t need_color_grad, int64_t need_opacity_grad,
    int64_t threads, float* g_means2d, float* g_cov, float* g_opacity, float* g_depth, float* g_colors, char* err,
    int64_t err_len) {
    using namespace mipslam_cpu;
    return guarded(err, err_len, [&] {
        const Inputs in{means2d, cov, opacity, depth, colors, node_counts, n, channels};
        check_settings(in, mode, width, height);
        MIPSLAM_CHECK(exact_order >= 1 && exact_order <= MAX_ROWS,
                      "mipslam cpu rasterizer: exact order must be in [1, ", MAX_ROWS, "]");
        const Settings settings = make_settings((int)mode, k_sigma, eta, tau, gl_nodes, gl_weights, exact_order);
        const GradInputs gin{grad_color, grad_depth, grad_alpha, grad_color_appearance, color, depth_img, alpha_img,
                             last};
        rasterize_backward(in, (int)mode, (int)width, (int)height, settings, order, count, tile_offsets, isect_ids,
                           pairs, pair_offsets, isect_pos, gin, need_color_grad != 0, need_opacity_grad != 0,
                           (int)threads, g_means2d, g_cov, g_opacity, g_depth, g_colors);
    });
}

namespace {

template <typename T>
mipslam_cpu::ProjectionInputs<T> projection_inputs(const void* means, const void* quats, const void* scales,
                                                   const void* opacities, const void* colors, int64_t n,
                                                   int64_t channels) {
    return mipslam_cpu::ProjectionInputs<T>{static_cast<const T*>(means), static_cast<const T*>(quats),
                                            static_cast<const T*>(scales), static_cast<const T*>(opacities),
                                            static_cast<const T*>(colors), n, channels};
}

}  // namespace

// The fused projection (projection.h) in float32 (is_double = 0) or float64 (1); every floating array in
// that type. rate [N] or null. Outputs: means2d [N, 2], depth [N], cov [N, 4], opacity [N], nodes [N] int32,
// visible [N] bool, radii [N], *n_visible.
MIPSLAM_API int mipslam_project_forward(int64_t is_double, const void* means, const void* quats, const void* scales,
                                        const void* opacities, const void* colors, int64_t n, int64_t channels,
                                        const void* viewmat, const void* K, const void* rate, int64_t width,
                                        int64_t height, const double* params, int64_t n_params, int64_t threads,
                                        void* means2d, void* depth, void* cov, void* opacity, int32_t* nodes,
                                        bool* visible, void* radii, int64_t* n_visible, char* err,
                                        int64_t err_len) {
    using namespace mipslam_cpu;
    return guarded(err, err_len, [&] {
        auto run = [&](auto zero) {
            using T = decltype(zero);
            const auto S = projection_settings<T>(static_cast<const T*>(viewmat), static_cast<const T*>(K),
                                                  static_cast<const T*>(rate), width, height, params, n_params);
            *n_visible = project_forward_impl<T>(
                S, projection_inputs<T>(means, quats, scales, opacities, colors, n, channels), (int)threads,
                static_cast<T*>(means2d), static_cast<T*>(depth), static_cast<T*>(cov), static_cast<T*>(opacity),
                nodes, visible, static_cast<T*>(radii));
        };
        if (is_double)
            run(0.0);
        else
            run(0.0f);
    });
}

// Backward of mipslam_project_forward: incoming gradients (each null when it is zero) -> out_means [N, 3],
// out_quats [N, 4], out_scales [N, 3], out_opacities [N] (when need_params) and g_viewmat [12] (when
// need_viewmat; zero-filled by the caller: rotation row-major, then translation), in double.
MIPSLAM_API int mipslam_project_backward(int64_t is_double, const void* means, const void* quats, const void* scales,
                                         const void* opacities, const void* colors, int64_t n, int64_t channels,
                                         const void* viewmat, const void* K, const void* rate, int64_t width,
                                         int64_t height, const double* params, int64_t n_params,
                                         const bool* visible, const void* g_means2d, const void* g_depth,
                                         const void* g_cov, const void* g_opacity, int64_t need_params,
                                         int64_t need_viewmat, int64_t threads, void* out_means, void* out_quats,
                                         void* out_scales, void* out_opacities, double* g_viewmat, char* err,
                                         int64_t err_len) {
    using namespace mipslam_cpu;
    return guarded(err, err_len, [&] {
        auto run = [&](auto zero) {
            using T = decltype(zero);
            const auto S = projection_settings<T>(static_cast<const T*>(viewmat), static_cast<const T*>(K),
                                                  static_cast<const T*>(rate), width, height, params, n_params);
            project_backward_impl<T>(S, projection_inputs<T>(means, quats, scales, opacities, colors, n, channels),
                                     (int)threads, visible, static_cast<const T*>(g_means2d),
                                     static_cast<const T*>(g_depth), static_cast<const T*>(g_cov),
                                     static_cast<const T*>(g_opacity), need_params != 0, need_viewmat != 0,
                                     static_cast<T*>(out_means), static_cast<T*>(out_quats),
                                     static_cast<T*>(out_scales), static_cast<T*>(out_opacities), g_viewmat);
        };
        if (is_double)
            run(0.0);
        else
            run(0.0f);
    });
}

// Test hook: the vector exp (which = 0) or erf (1) of x [n] into y [n].
MIPSLAM_API void mipslam_vector_math(const float* x, float* y, int64_t n, int64_t which) {
    using namespace mipslam_cpu;
    for (int64_t i = 0; i < n; i += LANES) {
        vf v = splat(0.f);
        for (int l = 0; l < LANES && i + l < n; ++l) v[l] = x[i + l];
        const vf r = which == 0 ? vexp(v) : verf(v);
        for (int l = 0; l < LANES && i + l < n; ++l) y[i + l] = r[l];
    }
}

// Direct RGB-D alignment (direct_align.h) over ``levels`` pyramid levels, coarse to fine. Per level l:
// points[l] [counts[l], 3] and intensity[l] [counts[l]] of the reference, channels[l] [7, heights[l],
// widths[l]] of the target, intrinsics[4 l .. 4 l + 3] = fx, fy, cx, cy. T [16] (row-major, float64) is the
// initial motion on entry and the result on return; stats[3] = Gauss-Newton steps, residuals used at the last
// step, 1 if any step ran. constants[NUM_CONSTANTS]: direct_align.h's Constant order. The result does not depend on
// ``threads``.
MIPSLAM_API int mipslam_direct_align(int64_t levels, const float* const* points, const float* const* intensity,
                                     const int64_t* counts, const float* const* channels, const int64_t* heights,
                                     const int64_t* widths, const float* intrinsics, int64_t iterations,
                                     double alpha_color, double convergence, const double* constants,
                                     int64_t n_constants, int threads, double* T, int64_t* stats, char* err,
                                     int64_t err_len) {
    using namespace mipslam_cpu;
    return guarded(err, err_len, [&] {
        MIPSLAM_CHECK(n_constants == direct::NUM_CONSTANTS, "mipslam_direct_align: ", n_constants,
                      " constants, expected ", (int)direct::NUM_CONSTANTS);
        MIPSLAM_CHECK(levels >= 0 && iterations >= 0, "mipslam_direct_align: bad sizes");
        std::vector<direct::Level> pyramid;
        for (int64_t l = 0; l < levels; ++l) {
            MIPSLAM_CHECK(counts[l] >= 0 && heights[l] >= 1 && widths[l] >= 1,
                          "mipslam_direct_align: level ", l, " has a bad size");
            pyramid.push_back(direct::Level{points[l], intensity[l], counts[l], channels[l], heights[l], widths[l],
                                            intrinsics[4 * l], intrinsics[4 * l + 1], intrinsics[4 * l + 2],
                                            intrinsics[4 * l + 3]});
        }
        const direct::Outcome outcome =
            direct::align(pyramid, T, iterations, alpha_color, convergence, constants, std::max(1, threads));
        stats[0] = outcome.steps;
        stats[1] = outcome.points;
        stats[2] = outcome.ran ? 1 : 0;
    });
}

// The rows of the Gaussians a view can draw (mipslam.rendering.frustum_indices, its torch reference): means and
// scales [N, 3] float32 (world, metres; std-devs), view [16] float64 = R_cw row-major [9], t_cw [3], fx, fy, cx,
// cy; limits [5] float64 = width, height, near (m), k_sigma, pad (px). A row is kept where z > near and the
// disc of radius k_sigma * max scale * max(fx, fy) / max(z, near) + pad around its projection reaches the image
// (pixel centres at integers, the image spans [-0.5, size - 0.5]). Increasing rows into rows [N], their number
// into count[0]. In float64: the float32 reference decides alike except within ~1e-5 px of a limit, where no
// render of the view draws the Gaussian either way.
MIPSLAM_API int mipslam_frustum_rows(const float* means, const float* scales, int64_t N, const double* view,
                                     const double* limits, int64_t* rows, int64_t* count, char* err,
                                     int64_t err_len) {
    using namespace mipslam_cpu;
    return guarded(err, err_len, [&] {
        MIPSLAM_CHECK(N >= 0, "mipslam_frustum_rows: bad size");
        const double fx = view[12], fy = view[13], cx = view[14], cy = view[15];
        const double width = limits[0], height = limits[1], near = limits[2], k_sigma = limits[3], pad = limits[4];
        const double focal = std::max(fx, fy);
        int64_t kept = 0;
        for (int64_t i = 0; i < N; ++i) {
            const float* m = means + 3 * i;
            const float* s = scales + 3 * i;
            const double z = view[6] * m[0] + view[7] * m[1] + view[8] * m[2] + view[11];
            const double x = view[0] * m[0] + view[1] * m[1] + view[2] * m[2] + view[9];
            const double y = view[3] * m[0] + view[4] * m[1] + view[5] * m[2] + view[10];
            const double inv_z = 1.0 / std::max(z, near);
            const double u = fx * x * inv_z + cx, v = fy * y * inv_z + cy;
            const double reach = k_sigma * (double)std::max(s[0], std::max(s[1], s[2])) * focal * inv_z + pad;
            // branch-free: a map's rows fall in and out of a view in no predictable order
            const bool keep = (z > near) & (u + reach > -0.5) & (u - reach < width - 0.5) & (v + reach > -0.5) &
                              (v - reach < height - 0.5);
            rows[kept] = i;
            kept += keep ? 1 : 0;
        }
        count[0] = kept;
    });
}

// The front-end's guided matching (feature_match.h): keypoints [M, 2] and projections [P, 2] px float64,
// projection_ids [P] in [0, N), descriptors query [M, 32] and train [N, 32] uint8; the mutual, ratio-tested pairs
// (keypoint, reference point) by keypoint into pairs [M, 2], their number into count[0].
MIPSLAM_API int mipslam_guided_match(const double* keypoints, int64_t M, const double* projections,
                                     const int64_t* projection_ids, int64_t P, double limit, const uint8_t* query,
                                     const uint8_t* train, int64_t N, double ratio, int64_t max_hamming,
                                     int64_t* pairs, int64_t* count, char* err, int64_t err_len) {
    using namespace mipslam_cpu;
    return guarded(err, err_len, [&] {
        MIPSLAM_CHECK(M >= 0 && P >= 0 && N >= 0, "mipslam_guided_match: bad sizes");
        for (int64_t m = 0; m < 2 * M; ++m)
            MIPSLAM_CHECK(std::isfinite(keypoints[m]), "mipslam_guided_match: keypoint ", m / 2, " is not finite");
        for (int64_t j = 0; j < P; ++j)
            MIPSLAM_CHECK(projection_ids[j] >= 0 && projection_ids[j] < N, "mipslam_guided_match: projection ", j,
                          " names reference point ", projection_ids[j], " of ", N);
        count[0] = feature_match::guided_match(keypoints, M, projections, projection_ids, P, limit, query, train, N,
                                               ratio, max_hamming, pairs);
    });
}

// The masked RGB-D L1 loss of a render and its gradients (rgbd_loss.h): images [H, W, C] and [H, W] float32, masks
// [H, W] bool (alpha read only with depth_normalise); settings alpha_color, gain, bias, depth_alpha_floor; flags
// exposure and depth_normalise. out [5] float32 (total, colour term, depth term, d/d log_gain, d/d bias), counts
// [2] int64; grad_color [H, W, C] and grad_depth [H, W] float32, or null for the loss alone.
MIPSLAM_API int mipslam_rgbd_l1(const float* color, const float* depth, const float* alpha, const float* color_gt,
                                const float* depth_gt, const uint8_t* mask_color, const uint8_t* mask_depth,
                                int64_t pixels, int64_t channels, double alpha_color, int64_t exposure, double gain,
                                double bias, int64_t depth_normalise, double depth_alpha_floor, float* out,
                                int64_t* counts, float* grad_color, float* grad_depth, char* err, int64_t err_len) {
    using namespace mipslam_cpu;
    return guarded(err, err_len, [&] {
        MIPSLAM_CHECK(pixels >= 0 && channels >= 1, "mipslam_rgbd_l1: bad sizes");
        MIPSLAM_CHECK(depth_normalise == 0 || alpha != nullptr, "mipslam_rgbd_l1: depth_normalise needs the opacity");
        MIPSLAM_CHECK_VALUE(alpha_color >= 0.0 && alpha_color <= 1.0, "mipslam_rgbd_l1: alpha_color ", alpha_color,
                            " is not in [0, 1]");
        const rgbd_loss::Images images{color, depth, alpha, color_gt, depth_gt, mask_color, mask_depth, pixels,
                                       channels};
        const rgbd_loss::Options options{(float)alpha_color, (float)(1.0 - alpha_color), exposure != 0 ? 1 : 0,
                                         (float)gain, (float)bias, depth_normalise != 0 ? 1 : 0,
                                         (float)depth_alpha_floor};
        rgbd_loss::evaluate(images, options, out, counts, grad_color, grad_depth);
    });
}

// SSIM of image and target [H, W, C] float32 with "same" (zero) padding (ssim_loss.h): window [taps] float32 (the
// separable Gaussian's 1D factor: odd taps <= 31, symmetric), constants c1 and c2. The mean over pixels and channels
// into out[0] (float64); with grad not null, grad_scale times its gradient with respect to the image into grad
// [H, W, C]. target_moments [2, H, W, C] (the blurred target and its blurred square, from mipslam_ssim_moments with
// the same window) or null (computed here).
MIPSLAM_API int mipslam_ssim(const float* image, const float* target, const float* target_moments, int64_t height,
                             int64_t width, int64_t channels, const float* window, int64_t taps, double c1, double c2,
                             double grad_scale, int64_t threads, double* out, float* grad, char* err,
                             int64_t err_len) {
    using namespace mipslam_cpu;
    return guarded(err, err_len, [&] {
        MIPSLAM_CHECK(height >= 1 && width >= 1 && channels >= 1, "mipslam_ssim: bad sizes");
        MIPSLAM_CHECK(taps >= 1 && taps <= ssim::MAX_TAPS && taps % 2 == 1, "mipslam_ssim: ", taps,
                      " window taps, expected an odd count up to ", ssim::MAX_TAPS);
        for (int64_t k = 0; k < taps / 2; ++k)
            MIPSLAM_CHECK(window[k] == window[taps - 1 - k], "mipslam_ssim: the window is not symmetric");
        const ssim::Geometry G(height, width, channels, window, (int)taps);
        out[0] = ssim::evaluate(G, image, target, target_moments, ssim::Constants{(float)c1, (float)c2,
                                (float)grad_scale}, std::max<int>(1, (int)threads), grad);
    });
}

// The target's SSIM moments (ssim_loss.h) into moments [2, H, W, C] float32: the blurred target and its blurred
// square, with mipslam_ssim's window and zero padding.
MIPSLAM_API int mipslam_ssim_moments(const float* target, int64_t height, int64_t width, int64_t channels,
                                     const float* window, int64_t taps, int64_t threads, float* moments, char* err,
                                     int64_t err_len) {
    using namespace mipslam_cpu;
    return guarded(err, err_len, [&] {
        MIPSLAM_CHECK(height >= 1 && width >= 1 && channels >= 1, "mipslam_ssim_moments: bad sizes");
        MIPSLAM_CHECK(taps >= 1 && taps <= ssim::MAX_TAPS && taps % 2 == 1, "mipslam_ssim_moments: ", taps,
                      " window taps, expected an odd count up to ", ssim::MAX_TAPS);
        for (int64_t k = 0; k < taps / 2; ++k)
            MIPSLAM_CHECK(window[k] == window[taps - 1 - k], "mipslam_ssim_moments: the window is not symmetric");
        const ssim::Geometry G(height, width, channels, window, (int)taps);
        ssim::moments(G, target, std::max<int>(1, (int)threads), moments);
    });
}
