// Per-pixel footprint of one projected Gaussian on 8 pixels at once, forward and hand-written backward.
//
// This is a line-by-line port of mipslam/render/footprint.py (docs/renderer.md sections 2-2.3) to the
// 8-lane vectors of simd_math.h. The 2D covariance arrives as (xx, xy, yy, det) in px^2 / px^4 (det
// from the projection's Cauchy-Binet formula, an input of its own), already dilated for the
// centre-sample modes by footprint.footprint_parameters on the torch side. Gradients are returned with
// respect to exactly those inputs: mean (x, y), xx, xy, yy, det, opacity (the torch side chains
// them to the 3D parameters and the viewmat through autograd).
//
// The backward of every footprint accumulates, over the pixels of a tile, a handful of per-Gaussian
// sums (vector accumulators) from which the gradient of the inputs is formed once per
// (Gaussian, tile) pair in finalize_*: the chain rule through per-Gaussian constants is applied to
// sums, not to every pixel.
#pragma once

#include <cmath>
#include <cstdint>

#include "simd_math.h"

namespace mipslam_cpu {

constexpr float ALPHA_MAX = 0.99f;
constexpr float ALPHA_MIN = 1.0f / 255.0f;
constexpr float TRANSMITTANCE_MIN = 1e-4f;
constexpr float SQRT_2PI = 2.5066282746310002f;
constexpr float INV_SQRT_2PI = 0.3989422804014327f;
constexpr float INV_SQRT2 = 0.7071067811865476f;
constexpr int MAX_ROWS = 64;  // cap of EAA nodes and of the exact-mode Gauss-Legendre order

enum Mode : int { MODE_CENTRE = 0, MODE_EAA = 1, MODE_EXACT = 2 };

// One projected Gaussian, prepared once per call (setup_gaussian in raster_ext.cpp). The first cache
// line holds everything the centre-sample modes touch per pixel row.
struct alignas(64) Gauss {
    float mx, my;          // centre, px
    float qa, qb, qc;      // -(ca, cb, cc) log2(e) / 2 (see centre_eval)
    float opacity, depth;
    float ca, cb, cc;      // conic: maha = ca dx^2 + 2 cb dx dy + cc dy^2 (= d^T Sigma^-1 d)
    int32_t px0, px1, py0, py1;  // inclusive pixel box (clamped to the image); px0 > px1 if empty
    // --- second cache line: covariance and row frame (EAA / exact) ---
    float xx, xy, yy, det;  // sampling covariance, px^2, and its determinant, px^4
    int32_t nodes;         // EAA node count (1 = centre sample), exact: unused
    int32_t outer_y;       // row frame: 1 if the outer axis is y (yy >= xx)
    float mu_o, mu_i, var_o, sigma_o, inv_sigma_o, slope, s, inv_s, inner_lim;
};

struct Settings {
    int mode;
    float k_sigma;
    float eta, tau;
    int exact_order;
    const float* gl_nodes;    // [exact_order] on [-1, 1]
    const float* gl_weights;  // [exact_order]
};

// Five per-Gaussian sums plus opacity, filled by the *_grad functions (meaning depends on the path):
// centre: sum gm dx, sum gm dy, sum gm dx^2, sum gm dx dy, sum gm dy^2 with gm = dL/dmaha;
// rows (eaa/exact): dL/dmu_o, dL/dmu_i, dL/dsigma_o, dL/dslope, dL/ds.
struct FootAcc {
    vf g0, g1, g2, g3, g4, go;
    void zero() { g0 = g1 = g2 = g3 = g4 = go = splat(0.f); }
};

// ---------------------------------------------------------------------------------------------
// Centre sample: a = o exp(-maha/2) if maha <= k^2 else 0
// ---------------------------------------------------------------------------------------------
struct CentrePixel {
    vf dx, G, a;
};

// -maha/2 log2(e) = qa dx^2 + 2 qb dx dy + qc dy^2 with (qa, qb, qc) = -(ca, cb, cc) log2(e) / 2, so
// G = 2^(that). Inside lanes have -maha/2 >= -k^2/2; the clamp at -80 keeps the other lanes off the slow
// subnormal path (they are masked).
static inline __attribute__((always_inline)) vf centre_eval(const Gauss& g, float k2, vf px, float py,
                                                            CentrePixel* st) {
    const vf dx = px - splat(g.mx);
    const float dy = py - g.my;
    const vf t = (splat(g.qa) * dx + splat(2.f * g.qb * dy)) * dx + splat(g.qc * dy * dy);
    const vf G = vexp2_unclamped(vmax(t, splat(-80.f)));
    const vf a = keep(t >= splat(-0.5f * LOG2E * k2), splat(g.opacity) * G);
    st->dx = dx;
    st->G = G;
    st->a = a;
    return a;
}

template <bool GRAD_OPACITY>
static inline __attribute__((always_inline)) void centre_grad(const Gauss& g, float py, const CentrePixel& st,
                                                              vf ga, FootAcc* acc) {
    const vf gm = splat(-0.5f) * ga * st.a;  // dL/dmaha (a is 0 outside the cut)
    const vf dy = splat(py - g.my);
    const vf gdx = gm * st.dx;
    acc->g0 += gdx;
    acc->g1 += gm * dy;
    acc->g2 += gdx * st.dx;
    acc->g3 += gdx * dy;
    acc->g4 += gm * dy * dy;
    if (GRAD_OPACITY) acc->go += ga * keep(st.a > splat(0.f), st.G);
}

// grads[0..6] = d/d(mx, my, xx, xy, yy, det, opacity) from the summed moments.
static inline void centre_finalize(const Gauss& g, const float sums[6], float* grads) {
    const float sx = sums[0], sy = sums[1], sxx = sums[2], sxy = sums[3], syy = sums[4];
    grads[0] = -2.f * (g.ca * sx + g.cb * sy);
    grads[1] = -2.f * (g.cb * sx + g.cc * sy);
    grads[2] = syy / g.det;
    grads[3] = -2.f * sxy / g.det;
    grads[4] = sxx / g.det;
    grads[5] = -(g.ca * sxx + 2.f * g.cb * sxy + g.cc * syy) / g.det;
    grads[6] = sums[5];
}

// ---------------------------------------------------------------------------------------------
// Row frame shared by EAA and exact: the pixel's outer extent clipped to mu_o +- k sigma_o
// ---------------------------------------------------------------------------------------------
struct Band {
    vf lo, hi, zl, zh, el, eh, mass;  // el/eh = exp(-z^2/2) at the band ends; mass = M_o
    vi lo_from_mean, hm_from_mean, hi_is_lo;
};

static inline __attribute__((always_inline)) Band outer_band(const Gauss& g, float k, vf po) {
    Band b;
    const vf lo_pixel = po - splat(0.5f), lo_mean = splat(g.mu_o - k * g.sigma_o);
    b.lo_from_mean = lo_mean > lo_pixel;
    b.lo = vmax(lo_pixel, lo_mean);
    const vf hm_pixel = po + splat(0.5f), hm_mean = splat(g.mu_o + k * g.sigma_o);
    b.hm_from_mean = hm_mean < hm_pixel;
    const vf hm = vmin(hm_pixel, hm_mean);
    b.hi_is_lo = b.lo > hm;
    b.hi = vmax(hm, b.lo);
    b.zh = (b.hi - splat(g.mu_o)) * splat(g.inv_sigma_o);
    b.zl = (b.lo - splat(g.mu_o)) * splat(g.inv_sigma_o);
    vf eh2, el2;  // exp(-(z/sqrt2)^2) = exp(-z^2/2)
    const vf erf_h = verf(b.zh * splat(INV_SQRT2), &eh2);
    const vf erf_l = verf(b.zl * splat(INV_SQRT2), &el2);
    b.eh = eh2;
    b.el = el2;
    b.mass = splat(SQRT_2PI * g.sigma_o) * (splat(0.5f) * (erf_h - erf_l));
    return b;
}

// dL/dlo, dL/dhi and dL/dmass -> accumulators (mu_o, sigma_o); mass = sqrt(2pi) sigma (Phi(zh) - Phi(zl)).
static inline __attribute__((always_inline)) void outer_band_grad(const Gauss& g, float k, const Band& b, vf glo,
                                                                  vf ghi, vf gmass, vf* gmu_o, vf* gsigma) {
    const vf sig = splat(g.sigma_o), isig = splat(g.inv_sigma_o);
    const vf gzh = gmass * sig * b.eh;
    const vf gzl = -(gmass * sig * b.el);
    ghi += gzh * isig;
    glo += gzl * isig;
    *gmu_o -= (gzh + gzl) * isig;
    *gsigma += gmass * b.mass * isig - (gzh * b.zh + gzl * b.zl) * isig;
    // hi = max(min(p_o + 0.5, mu_o + k sigma), lo)
    glo += select(b.hi_is_lo, ghi, splat(0.f));
    const vf ghm = select(b.hi_is_lo | ~b.hm_from_mean, splat(0.f), ghi);
    *gmu_o += ghm;
    *gsigma += splat(k) * ghm;
    // lo = max(p_o - 0.5, mu_o - k sigma)
    const vf glm = select(b.lo_from_mean, glo, splat(0.f));
    *gmu_o += glm;
    *gsigma -= splat(k) * glm;
}

// grads[0..6] = d/d(mx, my, xx, xy, yy, det, opacity) from the row-frame sums.
static inline void rows_finalize(const Gauss& g, const float sums[6], float* grads) {
    const float gmu_o = sums[0], gmu_i = sums[1], gsigma = sums[2], gslope = sums[3], gs = sums[4];
    const float gvar_o = gsigma * 0.5f * g.inv_sigma_o - gslope * g.slope / g.var_o - gs * g.s * 0.5f / g.var_o;
    grads[3] = gslope / g.var_o;
    grads[5] = gs * 0.5f * g.inv_s / g.var_o;
    if (g.outer_y) {
        grads[0] = gmu_i;
        grads[1] = gmu_o;
        grads[2] = 0.f;
        grads[4] = gvar_o;
    } else {
        grads[0] = gmu_o;
        grads[1] = gmu_i;
        grads[2] = gvar_o;
        grads[4] = 0.f;
    }
    grads[6] = sums[5];
}

static inline __attribute__((always_inline)) void row_frame_coords(const Gauss& g, vf px, float py, vf* po,
                                                                   vf* pi) {
    if (g.outer_y) {
        *po = splat(py);
        *pi = px;
    } else {
        *po = px;
        *pi = splat(py);
    }
}

// ---------------------------------------------------------------------------------------------
// EAA with n >= 2 rows (docs/renderer.md 2.2)
// ---------------------------------------------------------------------------------------------
struct EaaPixel {
    Band band;
    vf po, pi, sw, swr, avg, a_over_o, a;
    vi inside;
    vf phi[MAX_ROWS], R[MAX_ROWS], e[MAX_ROWS], eA[MAX_ROWS], eB[MAX_ROWS];
    // outer axis = y (row-constant outer quantities): A_j = (x - ridge_j + 1/2) / (s sqrt 2) per lane and
    // the same at x - 1 (Ap_j, shared with the left neighbour; lane 0 from a scalar), em = exp(-A^2)
    vf A[MAX_ROWS], Ap[MAX_ROWS], emp[MAX_ROWS];
    float phi_s[MAX_ROWS], dy_s[MAX_ROWS], u_s[MAX_ROWS], ridge_s[MAX_ROWS];
};

// State of the row-constant EAA path for at most MR node rows (the column blocks of the transposed
// path keep eight of these at once).
template <int MR>
struct EaaLineState {
    Band band;
    vf pi, sw, swr, avg, a_over_o, a;
    vi inside;
    vf R[MR], e[MR], eA[MR], A[MR], Ap[MR], emp[MR];
    float phi_s[MR], dy_s[MR], u_s[MR], ridge_s[MR];
};
constexpr int LINE_ROWS = 8;  // node cap of the transposed (outer axis x) path

// 8x8 transpose: out[r][c] = in[c][r] (unpack, 64-bit shuffle, 128-bit swap: 24 shuffles).
static inline __attribute__((always_inline)) void transpose8(const vf in[LANES], vf out[LANES]) {
    const vi lo32 = {0, 8, 1, 9, 4, 12, 5, 13}, hi32 = {2, 10, 3, 11, 6, 14, 7, 15};
    const vi lo64 = {0, 1, 8, 9, 4, 5, 12, 13}, hi64 = {2, 3, 10, 11, 6, 7, 14, 15};
    const vi lo128 = {0, 1, 2, 3, 8, 9, 10, 11}, hi128 = {4, 5, 6, 7, 12, 13, 14, 15};
    vf t[LANES], u[LANES];
    for (int k = 0; k < 4; ++k) {
        t[2 * k] = __builtin_shuffle(in[2 * k], in[2 * k + 1], lo32);
        t[2 * k + 1] = __builtin_shuffle(in[2 * k], in[2 * k + 1], hi32);
    }
    for (int k = 0; k < 2; ++k) {
        u[4 * k + 0] = __builtin_shuffle(t[4 * k + 0], t[4 * k + 2], lo64);
        u[4 * k + 1] = __builtin_shuffle(t[4 * k + 0], t[4 * k + 2], hi64);
        u[4 * k + 2] = __builtin_shuffle(t[4 * k + 1], t[4 * k + 3], lo64);
        u[4 * k + 3] = __builtin_shuffle(t[4 * k + 1], t[4 * k + 3], hi64);
    }
    for (int k = 0; k < 4; ++k) {
        out[k] = __builtin_shuffle(u[k], u[k + 4], lo128);
        out[k + 4] = __builtin_shuffle(u[k], u[k + 4], hi128);
    }
}

// [first, v[0], ..., v[6]]: the left neighbours' values of an 8-pixel row segment.
static inline __attribute__((always_inline)) vf shift_in_first(vf v, float first) {
    vf r = __builtin_shuffle(v, vi{0, 0, 1, 2, 3, 4, 5, 6});
    r[0] = first;
    return r;
}

// outer_band for a row-constant outer coordinate po (the Band's vectors are splats). Both erf values
// come from one vector call (no libm call per row).
static inline __attribute__((always_inline)) Band outer_band_row(const Gauss& g, float k, float po) {
    const float lo_pixel = po - 0.5f, lo_mean = g.mu_o - k * g.sigma_o;
    const float hm_pixel = po + 0.5f, hm_mean = g.mu_o + k * g.sigma_o;
    const float lo = std::max(lo_pixel, lo_mean), hm = std::min(hm_pixel, hm_mean);
    const float hi = std::max(hm, lo);
    const float zh = (hi - g.mu_o) * g.inv_sigma_o, zl = (lo - g.mu_o) * g.inv_sigma_o;
    vf z = splat(zl);
    z[0] = zh;
    vf em;
    const vf E = verf(z * splat(INV_SQRT2), &em);  // em = exp(-z^2 / 2)
    Band b;
    b.lo_from_mean = splati(lo_mean > lo_pixel ? -1 : 0);
    b.hm_from_mean = splati(hm_mean < hm_pixel ? -1 : 0);
    b.hi_is_lo = splati(lo > hm ? -1 : 0);
    b.lo = splat(lo);
    b.hi = splat(hi);
    b.zh = splat(zh);
    b.zl = splat(zl);
    b.eh = splat(em[0]);
    b.el = splat(em[1]);
    b.mass = splat(SQRT_2PI * g.sigma_o * (0.5f * (E[0] - E[1])));
    return b;
}

// EAA when the outer axis is y: everything that depends on the outer coordinate only (band, outer mass,
// row positions t_j, marginal phi_j, ridge_j) is one scalar per image row, and the inner integrals of
// neighbouring pixels share their common edge: R_j(x) = (erf(A_j(x)) - erf(A_j(x - 1))) / 2, so a row
// segment of 8 pixels costs one vector erf per node row (plus one vector erf for the left edges of all
// node rows). The row part (eaa_outer_y_row) is computed once per image row and shared by the row's
// segments in a tile (eaa_outer_y_segment); eaa_eval_outer_y does both.
// px: the 8 inner coordinates (consecutive pixels), py: the outer coordinate. With the outer axis x the
// same function evaluates a column segment: px = 8 consecutive y, py = x (see forward_tile).
template <typename State>
static inline __attribute__((always_inline)) void eaa_outer_y_row(const Gauss& g, const Settings& S, float py,
                                                                  State* st) {
    st->band = outer_band_row(g, S.k_sigma, py);
    const Band& b = st->band;
    const int n = g.nodes;
    const float lo = b.lo[0], width = b.hi[0] - b.lo[0];
    const vf lane = vf{0.f, 1.f, 2.f, 3.f, 4.f, 5.f, 6.f, 7.f};
    for (int j0 = 0; j0 < n; j0 += LANES) {
        const vf f = (splat((float)j0 + 0.5f) + lane) / splat((float)n);
        const vf dy = splat(lo) + f * splat(width) - splat(g.mu_o);
        const vf u = dy * splat(g.inv_sigma_o);
        const vf phi = vexp(splat(-0.5f) * u * u);
        const vf ridge = splat(g.mu_i) + splat(g.slope) * dy;
        for (int l = 0; l < LANES && j0 + l < n; ++l) {
            st->dy_s[j0 + l] = dy[l];
            st->u_s[j0 + l] = u[l];
            st->phi_s[j0 + l] = phi[l];
            st->ridge_s[j0 + l] = ridge[l];
        }
    }
}

template <typename State>
static inline __attribute__((always_inline)) vf eaa_outer_y_segment(const Gauss& g, const Settings& S, vf px,
                                                                    State* st) {
    st->pi = px;
    const Band& b = st->band;
    const int n = g.nodes;
    const float cis = g.inv_s * INV_SQRT2;
    const float x_left = px[0] - 1.f;
    // erf / exp(-A^2) at the left edge of the segment, 8 node rows per vector
    alignas(32) float e_left[MAX_ROWS], em_left[MAX_ROWS];
    for (int j0 = 0; j0 < n; j0 += LANES) {
        vf ridge = splat(0.f);
        for (int l = 0; l < LANES && j0 + l < n; ++l) ridge[l] = st->ridge_s[j0 + l];
        vf em;
        const vf E = verf((splat(x_left + 0.5f) - ridge) * splat(cis), &em);
        for (int l = 0; l < LANES && j0 + l < n; ++l) {
            e_left[j0 + l] = E[l];
            em_left[j0 + l] = em[l];
        }
    }
    vf sw = splat(0.f), swr = splat(0.f);
    for (int j = 0; j < n; ++j) {
        const float ridge = st->ridge_s[j], phi = st->phi_s[j];
        vf em;
        const vf A = (px + splat(0.5f - ridge)) * splat(cis);
        const vf E = verf(A, &em);
        const vf R = splat(0.5f) * (E - shift_in_first(E, e_left[j]));
        vf w = splat(phi);
        if (S.eta != 0.f) {
            const vf d = vabs(splat(0.5f) - vabs(splat(ridge) - px));
            const vf e = vexp(-d * splat(1.f / S.tau));
            st->e[j] = e;
            w = splat(phi) * (splat(1.f) + splat(S.eta) * e);
        }
        st->R[j] = R;
        st->A[j] = A;
        st->Ap[j] = shift_in_first(A, (x_left + 0.5f - ridge) * cis);
        st->eA[j] = em;
        st->emp[j] = shift_in_first(em, em_left[j]);
        sw += w;
        swr += w * R;
    }
    st->sw = sw;
    st->swr = swr;
    st->avg = swr / vmax(sw, splat(1.17549435e-38f));
    st->inside = vabs(px - splat(g.mu_i)) <= splat(g.inner_lim);
    st->a_over_o = keep(st->inside, b.mass * splat(SQRT_2PI * g.s) * st->avg);
    st->a = keep(st->inside, splat(g.opacity) * b.mass * splat(SQRT_2PI * g.s) * st->avg);
    return st->a;
}

template <typename State>
static inline __attribute__((always_inline)) vf eaa_eval_outer_y(const Gauss& g, const Settings& S, vf px,
                                                                 float py, State* st) {
    eaa_outer_y_row(g, S, py, st);
    return eaa_outer_y_segment(g, S, px, st);
}

template <bool GRAD_OPACITY, typename State>
static inline __attribute__((always_inline)) void eaa_grad_outer_y(const Gauss& g, const Settings& S,
                                                                   const State& st, vf ga, FootAcc* acc) {
    const Band& b = st.band;
    ga = keep(st.inside, ga);
    if (GRAD_OPACITY) acc->go += ga * st.a_over_o;
    const vf so = splat(g.opacity * SQRT_2PI);
    const vf gmass = ga * so * splat(g.s) * st.avg;
    vf gs = ga * so * b.mass * st.avg;
    const vf gavg = ga * so * b.mass * splat(g.s);
    const vf sw_cl = vmax(st.sw, splat(1.17549435e-38f));
    const vf gswr = gavg / sw_cl;
    const vf gsw = keep(st.sw >= splat(1.17549435e-38f), -(gavg * st.avg) / sw_cl);
    const int n = g.nodes;
    const float cis = g.inv_s * INV_SQRT2;
    const vf two_over_sqrt_pi = splat(1.1283791670955126f);
    // The chain from the per-lane gradients to the row scalars is linear, so it runs lane-wise with
    // the row constants broadcast; the lanes are summed once per (Gaussian, tile).
    vf glo = splat(0.f), ghi = splat(0.f), gmu_o = splat(0.f), gmu_i = splat(0.f), gsig = splat(0.f),
       gslope = splat(0.f);
    for (int j = 0; j < n; ++j) {
        const float f = ((float)j + 0.5f) / (float)n;
        const float phi = st.phi_s[j], dy = st.dy_s[j], u = st.u_s[j];
        const vf R = st.R[j];
        vf bemph = splat(1.f);
        if (S.eta != 0.f) bemph = splat(1.f) + splat(S.eta) * st.e[j];
        const vf w = splat(phi) * bemph;
        const vf gw = gswr * R + gsw;
        const vf gR = gswr * w;
        const vf gphi = gw * bemph;
        vf gridge = splat(0.f);
        if (S.eta != 0.f) {  // d = |1/2 - |ridge - x||
            const float ridge = g.mu_i + g.slope * dy;
            const vf off = splat(ridge) - st.pi;
            const vf gd = -(gw * splat(phi * S.eta / S.tau) * st.e[j]);
            gridge -= gd * vsign(splat(0.5f) - vabs(off)) * vsign(off);
        }
        // R = (erf(A) - erf(Ap)) / 2, A = (x - ridge + 1/2) / (s sqrt 2): dA/dridge = -1/(s sqrt 2), dA/ds = -A/s
        const vf gA = splat(0.5f) * gR * two_over_sqrt_pi * st.eA[j];
        const vf gAp = -(splat(0.5f) * gR * two_over_sqrt_pi * st.emp[j]);
        gridge -= (gA + gAp) * splat(cis);
        gs -= (gA * st.A[j] + gAp * st.Ap[j]) * splat(g.inv_s);
        // ridge = mu_i + slope dy, phi = exp(-u^2/2), u = dy / sigma, dy = t - mu_o, t = lo + f (hi - lo)
        const vf gu = -(gphi * splat(phi * u));
        const vf gdy = gridge * splat(g.slope) + gu * splat(g.inv_sigma_o);
        gsig -= gu * splat(u * g.inv_sigma_o);
        gmu_i += gridge;
        gslope += gridge * splat(dy);
        gmu_o -= gdy;
        glo += gdy * splat(1.f - f);
        ghi += gdy * splat(f);
    }
    outer_band_grad(g, S.k_sigma, b, glo, ghi, gmass, &gmu_o, &gsig);
    acc->g0 += gmu_o;
    acc->g1 += gmu_i;
    acc->g2 += gsig;
    acc->g3 += gslope;
    acc->g4 += gs;
}

static inline __attribute__((always_inline)) vf eaa_eval(const Gauss& g, const Settings& S, vf px, float py,
                                                         EaaPixel* st) {
    if (g.outer_y) return eaa_eval_outer_y(g, S, px, py, st);
    vf po, pi;
    row_frame_coords(g, px, py, &po, &pi);
    st->po = po;
    st->pi = pi;
    st->band = outer_band(g, S.k_sigma, po);
    const Band& b = st->band;
    const int n = g.nodes;
    const vf width = b.hi - b.lo;
    const vf isig = splat(g.inv_sigma_o), is = splat(g.inv_s);
    vf sw = splat(0.f), swr = splat(0.f);
    for (int j = 0; j < n; ++j) {
        const float f = ((float)j + 0.5f) / (float)n;
        const vf dy = b.lo + splat(f) * width - splat(g.mu_o);
        const vf u = dy * isig;
        const vf phi = vexp(splat(-0.5f) * u * u);
        const vf off = splat(g.mu_i) + splat(g.slope) * dy - pi;
        const vf zA = (splat(0.5f) - off) * is;
        const vf zB = (splat(-0.5f) - off) * is;
        vf eA, eB;
        const vf erfA = verf(zA * splat(INV_SQRT2), &eA);
        const vf erfB = verf(zB * splat(INV_SQRT2), &eB);
        const vf R = splat(0.5f) * (erfA - erfB);
        vf w = phi;
        if (S.eta != 0.f) {
            const vf d = vabs(splat(0.5f) - vabs(off));
            const vf e = vexp(-d * splat(1.f / S.tau));
            st->e[j] = e;
            w = phi * (splat(1.f) + splat(S.eta) * e);
        }
        st->phi[j] = phi;
        st->R[j] = R;
        st->eA[j] = eA;
        st->eB[j] = eB;
        sw += w;
        swr += w * R;
    }
    st->sw = sw;
    st->swr = swr;
    st->avg = swr / vmax(sw, splat(1.17549435e-38f));
    st->inside = vabs(pi - splat(g.mu_i)) <= splat(g.inner_lim);
    st->a_over_o = select(st->inside, b.mass * splat(SQRT_2PI * g.s) * st->avg, splat(0.f));
    st->a = select(st->inside, splat(g.opacity) * b.mass * splat(SQRT_2PI * g.s) * st->avg, splat(0.f));
    return st->a;
}

template <bool GRAD_OPACITY>
static inline __attribute__((always_inline)) void eaa_grad(const Gauss& g, const Settings& S, const EaaPixel& st,
                                                           vf ga, FootAcc* acc) {
    if (g.outer_y) {
        eaa_grad_outer_y<GRAD_OPACITY>(g, S, st, ga, acc);  // State = EaaPixel
        return;
    }
    const Band& b = st.band;
    ga = select(st.inside, ga, splat(0.f));
    if (GRAD_OPACITY) acc->go += ga * st.a_over_o;
    const vf so = splat(g.opacity * SQRT_2PI);
    const vf gmass = ga * so * splat(g.s) * st.avg;
    vf gs = ga * so * b.mass * st.avg;
    const vf gavg = ga * so * b.mass * splat(g.s);
    const vf sw_cl = vmax(st.sw, splat(1.17549435e-38f));
    const vf gswr = gavg / sw_cl;
    const vf gsw = select(st.sw >= splat(1.17549435e-38f), -(gavg * st.avg) / sw_cl, splat(0.f));
    const int n = g.nodes;
    const vf width = b.hi - b.lo;
    const vf isig = splat(g.inv_sigma_o), is = splat(g.inv_s);
    vf glo = splat(0.f), ghi = splat(0.f), gmu_o = splat(0.f), gmu_i = splat(0.f), gsig = splat(0.f),
       gslope = splat(0.f);
    for (int j = 0; j < n; ++j) {
        const float f = ((float)j + 0.5f) / (float)n;
        const vf dy = b.lo + splat(f) * width - splat(g.mu_o);
        const vf u = dy * isig;
        const vf off = splat(g.mu_i) + splat(g.slope) * dy - st.pi;
        const vf zA = (splat(0.5f) - off) * is;
        const vf zB = (splat(-0.5f) - off) * is;
        const vf phi = st.phi[j], R = st.R[j];
        vf bemph = splat(1.f);
        if (S.eta != 0.f) bemph = splat(1.f) + splat(S.eta) * st.e[j];
        const vf w = phi * bemph;
        const vf gw = gswr * R + gsw;
        const vf gR = gswr * w;
        const vf gphi = gw * bemph;
        vf goff = splat(0.f);
        if (S.eta != 0.f) {
            const vf gd = -(gw * phi * splat(S.eta / S.tau) * st.e[j]);
            const vf q = splat(0.5f) - vabs(off);
            goff -= gd * vsign(q) * vsign(off);
        }
        const vf gzA = gR * st.eA[j] * splat(INV_SQRT_2PI);
        const vf gzB = -(gR * st.eB[j] * splat(INV_SQRT_2PI));
        goff -= (gzA + gzB) * is;
        gs -= (gzA * zA + gzB * zB) * is;
        const vf gu = -(gphi * phi * u);
        vf gdy = gu * isig;
        gsig -= gu * u * isig;
        gmu_i += goff;
        gslope += goff * dy;
        gdy += goff * splat(g.slope);
        gmu_o -= gdy;
        glo += gdy * splat(1.f - f);
        ghi += gdy * splat(f);
    }
    outer_band_grad(g, S.k_sigma, b, glo, ghi, gmass, &gmu_o, &gsig);
    acc->g0 += gmu_o;
    acc->g1 += gmu_i;
    acc->g2 += gsig;
    acc->g3 += gslope;
    acc->g4 += gs;
}

// ---------------------------------------------------------------------------------------------
// Exact: Gauss-Legendre Q x Q in the row frame, k = 6 (docs/renderer.md 2.3)
// ---------------------------------------------------------------------------------------------
constexpr float EXACT_K = 6.0f;

struct ExactPixel {
    Band band;
    vf po, pi, sum;
    vf outer[MAX_ROWS], inner[MAX_ROWS];
};

static inline __attribute__((always_inline)) vf exact_eval(const Gauss& g, const Settings& S, vf px, float py,
                                                           ExactPixel* st) {
    vf po, pi;
    row_frame_coords(g, px, py, &po, &pi);
    st->po = po;
    st->pi = pi;
    // The band needs no erf here (exact integrates G itself); outer_band's mass is unused.
    Band b;
    const vf lo_pixel = po - splat(0.5f), lo_mean = splat(g.mu_o - EXACT_K * g.sigma_o);
    b.lo_from_mean = lo_mean > lo_pixel;
    b.lo = vmax(lo_pixel, lo_mean);
    const vf hm_pixel = po + splat(0.5f), hm_mean = splat(g.mu_o + EXACT_K * g.sigma_o);
    b.hm_from_mean = hm_mean < hm_pixel;
    const vf hm = vmin(hm_pixel, hm_mean);
    b.hi_is_lo = b.lo > hm;
    b.hi = vmax(hm, b.lo);
    st->band = b;
    const int Q = S.exact_order;
    const vf half_o = splat(0.5f) * (b.hi - b.lo), mid_o = splat(0.5f) * (b.hi + b.lo);
    const vf isig = splat(g.inv_sigma_o), is = splat(g.inv_s);
    const float s6 = EXACT_K * g.s;
    vf sum = splat(0.f);
    for (int j = 0; j < Q; ++j) {
        const vf dy = mid_o + half_o * splat(S.gl_nodes[j]) - splat(g.mu_o);
        const vf u = dy * isig;
        const vf outer = splat(S.gl_weights[j]) * half_o * vexp(splat(-0.5f) * u * u);
        const vf ridge = splat(g.mu_i) + splat(g.slope) * dy;
        const vf lo_i = vmax(pi - splat(0.5f), ridge - splat(s6));
        const vf hi_i = vmax(vmin(pi + splat(0.5f), ridge + splat(s6)), lo_i);
        const vf half_i = splat(0.5f) * (hi_i - lo_i), mid_i = splat(0.5f) * (hi_i + lo_i);
        vf inner = splat(0.f);
        for (int l = 0; l < Q; ++l) {
            const vf v = (mid_i + half_i * splat(S.gl_nodes[l]) - ridge) * is;
            inner += splat(S.gl_weights[l]) * half_i * vexp(splat(-0.5f) * v * v);
        }
        st->outer[j] = outer;
        st->inner[j] = inner;
        sum += outer * inner;
    }
    st->sum = sum;
    return splat(g.opacity) * sum;
}

template <bool GRAD_OPACITY>
static inline __attribute__((always_inline)) void exact_grad(const Gauss& g, const Settings& S,
                                                             const ExactPixel& st, vf ga, FootAcc* acc) {
    const Band& b = st.band;
    if (GRAD_OPACITY) acc->go += ga * st.sum;
    const vf gsum = ga * splat(g.opacity);
    const int Q = S.exact_order;
    const vf half_o = splat(0.5f) * (b.hi - b.lo), mid_o = splat(0.5f) * (b.hi + b.lo);
    const vf isig = splat(g.inv_sigma_o), is = splat(g.inv_s);
    const float s6 = EXACT_K * g.s;
    vf gmid_o = splat(0.f), ghalf_o = splat(0.f), gmu_o = splat(0.f), gmu_i = splat(0.f), gsig = splat(0.f),
       gslope = splat(0.f), gs = splat(0.f);
    for (int j = 0; j < Q; ++j) {
        const float xj = S.gl_nodes[j], wj = S.gl_weights[j];
        const vf dy = mid_o + half_o * splat(xj) - splat(g.mu_o);
        const vf u = dy * isig;
        const vf E = vexp(splat(-0.5f) * u * u);
        const vf ridge = splat(g.mu_i) + splat(g.slope) * dy;
        const vf lo_pix = st.pi - splat(0.5f), lo_rid = ridge - splat(s6);
        const vi lo_from_ridge = lo_rid > lo_pix;
        const vf lo_i = vmax(lo_pix, lo_rid);
        const vf hm_pix = st.pi + splat(0.5f), hm_rid = ridge + splat(s6);
        const vi hm_from_ridge = hm_rid < hm_pix;
        const vf hm = vmin(hm_pix, hm_rid);
        const vi hi_is_lo = lo_i > hm;
        const vf hi_i = vmax(hm, lo_i);
        const vf half_i = splat(0.5f) * (hi_i - lo_i), mid_i = splat(0.5f) * (hi_i + lo_i);
        const vf ginner = gsum * st.outer[j];
        const vf gouter = gsum * st.inner[j];
        vf ghalf_i = splat(0.f), gmid_i = splat(0.f), gridge = splat(0.f);
        for (int l = 0; l < Q; ++l) {
            const float xl = S.gl_nodes[l], wl = S.gl_weights[l];
            const vf v = (mid_i + half_i * splat(xl) - ridge) * is;
            const vf F = vexp(splat(-0.5f) * v * v);
            ghalf_i += ginner * splat(wl) * F;
            const vf gF = ginner * splat(wl) * half_i;
            const vf gv = -(gF * F * v);
            const vf gx = gv * is;
            gridge -= gx;
            gs -= gv * v * is;
            gmid_i += gx;
            ghalf_i += gx * splat(xl);
        }
        // mid_i = (hi_i + lo_i)/2, half_i = (hi_i - lo_i)/2
        vf ghi_i = splat(0.5f) * (gmid_i + ghalf_i);
        vf glo_i = splat(0.5f) * (gmid_i - ghalf_i);
        glo_i += select(hi_is_lo, ghi_i, splat(0.f));
        const vf ghm = select(hi_is_lo | ~hm_from_ridge, splat(0.f), ghi_i);
        gridge += ghm;
        gs += splat(EXACT_K) * ghm;
        const vf glr = select(lo_from_ridge, glo_i, splat(0.f));
        gridge += glr;
        gs -= splat(EXACT_K) * glr;
        // ridge = mu_i + slope dy
        gmu_i += gridge;
        gslope += gridge * dy;
        vf gdy = gridge * splat(g.slope);
        // outer = w_j half_o E
        ghalf_o += gouter * splat(wj) * E;
        const vf gE = gouter * splat(wj) * half_o;
        const vf gu = -(gE * E * u);
        gdy += gu * isig;
        gsig -= gu * u * isig;
        gmu_o -= gdy;
        gmid_o += gdy;
        ghalf_o += gdy * splat(xj);
    }
    vf glo = splat(0.5f) * (gmid_o - ghalf_o);
    const vf ghi = splat(0.5f) * (gmid_o + ghalf_o);
    glo += select(b.hi_is_lo, ghi, splat(0.f));
    const vf ghm = select(b.hi_is_lo | ~b.hm_from_mean, splat(0.f), ghi);
    gmu_o += ghm;
    gsig += splat(EXACT_K) * ghm;
    const vf glm = select(b.lo_from_mean, glo, splat(0.f));
    gmu_o += glm;
    gsig -= splat(EXACT_K) * glm;
    acc->g0 += gmu_o;
    acc->g1 += gmu_i;
    acc->g2 += gsig;
    acc->g3 += gslope;
    acc->g4 += gs;
}

}  // namespace mipslam_cpu
