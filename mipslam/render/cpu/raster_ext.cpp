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
#include <limits>
#include <vector>

#include "footprint_simd.h"
#include "simd_math.h"

#ifdef _OPENMP
#include <omp.h>
#endif

namespace mipslam_cpu {

constexpr int TILE = 16;
constexpr int BLOCKS_PER_ROW = TILE / LANES;
constexpr int NV = TILE * BLOCKS_PER_ROW;  // vectors per tile

struct Scene {
    int width, height, tiles_x, tiles_y, channels;
    Settings settings;
    const Gauss* gauss;
    const float* colors;          // [N, C]
    const int32_t* tile_offsets;  // [tiles + 1]
    const int32_t* isect_gauss;   // [P] Gaussian of each (tile, Gaussian) pair, tile-major, depth order
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
        const double kk = std::min((double)k * k, k_alpha2);
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

template <int MODE>
static inline __attribute__((always_inline)) vf eval_footprint(const Gauss& g, const Settings& S, float k2, vf px,
                                                               float py, CentrePixel* cp, EaaPixel* ep,
                                                               ExactPixel* xp) {
    if (MODE == MODE_CENTRE) return centre_eval(g, k2, px, py, cp);
    if (MODE == MODE_EAA) {
        if (g.nodes <= 1) return centre_eval(g, k2, px, py, cp);
        return eaa_eval(g, S, px, py, ep);
    }
    return exact_eval(g, S, px, py, xp);
}

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
    CentrePixel cp;
    EaaPixel ep;
    ExactPixel xp;
    for (int32_t j = begin; j < end; ++j) {
        const int32_t gi = sc.isect_gauss[j];
        const Gauss& g = sc.gauss[gi];
        const int r0 = std::max(g.py0 - y0, 0), r1 = std::min(g.py1 - y0, TILE - 1);
        const int b0 = std::max(g.px0 - x0, 0) / LANES, b1 = std::min(g.px1 - x0, TILE - 1) / LANES;
        const vi slot = splati(j - begin + 1);
        vf col[C];
        for (int c = 0; c < C; ++c) col[c] = splat(sc.colors[(int64_t)gi * C + c]);
        const vf z = splat(g.depth);
        for (int r = r0; r <= r1; ++r) {
            const float py = (float)(y0 + r);
            for (int b = b0; b <= b1; ++b) {
                const int v = r * BLOCKS_PER_ROW + b;
                const vf px = splat((float)(x0 + b * LANES)) + lane;
                const vf a = eval_footprint<MODE>(g, S, k2, px, py, &cp, &ep, &xp);
                vf al = vmin(a, splat(ALPHA_MAX));
                al = select(a < splat(ALPHA_MIN), splat(0.f), al);
                const vf t = T[v];
                const vf tn = t - al * t;
                const vi positive = al > splat(0.f);
                const vi contrib = positive & (tn >= splat(TRANSMITTANCE_MIN));
                const vi stop = positive & (tn < splat(TRANSMITTANCE_MIN));
                const vf w = select(contrib, al * t, splat(0.f));
                for (int c = 0; c < C; ++c) acc_c[c][v] += w * col[c];
                acc_d[v] += w * z;
                acc_a[v] += w;
                T[v] = select(contrib, tn, select(stop, splat(0.f), t));
                last[v] = selecti(contrib, slot, last[v]);
            }
        }
        lanes += (int64_t)(r1 - r0 + 1) * (b1 - b0 + 1) * LANES;
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
    if (MODE == MODE_CENTRE) {
        centre_grad<GO>(g, py, cp, ga, acc);
    } else if (MODE == MODE_EAA) {
        if (g.nodes <= 1)
            centre_grad<GO>(g, py, cp, ga, acc);
        else
            eaa_grad<GO>(g, S, ep, ga, acc);
    } else {
        exact_grad<GO>(g, S, xp, ga, acc);
    }
}

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
                float gd = 0.f, gal = 0.f, st = 0.f, gc[C > 0 ? C : 1] = {};
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
    CentrePixel cp;
    EaaPixel ep;
    ExactPixel xp;
    for (int32_t j = begin; j < stop; ++j) {
        const int32_t gi = sc.isect_gauss[j];
        const Gauss& g = sc.gauss[gi];
        const int r0 = std::max(g.py0 - y0, 0), r1 = std::min(g.py1 - y0, TILE - 1);
        const int b0 = std::max(g.px0 - x0, 0) / LANES, b1 = std::min(g.px1 - x0, TILE - 1) / LANES;
        const vi slot = splati(j - begin);
        vf col[C];
        for (int c = 0; c < C; ++c) col[c] = splat(sc.colors[(int64_t)gi * C + c]);
        const vf z = splat(g.depth);
        FootAcc acc;
        acc.zero();
        vf acc_c[C], acc_d = splat(0.f);
        for (int c = 0; c < C; ++c) acc_c[c] = splat(0.f);
        for (int r = r0; r <= r1; ++r) {
            const float py = (float)(y0 + r);
            for (int b = b0; b <= b1; ++b) {
                const int v = r * BLOCKS_PER_ROW + b;
                const vi listed = slot < last[v];
                if (!any_lane(listed)) continue;
                const vf px = splat((float)(x0 + b * LANES)) + lane;
                const vf a = eval_footprint<MODE>(g, S, k2, px, py, &cp, &ep, &xp);
                vf al = vmin(a, splat(ALPHA_MAX));
                al = select(a < splat(ALPHA_MIN), splat(0.f), al);
                const vi valid = listed & (al > splat(0.f));
                if (!any_lane(valid)) continue;
                vf s = gdep[v] * z + galp[v];
                for (int c = 0; c < C; ++c) s += gcol[c][v] * col[c];
                const vf t = T[v];
                const vf w = select(valid, al * t, splat(0.f));
                prefix[v] += w * s;
                // d out / d alpha_i = T_i s_i - (sum_{j > i} w_j s_j) / (1 - alpha_i)
                const vf dal = t * s - (stot[v] - prefix[v]) / (splat(1.f) - al);
                const vf ga = select(valid & (a <= splat(ALPHA_MAX)), dal, splat(0.f));
                T[v] = select(valid, t - al * t, t);
                if (GC)
                    for (int c = 0; c < C; ++c) acc_c[c] += w * gcol[c][v];
                acc_d += w * gdep[v];
                grad_footprint<MODE, GO>(g, S, py, cp, ep, xp, ga, &acc);
            }
        }
        float sums[6] = {hsum(acc.g0), hsum(acc.g1), hsum(acc.g2), hsum(acc.g3), hsum(acc.g4), hsum(acc.go)};
        float* rec = records + (int64_t)j * REC;
        if (MODE == MODE_CENTRE || (MODE == MODE_EAA && g.nodes <= 1))
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
    TORCH_CHECK(t.size(0) == dim0, "mipslam cpu rasterizer: ", name, " has the wrong length");
    if (dim1 >= 0)
        TORCH_CHECK(t.dim() >= 2 && t.size(1) == dim1, "mipslam cpu rasterizer: ", name, " has the wrong shape");
}

struct Prepared {
    std::vector<Gauss> gauss;
    at::Tensor tile_offsets, isect_gauss, gauss_offsets, isect_pos;
    int tiles_x, tiles_y;
};

static Prepared prepare(const at::Tensor& means2d, const at::Tensor& cov, const at::Tensor& opacity,
                        const at::Tensor& depth, const at::Tensor& node_counts, int mode, float k, int width,
                        int height, int threads) {
    const int64_t n = means2d.size(0);
    Prepared out;
    out.tiles_x = (width + TILE - 1) / TILE;
    out.tiles_y = (height + TILE - 1) / TILE;
    const int64_t num_tiles = (int64_t)out.tiles_x * out.tiles_y;
    out.gauss.resize(n);
    std::vector<int64_t> count(n + 1, 0);
    const float* m = means2d.data_ptr<float>();
    const float* cv = cov.data_ptr<float>();
    const float* op = opacity.data_ptr<float>();
    const float* dp = depth.data_ptr<float>();
    const int32_t* nc = node_counts.data_ptr<int32_t>();
    Gauss* gs = out.gauss.data();
#pragma omp parallel for schedule(static) num_threads(threads)
    for (int64_t i = 0; i < n; ++i) {
        bool drawn = false;
        gs[i] = setup_gaussian(mode, k, m + 2 * i, cv + 4 * i, op[i], dp[i], nc[i], width, height, &drawn);
        count[i] = drawn ? (int64_t)(gs[i].px1 / TILE - gs[i].px0 / TILE + 1) * (gs[i].py1 / TILE - gs[i].py0 / TILE + 1)
                         : 0;
    }
    // Per-Gaussian ranges of pairs (row-major over its tiles).
    out.gauss_offsets = at::empty({n + 1}, at::kInt);
    int32_t* goff = out.gauss_offsets.data_ptr<int32_t>();
    int64_t total = 0;
    for (int64_t i = 0; i < n; ++i) {
        goff[i] = (int32_t)total;
        total += count[i];
        TORCH_CHECK(total < (int64_t)std::numeric_limits<int32_t>::max(),
                    "mipslam cpu rasterizer: more than 2^31 (tile, Gaussian) pairs; render at a lower resolution");
    }
    goff[n] = (int32_t)total;
    // Depth order (stable: ties keep the input order), then counting sort by tile keeps it per tile.
    std::vector<int32_t> order;
    order.reserve(n);
    for (int64_t i = 0; i < n; ++i)
        if (count[i] > 0) order.push_back((int32_t)i);
    std::stable_sort(order.begin(), order.end(), [&](int32_t a, int32_t b) { return dp[a] < dp[b]; });
    out.tile_offsets = at::zeros({num_tiles + 1}, at::kInt);
    int32_t* toff = out.tile_offsets.data_ptr<int32_t>();
    for (int32_t i : order) {
        const Gauss& g = gs[i];
        for (int ty = g.py0 / TILE; ty <= g.py1 / TILE; ++ty)
            for (int tx = g.px0 / TILE; tx <= g.px1 / TILE; ++tx) toff[(int64_t)ty * out.tiles_x + tx + 1] += 1;
    }
    for (int64_t t = 0; t < num_tiles; ++t) toff[t + 1] += toff[t];
    out.isect_gauss = at::empty({total}, at::kInt);
    out.isect_pos = at::empty({total}, at::kInt);
    int32_t* ig = out.isect_gauss.data_ptr<int32_t>();
    int32_t* ip = out.isect_pos.data_ptr<int32_t>();
    std::vector<int32_t> cursor(toff, toff + num_tiles);
    for (int32_t i : order) {
        const Gauss& g = gs[i];
        int32_t kk = goff[i];
        for (int ty = g.py0 / TILE; ty <= g.py1 / TILE; ++ty)
            for (int tx = g.px0 / TILE; tx <= g.px1 / TILE; ++tx) {
                const int32_t pos = cursor[(int64_t)ty * out.tiles_x + tx]++;
                ig[pos] = i;
                ip[kk++] = pos;
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

static void check_inputs(const at::Tensor& means2d, const at::Tensor& cov, const at::Tensor& opacity,
                         const at::Tensor& depth, const at::Tensor& colors, const at::Tensor& node_counts,
                         int64_t mode, const at::Tensor& gl_nodes, const at::Tensor& gl_weights) {
    const int64_t n = means2d.size(0);
    check_tensor(means2d, "means2d", at::kFloat, n, 2);
    check_tensor(cov, "cov", at::kFloat, n, 4);
    check_tensor(opacity, "opacity", at::kFloat, n, -1);
    check_tensor(depth, "depth", at::kFloat, n, -1);
    check_tensor(colors, "colors", at::kFloat, n, colors.size(1));
    check_tensor(node_counts, "node_counts", at::kInt, n, -1);
    check_tensor(gl_nodes, "gl_nodes", at::kFloat, gl_nodes.size(0), -1);
    check_tensor(gl_weights, "gl_weights", at::kFloat, gl_nodes.size(0), -1);
    TORCH_CHECK(mode >= 0 && mode <= 2, "mipslam cpu rasterizer: unknown mode ", mode);
    TORCH_CHECK(gl_nodes.size(0) >= 1 && gl_nodes.size(0) <= MAX_ROWS,
                "mipslam cpu rasterizer: exact order must be in [1, ", MAX_ROWS, "]");
    if (n > 0 && mode == MODE_EAA) {
        const int32_t* nc = node_counts.data_ptr<int32_t>();
        for (int64_t i = 0; i < n; ++i)
            TORCH_CHECK(nc[i] >= 1 && nc[i] <= MAX_ROWS, "mipslam cpu rasterizer: EAA node counts must be in [1, ",
                        MAX_ROWS, "]");
    }
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

std::vector<at::Tensor> rasterize_forward(const at::Tensor& means2d, const at::Tensor& cov,
                                          const at::Tensor& opacity, const at::Tensor& depth,
                                          const at::Tensor& colors, const at::Tensor& node_counts, int64_t mode,
                                          int64_t width, int64_t height, double k_sigma, double eta, double tau,
                                          const at::Tensor& gl_nodes, const at::Tensor& gl_weights,
                                          int64_t threads) {
    check_inputs(means2d, cov, opacity, depth, colors, node_counts, mode, gl_nodes, gl_weights);
    TORCH_CHECK(width >= 1 && height >= 1, "mipslam cpu rasterizer: image size must be positive");
    const int64_t C = colors.size(1);
    at::Tensor color = at::zeros({height, width, C}, at::kFloat);
    at::Tensor depth_img = at::zeros({height, width}, at::kFloat);
    at::Tensor alpha_img = at::zeros({height, width}, at::kFloat);
    at::Tensor last = at::zeros({height, width}, at::kInt);
    at::Tensor stats = at::zeros({2}, at::kLong);
    Prepared prep;
    {
        pybind11::gil_scoped_release no_gil;
        prep = prepare(means2d, cov, opacity, depth, node_counts, (int)mode, (float)k_sigma, (int)width,
                       (int)height, (int)threads);
        Scene sc{(int)width, (int)height, prep.tiles_x, prep.tiles_y, (int)C,
                 make_settings((int)mode, k_sigma, eta, tau, gl_nodes, gl_weights), prep.gauss.data(),
                 colors.data_ptr<float>(), prep.tile_offsets.data_ptr<int32_t>(),
                 prep.isect_gauss.data_ptr<int32_t>()};
        int64_t lanes = 0;
        MIPSLAM_DISPATCH_CHANNELS(C, lanes = run_forward<CH>(sc, (int)threads, color.data_ptr<float>(),
                                                           depth_img.data_ptr<float>(), alpha_img.data_ptr<float>(),
                                                           last.data_ptr<int32_t>()));
        stats.data_ptr<int64_t>()[0] = lanes;
        stats.data_ptr<int64_t>()[1] = prep.isect_gauss.size(0);
    }
    return {color, depth_img, alpha_img, prep.tile_offsets, prep.isect_gauss, prep.gauss_offsets, prep.isect_pos,
            last, stats};
}

std::vector<at::Tensor> rasterize_backward(
    const at::Tensor& means2d, const at::Tensor& cov, const at::Tensor& opacity, const at::Tensor& depth,
    const at::Tensor& colors, const at::Tensor& node_counts, int64_t mode, int64_t width, int64_t height,
    double k_sigma, double eta, double tau, const at::Tensor& gl_nodes, const at::Tensor& gl_weights,
    const at::Tensor& tile_offsets, const at::Tensor& isect_gauss, const at::Tensor& gauss_offsets,
    const at::Tensor& isect_pos, const at::Tensor& last, const at::Tensor& color, const at::Tensor& depth_img,
    const at::Tensor& alpha_img, const at::Tensor& grad_color, const at::Tensor& grad_depth,
    const at::Tensor& grad_alpha, bool need_color_grad, bool need_opacity_grad, int64_t threads) {
    check_inputs(means2d, cov, opacity, depth, colors, node_counts, mode, gl_nodes, gl_weights);
    const int64_t n = means2d.size(0), C = colors.size(1);
    const int64_t num_tiles = ((width + TILE - 1) / TILE) * ((height + TILE - 1) / TILE);
    check_tensor(tile_offsets, "tile_offsets", at::kInt, num_tiles + 1, -1);
    check_tensor(gauss_offsets, "gauss_offsets", at::kInt, n + 1, -1);
    const int64_t total = isect_gauss.size(0);
    check_tensor(isect_gauss, "isect_gauss", at::kInt, total, -1);
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
        const int tiles_x = (int)((width + TILE - 1) / TILE), tiles_y = (int)((height + TILE - 1) / TILE);
        // Re-create the per-Gaussian set-up (cheap, identical to the forward's).
        std::vector<Gauss> gauss(n);
        const float* m = means2d.data_ptr<float>();
        const float* cv = cov.data_ptr<float>();
        const float* op = opacity.data_ptr<float>();
        const float* dp = depth.data_ptr<float>();
        const int32_t* nc = node_counts.data_ptr<int32_t>();
        Gauss* gs = gauss.data();
#pragma omp parallel for schedule(static) num_threads((int)threads)
        for (int64_t i = 0; i < n; ++i) {
            bool drawn = false;
            gs[i] = setup_gaussian((int)mode, (float)k_sigma, m + 2 * i, cv + 4 * i, op[i], dp[i], nc[i], (int)width,
                                   (int)height, &drawn);
        }
        Scene sc{(int)width, (int)height, tiles_x, tiles_y, (int)C,
                 make_settings((int)mode, k_sigma, eta, tau, gl_nodes, gl_weights), gauss.data(),
                 colors.data_ptr<float>(), tile_offsets.data_ptr<int32_t>(), isect_gauss.data_ptr<int32_t>()};
        GradInputs gin{grad_color.data_ptr<float>(), grad_depth.data_ptr<float>(), grad_alpha.data_ptr<float>(),
                       color.data_ptr<float>(), depth_img.data_ptr<float>(), alpha_img.data_ptr<float>(),
                       last.data_ptr<int32_t>()};
        const int64_t rec = 8 + C;
        std::vector<float> records((size_t)(total * rec));
        MIPSLAM_DISPATCH_CHANNELS(C, run_backward<CH>(sc, (int)threads, gin, records.data(), need_color_grad,
                                                      need_opacity_grad));
        // Deterministic reduction: each Gaussian sums its pairs in tile order.
        const int32_t* goff = gauss_offsets.data_ptr<int32_t>();
        const int32_t* ip = isect_pos.data_ptr<int32_t>();
        float* gm = g_means2d.data_ptr<float>();
        float* gc = g_cov.data_ptr<float>();
        float* go = g_opacity.data_ptr<float>();
        float* gd = g_depth.data_ptr<float>();
        float* gcol = g_colors.data_ptr<float>();
        const float* rp = records.data();
#pragma omp parallel for schedule(static) num_threads((int)threads)
        for (int64_t i = 0; i < n; ++i) {
            float acc[8 + 64] = {};
            for (int32_t q = goff[i]; q < goff[i + 1]; ++q) {
                const float* r = rp + (int64_t)ip[q] * rec;
                for (int64_t e = 0; e < rec; ++e) acc[e] += r[e];
            }
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

// Test hooks: the vector exp / erf on a float tensor (any length).
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
    m.def("vector_math", &mipslam_cpu::vector_math);
    m.def("build_info", &mipslam_cpu::build_info);
}
