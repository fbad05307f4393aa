// mipslam CPU rasterizer: tile binning, depth sort, SIMD footprint evaluation and front-to-back
// compositing of projected Gaussians, forward and hand-written backward (docs/renderer.md, section
// "CPU backend"). The projection stays in torch (mipslam/render/projection.py); this file receives the
// projected per-Gaussian quantities the torch rasterizer composites and returns the gradient with
// respect to them.
//
// Parallelism: OpenMP over 16x16 tiles (dynamic schedule). Each (Gaussian, tile) pair writes its
// gradient to its own record; records are summed per Gaussian in a fixed (tile) order afterwards, so
// the backward has no atomics and its result does not depend on the thread count or the schedule.
// SIMD: inside a tile a Gaussian is evaluated on the 8-pixel row segments its pixel box touches
// (vectors of simd_math.h; the channel count C is a template parameter, never a runtime loop bound in
// the pixel loop).
#include <torch/extension.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <limits>
#include <memory>
#include <vector>

#include "footprint_simd.h"
#include "projection.h"
#include "simd_math.h"

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

// Rows [*ra, *rb] and blocks [*b0, *b1] (inclusive) of the tile at (x0, y0) that cover the Gaussian's
// pixel box. The tile loops take the rows in pairs (two independent pixel vectors per iteration) and an
// odd last row alone.
static inline __attribute__((always_inline)) bool tile_span(const Gauss& g, int x0, int y0, int* ra, int* rb,
                                                            int* b0, int* b1) {
    const int r0 = std::max(g.py0 - y0, 0), r1 = std::min(g.py1 - y0, TILE - 1);
    const int c0 = std::max(g.px0 - x0, 0), c1 = std::min(g.px1 - x0, TILE - 1);
    if (r0 > r1 || c0 > c1) return false;
    *ra = r0;
    *rb = r1;
    *b0 = c0 / LANES;
    *b1 = c1 / LANES;
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
        int ra, rb, b0, b1;
        if (!tile_span(g, x0, y0, &ra, &rb, &b0, &b1)) continue;
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
        if (uses_columns<MODE>(g)) {
            const int r0 = std::max(g.py0 - y0, 0), r1 = std::min(g.py1 - y0, TILE - 1);
            const int c0 = std::max(g.px0 - x0, 0), c1 = std::min(g.px1 - x0, TILE - 1);
            for (int R = r0 / LANES; R <= r1 / LANES; ++R) {
                const int rr0 = std::max(r0, R * LANES), rr1 = std::min(r1, R * LANES + LANES - 1);
                const vf py_lanes = splat((float)(y0 + R * LANES)) + lane;
                for (int b = c0 / LANES; b <= c1 / LANES; ++b) {
                    const int cc0 = std::max(c0, b * LANES), cc1 = std::min(c1, b * LANES + LANES - 1);
                    vf cols[LANES], rows[LANES];
                    for (int i = 0; i < LANES; ++i) {
                        const int cx = b * LANES + i;
                        cols[i] = (cx < cc0 || cx > cc1) ? splat(0.f)
                                                         : eaa_eval_outer_y(g, S, py_lanes, (float)(x0 + cx), &lp);
                    }
                    transpose8(cols, rows);
                    for (int r = rr0; r <= rr1; ++r) composite(r * BLOCKS_PER_ROW + b, rows[r - R * LANES]);
                    lanes += (int64_t)(cc1 - cc0 + 1) * LANES;
                }
            }
        } else {
            int r = ra;
            for (; r < rb; r += 2) {
                const float py0 = (float)(y0 + r), py1 = py0 + 1.f;
                bool ready0 = false, ready1 = false;
                for (int b = b0; b <= b1; ++b) {
                    const int v0 = r * BLOCKS_PER_ROW + b;
                    const vf px = splat((float)(x0 + b * LANES)) + lane;
                    const vf a0 = eval_footprint<MODE>(g, S, k2, px, py0, &cp0, &ep0, &xp0, &ready0);
                    const vf a1 = eval_footprint<MODE>(g, S, k2, px, py1, &cp1, &ep1, &xp1, &ready1);
                    composite(v0, a0);
                    composite(v0 + BLOCKS_PER_ROW, a1);
                }
            }
            if (r == rb) {  // odd last row
                const float py0 = (float)(y0 + r);
                bool ready0 = false;
                for (int b = b0; b <= b1; ++b) {
                    const vf px = splat((float)(x0 + b * LANES)) + lane;
                    composite(r * BLOCKS_PER_ROW + b, eval_footprint<MODE>(g, S, k2, px, py0, &cp0, &ep0, &xp0,
                                                                           &ready0));
                }
            }
            lanes += (int64_t)(rb - ra + 1) * (b1 - b0 + 1) * LANES;
        }
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
    vf gcol[C][NV], gdep[NV], galp[NV], stot[NV], T[NV], prefix[NV];
    vi last[NV];
    for (int r = 0; r < TILE; ++r) {
        for (int b = 0; b < BLOCKS_PER_ROW; ++b) {
            const int v = r * BLOCKS_PER_ROW + b;
            for (int i = 0; i < LANES; ++i) {
                const int x = x0 + b * LANES + i, y = y0 + r;
                float gd = 0.f, gal = 0.f, st = 0.f, gc[C] = {};
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
                    la = gin.last[p];
                    // a pixel without incoming gradient (masked out of the loss) contributes nothing: skip it
                    bool any = gd != 0.f || gal != 0.f;
                    for (int c = 0; c < C; ++c) any = any || gc[c] != 0.f;
                    if (!any) la = 0;
                }
                gdep[v][i] = gd;
                galp[v][i] = gal;
                stot[v][i] = st;
                for (int c = 0; c < C; ++c) gcol[c][v][i] = gc[c];
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
        int ra, rb, b0, b1;
        if (!tile_span(g, x0, y0, &ra, &rb, &b0, &b1)) {
            for (int q = 0; q < REC; ++q) records[(int64_t)j * REC + q] = 0.f;
            continue;
        }
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
                for (int c = 0; c < C; ++c) acc_c[c] += w * gcol[c][v];
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
        if (uses_columns<MODE>(g)) {
            const int r0 = std::max(g.py0 - y0, 0), r1 = std::min(g.py1 - y0, TILE - 1);
            const int c0 = std::max(g.px0 - x0, 0), c1 = std::min(g.px1 - x0, TILE - 1);
            for (int R = r0 / LANES; R <= r1 / LANES; ++R) {
                const int rr0 = std::max(r0, R * LANES), rr1 = std::min(r1, R * LANES + LANES - 1);
                const vf py_lanes = splat((float)(y0 + R * LANES)) + lane;
                for (int b = c0 / LANES; b <= c1 / LANES; ++b) {
                    vi listed_any = splati(0);
                    for (int r = rr0; r <= rr1; ++r) listed_any |= slot < last[r * BLOCKS_PER_ROW + b];
                    if (!any_lane(listed_any)) continue;
                    const int cc0 = std::max(c0, b * LANES), cc1 = std::min(c1, b * LANES + LANES - 1);
                    vf cols[LANES], rows[LANES], ga_rows[LANES], ga_cols[LANES];
                    for (int i = 0; i < LANES; ++i) {
                        const int cx = b * LANES + i;
                        cols[i] = (cx < cc0 || cx > cc1)
                                      ? splat(0.f)
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
                }
            }
        } else {
            int r = ra;
            for (; r < rb; r += 2) {
                const float py0 = (float)(y0 + r), py1 = py0 + 1.f;
                bool ready0 = false, ready1 = false;
                for (int b = b0; b <= b1; ++b) {
                    const int v0 = r * BLOCKS_PER_ROW + b;
                    const vf px = splat((float)(x0 + b * LANES)) + lane;
                    process(v0, px, py0, &cp0, &ep0, &xp0, &ready0);
                    process(v0 + BLOCKS_PER_ROW, px, py1, &cp1, &ep1, &xp1, &ready1);
                }
            }
            if (r == rb) {  // odd last row
                bool ready0 = false;
                for (int b = b0; b <= b1; ++b)
                    process(r * BLOCKS_PER_ROW + b, splat((float)(x0 + b * LANES)) + lane, (float)(y0 + r), &cp0,
                            &ep0, &xp0, &ready0);
            }
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
// Host functions
// ---------------------------------------------------------------------------------------------
static void check_tensor(const at::Tensor& t, const char* name, at::ScalarType dtype, int64_t dim0, int64_t dim1) {
    TORCH_CHECK(t.device().is_cpu(), "mipslam cpu rasterizer: ", name, " must be a CPU tensor");
    TORCH_CHECK(t.scalar_type() == dtype, "mipslam cpu rasterizer: ", name, " has the wrong dtype");
    TORCH_CHECK(t.is_contiguous(), "mipslam cpu rasterizer: ", name, " must be contiguous");
    TORCH_CHECK(t.dim() >= 1 && t.size(0) == dim0, "mipslam cpu rasterizer: ", name, " has the wrong length");
    if (dim1 >= 0)
        TORCH_CHECK(t.dim() >= 2 && t.size(1) == dim1, "mipslam cpu rasterizer: ", name, " has the wrong shape");
}

struct Inputs {
    const float *means2d, *cov, *opacity, *depth, *colors;
    const int32_t* node_counts;
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

struct Binning {
    at::Tensor order;         // [M] int32 input index of each drawn Gaussian, front to back
    at::Tensor tile_offsets;  // [tiles + 1] int32
    at::Tensor isect_ids;     // [P] int32 sorted index of each pair (tile-major)
    at::Tensor pair_offsets;  // [M + 1] int32 pairs of sorted Gaussian m: isect_pos[pair_offsets[m] ..]
    at::Tensor isect_pos;     // [P] int32 position of each of those pairs in the tile-major list
};

static Binning bin_gaussians(const Inputs& in, int mode, float k, int width, int height, int threads,
                             Sorted* sorted) {
    const int64_t n = in.n;
    const int tiles_x = (width + TILE - 1) / TILE, tiles_y = (height + TILE - 1) / TILE;
    const int64_t num_tiles = (int64_t)tiles_x * tiles_y;
    std::unique_ptr<Gauss[]> all(new Gauss[(size_t)std::max<int64_t>(n, 1)]);  // written by setup_all
    std::vector<uint8_t> drawn(n, 0);
    setup_all(in, mode, k, width, height, threads, all.get(), drawn.data());
    // Depth order, ties in input order (the torch backend's stable argsort): the depth as an
    // order-preserving unsigned integer, radix-sorted stably with the indices in increasing order.
    // Depths are finite here.
    std::vector<uint32_t> keys;
    std::vector<int32_t> index;
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
    const int64_t count = (int64_t)keys.size();
    Binning out;
    out.order = at::empty({count}, at::kInt);
    int32_t* order = out.order.data_ptr<int32_t>();
    std::copy(index.begin(), index.end(), order);
    gather_sorted(in, all.get(), order, count, threads, sorted);
    const Gauss* gs = sorted->gauss.get();

    out.pair_offsets = at::empty({count + 1}, at::kInt);
    int32_t* poff = out.pair_offsets.data_ptr<int32_t>();
    out.tile_offsets = at::zeros({num_tiles + 1}, at::kInt);
    int32_t* toff = out.tile_offsets.data_ptr<int32_t>();
    int64_t total = 0;
    for (int64_t m = 0; m < count; ++m) {
        const Gauss& g = gs[m];
        poff[m] = (int32_t)total;
        for (int ty = g.py0 / TILE; ty <= g.py1 / TILE; ++ty)
            for (int tx = g.px0 / TILE; tx <= g.px1 / TILE; ++tx) toff[(int64_t)ty * tiles_x + tx + 1] += 1;
        total += (int64_t)(g.px1 / TILE - g.px0 / TILE + 1) * (g.py1 / TILE - g.py0 / TILE + 1);
        TORCH_CHECK(total < (int64_t)std::numeric_limits<int32_t>::max(),
                    "mipslam cpu rasterizer: more than 2^31 (tile, Gaussian) pairs; render at a lower resolution");
    }
    poff[count] = (int32_t)total;
    for (int64_t t = 0; t < num_tiles; ++t) toff[t + 1] += toff[t];
    out.isect_ids = at::empty({total}, at::kInt);
    out.isect_pos = at::empty({total}, at::kInt);
    int32_t* ids = out.isect_ids.data_ptr<int32_t>();
    int32_t* pos = out.isect_pos.data_ptr<int32_t>();
    std::vector<int32_t> cursor(toff, toff + num_tiles);
    for (int64_t m = 0; m < count; ++m) {
        const Gauss& g = gs[m];
        int32_t q = poff[m];
        for (int ty = g.py0 / TILE; ty <= g.py1 / TILE; ++ty)
            for (int tx = g.px0 / TILE; tx <= g.px1 / TILE; ++tx) {
                const int32_t p = cursor[(int64_t)ty * tiles_x + tx]++;
                ids[p] = (int32_t)m;
                pos[q++] = p;
            }
    }
    return out;
}

static Settings make_settings(int mode, double k, double eta, double tau, const at::Tensor& gl_nodes,
                              const at::Tensor& gl_weights) {
    Settings s;
    s.mode = mode;
    s.k_sigma = (float)k;
    s.eta = (float)eta;
    s.tau = (float)tau;
    s.exact_order = (int)gl_nodes.size(0);
    s.gl_nodes = gl_nodes.data_ptr<float>();
    s.gl_weights = gl_weights.data_ptr<float>();
    return s;
}

static Inputs check_inputs(const at::Tensor& means2d, const at::Tensor& cov, const at::Tensor& opacity,
                           const at::Tensor& depth, const at::Tensor& colors, const at::Tensor& node_counts,
                           int64_t mode, int64_t width, int64_t height, const at::Tensor& gl_nodes,
                           const at::Tensor& gl_weights) {
    const int64_t n = means2d.size(0);
    check_tensor(means2d, "means2d", at::kFloat, n, 2);
    check_tensor(cov, "cov", at::kFloat, n, 4);
    check_tensor(opacity, "opacity", at::kFloat, n, -1);
    check_tensor(depth, "depth", at::kFloat, n, -1);
    TORCH_CHECK(colors.dim() == 2, "mipslam cpu rasterizer: colors must be [N, C]");
    check_tensor(colors, "colors", at::kFloat, n, colors.size(1));
    check_tensor(node_counts, "node_counts", at::kInt, n, -1);
    check_tensor(gl_nodes, "gl_nodes", at::kFloat, gl_nodes.size(0), -1);
    check_tensor(gl_weights, "gl_weights", at::kFloat, gl_nodes.size(0), -1);
    TORCH_CHECK(mode >= 0 && mode <= 2, "mipslam cpu rasterizer: unknown mode ", mode);
    TORCH_CHECK(width >= 1 && height >= 1 && width <= (1 << 24) && height <= (1 << 24),
                "mipslam cpu rasterizer: image size must be in [1, 2^24]");
    TORCH_CHECK(gl_nodes.size(0) >= 1 && gl_nodes.size(0) <= MAX_ROWS,
                "mipslam cpu rasterizer: exact order must be in [1, ", MAX_ROWS, "]");
    if (n > 0 && mode == MODE_EAA) {
        const int32_t* nc = node_counts.data_ptr<int32_t>();
        for (int64_t i = 0; i < n; ++i)
            TORCH_CHECK(nc[i] >= 1 && nc[i] <= MAX_ROWS, "mipslam cpu rasterizer: EAA node counts must be in [1, ",
                        MAX_ROWS, "]");
    }
    return Inputs{means2d.data_ptr<float>(), cov.data_ptr<float>(), opacity.data_ptr<float>(),
                  depth.data_ptr<float>(), colors.data_ptr<float>(), node_counts.data_ptr<int32_t>(), n,
                  colors.size(1)};
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

#define MIPSLAM_DISPATCH_CHANNELS(C_VALUE, CALL)                                                         \
    switch (C_VALUE) {                                                                                   \
        case 1: { constexpr int CH = 1; CALL; break; }                                                   \
        case 3: { constexpr int CH = 3; CALL; break; }                                                   \
        case 4: { constexpr int CH = 4; CALL; break; }                                                   \
        default: TORCH_CHECK(false, "mipslam cpu rasterizer: colour channels must be 1, 3 or 4, got ", C_VALUE); \
    }

// Returns color [H, W, C], depth [H, W], alpha [H, W], then the state the backward needs (order,
// tile_offsets, isect_ids, pair_offsets, isect_pos, last [H, W]) and stats [2] int64 (footprint lanes
// evaluated, pairs).
std::vector<at::Tensor> rasterize_forward(const at::Tensor& means2d, const at::Tensor& cov,
                                          const at::Tensor& opacity, const at::Tensor& depth,
                                          const at::Tensor& colors, const at::Tensor& node_counts, int64_t mode,
                                          int64_t width, int64_t height, double k_sigma, double eta, double tau,
                                          const at::Tensor& gl_nodes, const at::Tensor& gl_weights,
                                          int64_t threads) {
    const Inputs in = check_inputs(means2d, cov, opacity, depth, colors, node_counts, mode, width, height, gl_nodes,
                                   gl_weights);
    const int64_t C = in.channels;
    // every pixel is written by forward_tile
    at::Tensor color = at::empty({height, width, C}, at::kFloat);
    at::Tensor depth_img = at::empty({height, width}, at::kFloat);
    at::Tensor alpha_img = at::empty({height, width}, at::kFloat);
    at::Tensor last = at::empty({height, width}, at::kInt);
    at::Tensor stats = at::zeros({2}, at::kLong);
    Binning bins;
    {
        pybind11::gil_scoped_release no_gil;
        Sorted sorted;
        bins = bin_gaussians(in, (int)mode, (float)k_sigma, (int)width, (int)height, (int)threads, &sorted);
        Scene sc{(int)width, (int)height, (int)((width + TILE - 1) / TILE), (int)((height + TILE - 1) / TILE),
                 (int)C, make_settings((int)mode, k_sigma, eta, tau, gl_nodes, gl_weights), sorted.gauss.get(),
                 sorted.colors.get(), bins.tile_offsets.data_ptr<int32_t>(), bins.isect_ids.data_ptr<int32_t>()};
        int64_t lanes = 0;
        MIPSLAM_DISPATCH_CHANNELS(C, lanes = run_forward<CH>(sc, (int)threads, color.data_ptr<float>(),
                                                           depth_img.data_ptr<float>(), alpha_img.data_ptr<float>(),
                                                           last.data_ptr<int32_t>()));
        stats.data_ptr<int64_t>()[0] = lanes;
        stats.data_ptr<int64_t>()[1] = bins.isect_ids.size(0);
    }
    return {color, depth_img, alpha_img, bins.order, bins.tile_offsets, bins.isect_ids, bins.pair_offsets,
            bins.isect_pos, last, stats};
}

// Gradient of sum(grad_color * color + grad_depth * depth + grad_alpha * alpha) with respect to
// means2d [N, 2], cov [N, 4], opacity [N], depth [N], colors [N, C] (in this order).
std::vector<at::Tensor> rasterize_backward(
    const at::Tensor& means2d, const at::Tensor& cov, const at::Tensor& opacity, const at::Tensor& depth,
    const at::Tensor& colors, const at::Tensor& node_counts, int64_t mode, int64_t width, int64_t height,
    double k_sigma, double eta, double tau, const at::Tensor& gl_nodes, const at::Tensor& gl_weights,
    const at::Tensor& order, const at::Tensor& tile_offsets, const at::Tensor& isect_ids,
    const at::Tensor& pair_offsets, const at::Tensor& isect_pos, const at::Tensor& last, const at::Tensor& color,
    const at::Tensor& depth_img, const at::Tensor& alpha_img, const at::Tensor& grad_color,
    const at::Tensor& grad_depth, const at::Tensor& grad_alpha, bool need_color_grad, bool need_opacity_grad,
    int64_t threads) {
    const Inputs in = check_inputs(means2d, cov, opacity, depth, colors, node_counts, mode, width, height, gl_nodes,
                                   gl_weights);
    const int64_t n = in.n, C = in.channels;
    const int tiles_x = (int)((width + TILE - 1) / TILE), tiles_y = (int)((height + TILE - 1) / TILE);
    const int64_t num_tiles = (int64_t)tiles_x * tiles_y;
    const int64_t count = order.size(0), total = isect_ids.size(0);
    check_tensor(order, "order", at::kInt, count, -1);
    check_tensor(tile_offsets, "tile_offsets", at::kInt, num_tiles + 1, -1);
    check_tensor(pair_offsets, "pair_offsets", at::kInt, count + 1, -1);
    check_tensor(isect_ids, "isect_ids", at::kInt, total, -1);
    check_tensor(isect_pos, "isect_pos", at::kInt, total, -1);
    check_tensor(last, "last", at::kInt, height, width);
    check_tensor(color, "color", at::kFloat, height, width);
    check_tensor(grad_color, "grad_color", at::kFloat, height, width);
    check_tensor(depth_img, "depth", at::kFloat, height, width);
    check_tensor(alpha_img, "alpha", at::kFloat, height, width);
    check_tensor(grad_depth, "grad_depth", at::kFloat, height, width);
    check_tensor(grad_alpha, "grad_alpha", at::kFloat, height, width);
    TORCH_CHECK(color.dim() == 3 && color.size(2) == C && grad_color.dim() == 3 && grad_color.size(2) == C,
                "mipslam cpu rasterizer: colour images must be [H, W, C]");
    at::Tensor g_means2d = at::zeros({n, 2}, at::kFloat);
    at::Tensor g_cov = at::zeros({n, 4}, at::kFloat);
    at::Tensor g_opacity = at::zeros({n}, at::kFloat);
    at::Tensor g_depth = at::zeros({n}, at::kFloat);
    at::Tensor g_colors = at::zeros({n, C}, at::kFloat);
    {
        pybind11::gil_scoped_release no_gil;
        const int32_t* ord = order.data_ptr<int32_t>();
        for (int64_t m = 0; m < count; ++m)
            TORCH_CHECK(ord[m] >= 0 && ord[m] < n, "mipslam cpu rasterizer: corrupt backward state (order)");
        Sorted sorted;  // identical to the forward's (same inputs, same arithmetic)
        sorted.allocate(count, C);
        {
            Gauss* gs = sorted.gauss.get();
            float* cs = sorted.colors.get();
#pragma omp parallel for schedule(static) num_threads((int)threads)
            for (int64_t m = 0; m < count; ++m) {
                const int64_t i = ord[m];
                bool drawn = false;
                gs[m] = setup_gaussian((int)mode, (float)k_sigma, in.means2d + 2 * i, in.cov + 4 * i, in.opacity[i],
                                       in.depth[i], in.node_counts[i], (int)width, (int)height, &drawn);
                for (int64_t c = 0; c < C; ++c) cs[m * C + c] = in.colors[i * C + c];
            }
        }
        Scene sc{(int)width, (int)height, tiles_x, tiles_y, (int)C,
                 make_settings((int)mode, k_sigma, eta, tau, gl_nodes, gl_weights), sorted.gauss.get(),
                 sorted.colors.get(), tile_offsets.data_ptr<int32_t>(), isect_ids.data_ptr<int32_t>()};
        GradInputs gin{grad_color.data_ptr<float>(), grad_depth.data_ptr<float>(), grad_alpha.data_ptr<float>(),
                       color.data_ptr<float>(), depth_img.data_ptr<float>(), alpha_img.data_ptr<float>(),
                       last.data_ptr<int32_t>()};
        const int64_t rec = 8 + C;
        // every record is written by backward_tile (zeros for pairs it skips)
        std::unique_ptr<float[]> records(new float[(size_t)std::max<int64_t>(total * rec, 1)]);
        MIPSLAM_DISPATCH_CHANNELS(C, run_backward<CH>(sc, (int)threads, gin, records.get(), need_color_grad,
                                                      need_opacity_grad));
        // Deterministic reduction: each Gaussian sums its pairs in tile order (no atomics, and the
        // result does not depend on the number of threads or on the schedule).
        const int32_t* poff = pair_offsets.data_ptr<int32_t>();
        const int32_t* ip = isect_pos.data_ptr<int32_t>();
        float* gm = g_means2d.data_ptr<float>();
        float* gc = g_cov.data_ptr<float>();
        float* go = g_opacity.data_ptr<float>();
        float* gd = g_depth.data_ptr<float>();
        float* gcol = g_colors.data_ptr<float>();
        const float* rp = records.get();
#pragma omp parallel for schedule(static) num_threads((int)threads)
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
    return {g_means2d, g_cov, g_opacity, g_depth, g_colors};
}

// Test hooks: the vector exp / erf on a float tensor (any length). which: 0 = exp, 1 = erf.
at::Tensor vector_math(const at::Tensor& x, int64_t which) {
    TORCH_CHECK(x.scalar_type() == at::kFloat && x.dim() == 1 && x.is_contiguous(),
                "vector_math: x must be a contiguous 1-D float32 tensor");
    at::Tensor y = at::empty_like(x);
    const float* xp = x.data_ptr<float>();
    float* yp = y.data_ptr<float>();
    const int64_t n = x.size(0);
    for (int64_t i = 0; i < n; i += LANES) {
        vf v = splat(0.f);
        for (int l = 0; l < LANES && i + l < n; ++l) v[l] = xp[i + l];
        const vf r = which == 0 ? vexp(v) : verf(v);
        for (int l = 0; l < LANES && i + l < n; ++l) yp[i + l] = r[l];
    }
    return y;
}

std::string build_info() {
    std::string s;
#ifdef __AVX2__
    s += "avx2 ";
#endif
#ifdef __FMA__
    s += "fma ";
#endif
#ifdef __SSE2__
    s += "sse2 ";
#endif
#ifdef _OPENMP
    s += "openmp";
#else
    s += "no-openmp";
#endif
    return s;
}

}  // namespace mipslam_cpu

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
    m.doc() = "mipslam CPU rasterizer (tile binning, SIMD footprints, compositing; forward and backward)";
    m.def("rasterize_forward", &mipslam_cpu::rasterize_forward);
    m.def("rasterize_backward", &mipslam_cpu::rasterize_backward);
    m.def("project_forward", &mipslam_cpu::project_forward);
    m.def("project_backward", &mipslam_cpu::project_backward);
    m.def("vector_math", &mipslam_cpu::vector_math);
    m.def("build_info", &mipslam_cpu::build_info);
}
