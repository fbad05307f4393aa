// Fused EWA projection of 3D Gaussians with the footprint parameters of a mode, forward and
// hand-written backward (docs/renderer_cpu.md, section "Fused projection").
//
// One pass per Gaussian does what the torch reference does in ~100 tensor operations:
//   mipslam/render/projection.py   project_gaussians (robustness rules, EWA, Cauchy-Binet det,
//                                  COV_FLOOR, FOV-clamped Jacobian, 3D filter, visibility),
//   mipslam/render/footprint.py    footprint_parameters (dilation, energy factor), eaa_node_counts,
//   mipslam/render/__init__.py     radii of rasterize_torch,
// in the same floating-point operation order as the reference wherever it matters, so the results
// agree to a few ulps. Templated on the scalar type: float for rendering, double for gradchecks.
//
// Backward: the chain rule of exactly that computation (including torch's conventions at the kinks:
// clamp passes the gradient on its closed interval, maximum/minimum split it at ties), written out per
// Gaussian. The viewmat gradient is reduced over Gaussians in fixed blocks of rows, each block summed
// in double in row order and the blocks summed in block order, so the result is bitwise identical for
// any thread count and schedule.
#pragma once

#include "check.h"

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <limits>
#include <vector>

#ifdef _OPENMP
#include <omp.h>
#endif

namespace mipslam_cpu {

// Layout of the `params` vector passed from Python (mipslam/render/cpu/__init__.py, _projection_params).
enum ProjectionParam : int {
    P_NEAR = 0,
    P_FAR,
    P_EXTENT_SIGMA,
    P_EXTENT_PAD,
    P_EXTENT_DILATION,
    P_FILTER_SCALE,  // 0 = off
    P_DILATION,      // the mode's 2D dilation (px^2), 0 for eaa/exact
    P_DILATION_SQ,   // dilation * dilation, computed in double as the reference does
    P_ENERGY,        // 1: opacity times sqrt(det / det_dilated) (mip, ewa)
    P_EAA,           // 1: compute EAA node counts
    P_MAX_NODES,
    P_GAMMA,
    P_SINGLE_NODE_SIGMA,  // EAA: minor-axis std-dev (px) from which a Gaussian takes 1 node
    P_BOX_VARIANCE,       // EAA: variance of the unit pixel box (1/12 px^2), added to a 1-node Gaussian
    P_RADIUS_SIGMA,
    P_RADIUS_PAD,
    P_COV_FLOOR,
    P_COV_FLOOR_SQ,
    P_FOV_MARGIN,
    P_MAX_SIGMA_PX,
    P_MAX_TANGENT,
    P_COUNT
};

// Rows per block of the deterministic viewmat reduction (independent of the thread count).
constexpr int64_t PROJECTION_BLOCK = 256;
// Below this many Gaussians the projection runs on one thread (an OpenMP region costs more than it saves).
constexpr int64_t PROJECTION_PARALLEL_MIN = 4096;

template <typename T>
struct ProjectionSettings {
    T fx, fy, cx, cy;
    T W[3][3], t[3];  // rotation and translation of viewmat (world to camera)
    int width, height;
    T lim_x_pos, lim_x_neg, lim_y_pos, lim_y_neg;  // FOV clamp of the Jacobian's direction
    T focal_max, focal_max_abs;
    T near_plane, far_plane, max_tangent, max_sigma_px, cov_floor, cov_floor_sq;
    T extent_sigma, extent_pad, extent_dilation;
    bool filter;
    T filter_scale;
    const T* sampling_rate;  // [N] px/m, or nullptr: max(fx, fy) / z
    T dilation, dilation_sq;
    bool energy, eaa;
    int max_nodes;
    T gamma, single_node_var;   // single_node_var = single_node_sigma^2 (px^2)
    T box_variance, box_variance_sq;
    T radius_sigma, radius_pad;
};

template <typename T>
struct ProjectionInputs {
    const T *means, *quats, *scales, *opacities, *colors;  // [N,3] [N,4] [N,3] [N] [N,C]
    int64_t n, channels;
};

// Everything the backward needs about one Gaussian (recomputed there, never stored).
template <typename T>
struct ProjectedRow {
    bool visible;
    T m[3], q[4], s[3];    // inputs (replaced rows: harmless values)
    T o_raw, o_clamped, o;  // opacity as given, clamped to [0, 1], times the 3D filter factor
    T qnorm, qn[4], R[3][3];
    T p[3], z, u, v;  // camera-frame centre, pixel centre
    T rx, ry, tx, ty, dtx, dty;  // direction, clamped direction and d(clamped)/d(direction) (torch's tie rule)
    T J00, J02, J11, J12;
    T nu, var3d, s2[3], f2[3], r[3], P, sqrtP, stdv[3];  // 3D filter (stdv = scales when off)
    T A[2][3], B[3][3], M[2][3];  // A = J W, B = R diag(std), M = A B
    T c00, c01, c11, c, c4, Mn[2][3], mn[3];
    T xx, xy, yy, det;  // Sigma2D with the floor, det by Cauchy-Binet
};

template <typename T>
static inline bool finite_all(const T* x, int64_t count) {
    bool ok = true;
    for (int64_t k = 0; k < count; ++k) ok = ok && std::isfinite(x[k]);
    return ok;
}

// d min(max(x, lo), hi) / dx with torch's conventions (maximum/minimum: half the gradient at a tie).
template <typename T>
static inline T clamp_derivative(T x, T lo, T hi, T* clamped) {
    const T a = std::max(x, lo);  // torch.maximum(x, lo)
    const T da = x > lo ? T(1) : (x == lo ? T(0.5) : T(0));
    const T b = std::min(a, hi);
    const T db = a < hi ? T(1) : (a == hi ? T(0.5) : T(0));
    *clamped = b;
    return da * db;
}

// Forward of one Gaussian: the reference's projection up to (and including) the visibility test.
template <typename T>
static inline void project_row(const ProjectionSettings<T>& S, const ProjectionInputs<T>& in, int64_t i,
                               ProjectedRow<T>* r) {
    const T* mi = in.means + 3 * i;
    const T* qi = in.quats + 4 * i;
    const T* si = in.scales + 3 * i;
    const T oi = in.opacities[i];
    bool keep = finite_all(mi, 3) && finite_all(qi, 4) && finite_all(si, 3) && std::isfinite(oi) &&
                finite_all(in.colors + in.channels * i, in.channels);
    const T qn2 = qi[0] * qi[0] + qi[1] * qi[1] + qi[2] * qi[2] + qi[3] * qi[3];
    const T qnorm_in = std::sqrt(qn2);
    keep = keep && qnorm_in > T(0) && std::isfinite(qnorm_in);
    for (int k = 0; k < 3; ++k) {
        r->m[k] = keep ? mi[k] : T(0);
        r->s[k] = keep ? si[k] : T(1);
    }
    for (int k = 0; k < 4; ++k) r->q[k] = keep ? qi[k] : T(1);
    r->o_raw = keep ? oi : T(0);
    r->o_clamped = std::min(std::max(r->o_raw, T(0)), T(1));

    for (int j = 0; j < 3; ++j)
        r->p[j] = S.W[j][0] * r->m[0] + S.W[j][1] * r->m[1] + S.W[j][2] * r->m[2] + S.t[j];
    // Rows the arithmetic below can take without overflow (projection.py): others get a harmless row.
    const T z_raw = r->p[2];
    const T z_pos = std::max(z_raw, S.near_plane);
    const T smax = std::max(std::max(std::abs(r->s[0]), std::abs(r->s[1])), std::abs(r->s[2]));
    const T sigma_px_bound = smax * S.focal_max_abs / z_pos;
    const bool in_range = z_raw > S.near_plane && z_raw < S.far_plane && finite_all(r->p, 3) &&
                          std::abs(r->p[0]) < S.max_tangent * z_pos && std::abs(r->p[1]) < S.max_tangent * z_pos &&
                          sigma_px_bound < S.max_sigma_px;
    keep = keep && in_range;
    if (!keep) {
        r->p[0] = T(0);
        r->p[1] = T(0);
        r->p[2] = T(1);
        r->s[0] = r->s[1] = r->s[2] = T(1);
    }
    const T z = r->p[2];
    r->z = z;
    r->u = S.fx * r->p[0] / z + S.cx;
    r->v = S.fy * r->p[1] / z + S.cy;
    r->rx = r->p[0] / z;
    r->ry = r->p[1] / z;
    r->dtx = clamp_derivative(r->rx, -S.lim_x_neg, S.lim_x_pos, &r->tx);
    r->dty = clamp_derivative(r->ry, -S.lim_y_neg, S.lim_y_pos, &r->ty);
    r->J00 = S.fx / z;
    r->J02 = -S.fx * r->tx / z;
    r->J11 = S.fy / z;
    r->J12 = -S.fy * r->ty / z;

    r->o = r->o_clamped;
    for (int k = 0; k < 3; ++k) r->stdv[k] = r->s[k];
    if (S.filter) {
        r->nu = S.sampling_rate != nullptr ? S.sampling_rate[i] : S.focal_max / z;
        r->var3d = S.filter_scale / (r->nu * r->nu);
        for (int k = 0; k < 3; ++k) {
            r->s2[k] = r->s[k] * r->s[k];
            r->f2[k] = r->s2[k] + r->var3d;
            r->r[k] = r->s2[k] / r->f2[k];
            r->stdv[k] = std::sqrt(r->f2[k]);
        }
        r->P = r->r[0] * r->r[1] * r->r[2];
        r->sqrtP = std::sqrt(r->P);
        r->o = r->o_clamped * r->sqrtP;
    }

    // R of the normalised quaternion (geometry.se3.quat_wxyz_to_rotmat)
    const T* q = r->q;
    const T qnorm = std::max(std::sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]),
                             std::numeric_limits<T>::min());
    r->qnorm = qnorm;
    for (int k = 0; k < 4; ++k) r->qn[k] = q[k] / qnorm;
    const T w = r->qn[0], x = r->qn[1], y = r->qn[2], zq = r->qn[3];
    r->R[0][0] = 1 - 2 * (y * y + zq * zq);
    r->R[0][1] = 2 * (x * y - w * zq);
    r->R[0][2] = 2 * (x * zq + w * y);
    r->R[1][0] = 2 * (x * y + w * zq);
    r->R[1][1] = 1 - 2 * (x * x + zq * zq);
    r->R[1][2] = 2 * (y * zq - w * x);
    r->R[2][0] = 2 * (x * zq - w * y);
    r->R[2][1] = 2 * (y * zq + w * x);
    r->R[2][2] = 1 - 2 * (x * x + y * y);

    // M = (J W)(R diag(std)), Sigma2D = M M^T
    for (int c = 0; c < 3; ++c) {
        r->A[0][c] = r->J00 * S.W[0][c] + r->J02 * S.W[2][c];
        r->A[1][c] = r->J11 * S.W[1][c] + r->J12 * S.W[2][c];
    }
    for (int k = 0; k < 3; ++k)
        for (int c = 0; c < 3; ++c) r->B[k][c] = r->R[k][c] * r->stdv[c];
    for (int a = 0; a < 2; ++a)
        for (int c = 0; c < 3; ++c)
            r->M[a][c] = r->A[a][0] * r->B[0][c] + r->A[a][1] * r->B[1][c] + r->A[a][2] * r->B[2][c];
    const auto& M = r->M;
    r->c00 = M[0][0] * M[0][0] + M[0][1] * M[0][1] + M[0][2] * M[0][2];
    r->c01 = M[0][0] * M[1][0] + M[0][1] * M[1][1] + M[0][2] * M[1][2];
    r->c11 = M[1][0] * M[1][0] + M[1][1] * M[1][1] + M[1][2] * M[1][2];
    // det by Cauchy-Binet on M / c (c = largest |entry|, a constant for the gradient): no product overflows.
    T cmax = T(0);
    for (int a = 0; a < 2; ++a)
        for (int c = 0; c < 3; ++c) cmax = std::max(cmax, std::abs(M[a][c]));
    r->c = std::max(cmax, std::numeric_limits<T>::min());
    for (int a = 0; a < 2; ++a)
        for (int c = 0; c < 3; ++c) r->Mn[a][c] = M[a][c] / r->c;
    const auto& Mn = r->Mn;
    r->mn[0] = Mn[0][0] * Mn[1][1] - Mn[0][1] * Mn[1][0];
    r->mn[1] = Mn[0][0] * Mn[1][2] - Mn[0][2] * Mn[1][0];
    r->mn[2] = Mn[0][1] * Mn[1][2] - Mn[0][2] * Mn[1][1];
    r->c4 = (r->c * r->c) * (r->c * r->c);
    const T minor_sum = r->mn[0] * r->mn[0] + r->mn[1] * r->mn[1] + r->mn[2] * r->mn[2];
    r->xx = r->c00 + S.cov_floor;
    r->yy = r->c11 + S.cov_floor;
    r->xy = r->c01;
    r->det = r->c4 * minor_sum + S.cov_floor * (r->c00 + r->c11) + S.cov_floor_sq;

    const bool finite2d = std::isfinite(r->u) && std::isfinite(r->v) && std::isfinite(r->xx) &&
                          std::isfinite(r->yy) && std::isfinite(r->xy) && std::isfinite(r->det);
    const T ext_x = S.extent_sigma * std::sqrt(r->xx + S.extent_dilation) + S.extent_pad;
    const T ext_y = S.extent_sigma * std::sqrt(r->yy + S.extent_dilation) + S.extent_pad;
    const bool on_screen = (r->u + ext_x > T(-0.5)) && (r->u - ext_x < T(S.width - 0.5)) &&
                           (r->v + ext_y > T(-0.5)) && (r->v - ext_y < T(S.height - 0.5));
    r->visible = keep && finite2d && on_screen && r->o > T(0);
}

// Footprint parameters of the mode (footprint.footprint_parameters) and the EAA node count.
template <typename T>
struct Footprint {
    T xx, xy, yy, det, opacity;
    int32_t nodes;
};

// EAA node count of a sampling covariance (footprint.eaa_node_counts, same operation order).
template <typename T>
static inline int32_t eaa_node_count(const ProjectionSettings<T>& S, T xx, T xy, T yy, T det) {
    const T half_trace = T(0.5) * (xx + yy);
    const T half_diff = T(0.5) * (xx - yy);
    const T radius = std::sqrt(half_diff * half_diff + xy * xy);
    const T lambda_major = half_trace + radius;
    const T lambda_minor = det / lambda_major;
    T kappa = std::sqrt(lambda_major / lambda_minor);
    kappa = kappa < T(1) ? T(1) : kappa;  // clamp_min keeps NaN
    T n = std::floor(T(2) * (T(1) + S.gamma * std::log(kappa)) + T(0.5));
    if (std::isnan(n) || n == std::numeric_limits<T>::infinity()) n = T(S.max_nodes);
    if (lambda_minor >= S.single_node_var) n = T(1);
    n = std::min(std::max(n, T(1)), T(S.max_nodes));
    return (int32_t)n;
}

// The dilation a Gaussian is sampled with: the mode's, or for an EAA 1-node Gaussian the pixel box's
// variance (footprint.eaa_single_node_footprint); both with their energy factor where the mode has one.
template <typename T>
struct Dilation {
    T d, d_sq;
    bool energy;
};

template <typename T>
static inline Dilation<T> dilation_of(const ProjectionSettings<T>& S, int32_t nodes) {
    if (S.eaa && nodes <= 1) return {S.box_variance, S.box_variance_sq, true};
    return {S.dilation, S.dilation_sq, S.energy};
}

template <typename T>
static inline Footprint<T> footprint_of(const ProjectionSettings<T>& S, T xx, T xy, T yy, T det, T opacity) {
    Footprint<T> f{xx, xy, yy, det, opacity, 1};
    if (S.eaa) f.nodes = eaa_node_count(S, xx, xy, yy, det);  // eaa has no mode dilation: the raw covariance
    const Dilation<T> D = dilation_of(S, f.nodes);
    if (D.d != T(0)) {
        f.det = det + D.d * (xx + yy) + D.d_sq;
        f.xx = xx + D.d;
        f.yy = yy + D.d;
        if (D.energy) f.opacity = opacity * std::sqrt(det / f.det);
    }
    return f;
}

// Gradient of one visible Gaussian. Incoming: d/d(means2d, depth, footprint cov (xx, xy, yy, det),
// footprint opacity). Adds its share of the viewmat gradient to gW / gt; writes the parameter
// gradients when need_params.
template <typename T>
struct RowGrads {
    T means[3], quats[4], scales[3], opacity;
};

template <typename T>
static inline void project_row_backward(const ProjectionSettings<T>& S, const ProjectedRow<T>& r, T gu, T gv,
                                        T gdepth, T gfxx, T gfxy, T gfyy, T gfdet, T gfo, bool need_params,
                                        bool need_viewmat, double* gW, double* gt, RowGrads<T>* out) {
    // footprint_parameters / eaa_single_node_footprint
    T g_xx = gfxx, g_yy = gfyy, g_xy = gfxy, g_det = gfdet, g_o = gfo;
    const Dilation<T> D = dilation_of(S, S.eaa ? eaa_node_count(S, r.xx, r.xy, r.yy, r.det) : int32_t(1));
    if (D.d != T(0)) {
        const T fdet = r.det + D.d * (r.xx + r.yy) + D.d_sq;
        T g_fdet = gfdet;
        g_det = T(0);
        if (D.energy) {
            const T ratio = r.det / fdet;
            const T sq = std::sqrt(ratio);
            g_o = gfo * sq;
            const T g_ratio = (gfo * r.o) / (T(2) * sq);
            g_det += g_ratio / fdet;
            g_fdet += -g_ratio * r.det / (fdet * fdet);
        }
        g_det += g_fdet;
        g_xx += D.d * g_fdet;
        g_yy += D.d * g_fdet;
    }
    // covariance with floor and the Cauchy-Binet determinant
    const T g_c00 = g_xx + S.cov_floor * g_det;
    const T g_c11 = g_yy + S.cov_floor * g_det;
    const T g_c01 = g_xy;
    const T g_sum = g_det * r.c4;  // d det / d(sum of squared minors)
    const auto& Mn = r.Mn;
    const T* mn = r.mn;
    const T gm0 = T(2) * mn[0] * g_sum, gm1 = T(2) * mn[1] * g_sum, gm2 = T(2) * mn[2] * g_sum;
    T gM[2][3];
    gM[0][0] = (gm0 * Mn[1][1] + gm1 * Mn[1][2]) / r.c;
    gM[0][1] = (-gm0 * Mn[1][0] + gm2 * Mn[1][2]) / r.c;
    gM[0][2] = (-gm1 * Mn[1][0] - gm2 * Mn[1][1]) / r.c;
    gM[1][0] = (-gm0 * Mn[0][1] - gm1 * Mn[0][2]) / r.c;
    gM[1][1] = (gm0 * Mn[0][0] - gm2 * Mn[0][2]) / r.c;
    gM[1][2] = (gm1 * Mn[0][0] + gm2 * Mn[0][1]) / r.c;
    for (int c = 0; c < 3; ++c) {
        gM[0][c] += T(2) * g_c00 * r.M[0][c] + g_c01 * r.M[1][c];
        gM[1][c] += g_c01 * r.M[0][c] + T(2) * g_c11 * r.M[1][c];
    }
    // M = A B
    T gA[2][3];
    for (int a = 0; a < 2; ++a)
        for (int k = 0; k < 3; ++k) gA[a][k] = gM[a][0] * r.B[k][0] + gM[a][1] * r.B[k][1] + gM[a][2] * r.B[k][2];
    // the 3D filter makes std depend on z (when the sampling rate comes from this camera)
    const bool need_B = need_params || (S.filter && S.sampling_rate == nullptr);
    T gB[3][3] = {};
    T g_std[3] = {};
    if (need_B) {
        for (int k = 0; k < 3; ++k)
            for (int c = 0; c < 3; ++c) gB[k][c] = r.A[0][k] * gM[0][c] + r.A[1][k] * gM[1][c];
        for (int c = 0; c < 3; ++c) g_std[c] = gB[0][c] * r.R[0][c] + gB[1][c] * r.R[1][c] + gB[2][c] * r.R[2][c];
    }
    // A = J W
    const T gJ00 = gA[0][0] * S.W[0][0] + gA[0][1] * S.W[0][1] + gA[0][2] * S.W[0][2];
    const T gJ02 = gA[0][0] * S.W[2][0] + gA[0][1] * S.W[2][1] + gA[0][2] * S.W[2][2];
    const T gJ11 = gA[1][0] * S.W[1][0] + gA[1][1] * S.W[1][1] + gA[1][2] * S.W[1][2];
    const T gJ12 = gA[1][0] * S.W[2][0] + gA[1][1] * S.W[2][1] + gA[1][2] * S.W[2][2];
    if (need_viewmat)
        for (int c = 0; c < 3; ++c) {
            gW[0 * 3 + c] += (double)(r.J00 * gA[0][c]);
            gW[1 * 3 + c] += (double)(r.J11 * gA[1][c]);
            gW[2 * 3 + c] += (double)(r.J02 * gA[0][c] + r.J12 * gA[1][c]);
        }
    const T z = r.z, zz = z * z;
    T g_z = gdepth;
    g_z += -gJ00 * S.fx / zz;
    g_z += -gJ11 * S.fy / zz;
    const T g_tx = -S.fx * (gJ02 / z), g_ty = -S.fy * (gJ12 / z);
    g_z += -gJ02 * (-S.fx * r.tx) / zz;
    g_z += -gJ12 * (-S.fy * r.ty) / zz;
    const T g_rx = g_tx * r.dtx, g_ry = g_ty * r.dty;
    T g_p[3];
    g_p[0] = g_rx / z + S.fx * (gu / z);
    g_p[1] = g_ry / z + S.fy * (gv / z);
    g_z += -g_rx * r.p[0] / zz - g_ry * r.p[1] / zz;
    g_z += -gu * (S.fx * r.p[0]) / zz - gv * (S.fy * r.p[1]) / zz;

    // 3D filter and opacity
    T g_s[3];
    T g_oc = g_o;
    if (S.filter) {
        T g_f2[3], g_s2[3], g_r[3];
        for (int k = 0; k < 3; ++k) g_f2[k] = g_std[k] / (T(2) * r.stdv[k]);
        g_oc = g_o * r.sqrtP;
        const T g_P = r.sqrtP > T(0) ? (g_o * r.o_clamped) / (T(2) * r.sqrtP) : T(0);
        g_r[0] = g_P * (r.r[1] * r.r[2]);
        g_r[1] = g_P * (r.r[0] * r.r[2]);
        g_r[2] = g_P * (r.r[0] * r.r[1]);
        T g_var3d = T(0);
        for (int k = 0; k < 3; ++k) {
            g_s2[k] = g_r[k] / r.f2[k];
            g_f2[k] += -g_r[k] * r.s2[k] / (r.f2[k] * r.f2[k]);
            g_s2[k] += g_f2[k];
            g_var3d += g_f2[k];
            g_s[k] = T(2) * r.s[k] * g_s2[k];
        }
        if (S.sampling_rate == nullptr) {
            const T nn = r.nu * r.nu;
            const T g_nn = -g_var3d * S.filter_scale / (nn * nn);
            const T g_nu = T(2) * r.nu * g_nn;
            g_z += -g_nu * S.focal_max / zz;
        }
    } else {
        for (int k = 0; k < 3; ++k) g_s[k] = g_std[k];
    }
    g_p[2] = g_z;
    if (need_viewmat)
        for (int j = 0; j < 3; ++j) {
            for (int k = 0; k < 3; ++k) gW[j * 3 + k] += (double)(g_p[j] * r.m[k]);
            gt[j] += (double)g_p[j];
        }
    if (!need_params) return;
    for (int k = 0; k < 3; ++k)
        out->means[k] = S.W[0][k] * g_p[0] + S.W[1][k] * g_p[1] + S.W[2][k] * g_p[2];
    for (int k = 0; k < 3; ++k) out->scales[k] = g_s[k];
    out->opacity = (r.o_raw >= T(0) && r.o_raw <= T(1)) ? g_oc : T(0);
    // R(qn), then the normalisation qn = q / |q|
    T gR[3][3];
    for (int k = 0; k < 3; ++k)
        for (int c = 0; c < 3; ++c) gR[k][c] = gB[k][c] * r.stdv[c];
    const T w = r.qn[0], x = r.qn[1], y = r.qn[2], zq = r.qn[3];
    T gq[4];
    gq[0] = T(2) * (-zq * gR[0][1] + y * gR[0][2] + zq * gR[1][0] - x * gR[1][2] - y * gR[2][0] + x * gR[2][1]);
    gq[1] = T(2) * (y * gR[0][1] + zq * gR[0][2] + y * gR[1][0] - T(2) * x * gR[1][1] - w * gR[1][2] +
                    zq * gR[2][0] + w * gR[2][1] - T(2) * x * gR[2][2]);
    gq[2] = T(2) * (-T(2) * y * gR[0][0] + x * gR[0][1] + w * gR[0][2] + x * gR[1][0] + zq * gR[1][2] -
                    w * gR[2][0] + zq * gR[2][1] - T(2) * y * gR[2][2]);
    gq[3] = T(2) * (-T(2) * zq * gR[0][0] - w * gR[0][1] + x * gR[0][2] + w * gR[1][0] - T(2) * zq * gR[1][1] +
                    y * gR[1][2] + x * gR[2][0] + y * gR[2][1]);
    const T dot = w * gq[0] + x * gq[1] + y * gq[2] + zq * gq[3];
    for (int k = 0; k < 4; ++k) out->quats[k] = (gq[k] - r.qn[k] * dot) / r.qnorm;
}

// ---------------------------------------------------------------------------------------------
// Host side (raw pointers of contiguous CPU arrays; the Python side checks shapes and dtypes)
// ---------------------------------------------------------------------------------------------
// The camera's values; a bad camera throws std::invalid_argument (a RenderError in Python).
template <typename T>
static ProjectionSettings<T> projection_settings(const T* v, const T* k, const T* rate, int64_t width,
                                                 int64_t height, const double* p, int64_t n_params) {
    MIPSLAM_CHECK(n_params == (int64_t)P_COUNT, "mipslam fused projection: expected ", (int)P_COUNT,
                  " parameters, got ", n_params);
    bool finite = true;
    for (int e = 0; e < 16; ++e) finite = finite && std::isfinite(v[e]);
    for (int e = 0; e < 9; ++e) finite = finite && std::isfinite(k[e]);
    MIPSLAM_CHECK_VALUE(finite, "rasterize: viewmat and K must be finite (a NaN pose cannot be rendered; check the "
                                "tracking result that produced it)");
    MIPSLAM_CHECK_VALUE(k[0] > 0 && k[4] > 0, "rasterize: focal lengths must be positive, got fx=", (double)k[0],
                        ", fy=", (double)k[4]);
    ProjectionSettings<T> S;
    S.fx = k[0];
    S.fy = k[4];
    S.cx = k[2];
    S.cy = k[5];
    for (int j = 0; j < 3; ++j) {
        for (int c = 0; c < 3; ++c) S.W[j][c] = v[j * 4 + c];
        S.t[j] = v[j * 4 + 3];
    }
    S.width = (int)width;
    S.height = (int)height;
    // as projection.py computes them (0-dim tensor arithmetic in T)
    const T margin = (T)p[P_FOV_MARGIN];
    const T tan_x = (T)(0.5 * width) / S.fx, tan_y = (T)(0.5 * height) / S.fy;
    S.lim_x_pos = ((T)width - S.cx) / S.fx + margin * tan_x;
    S.lim_x_neg = S.cx / S.fx + margin * tan_x;
    S.lim_y_pos = ((T)height - S.cy) / S.fy + margin * tan_y;
    S.lim_y_neg = S.cy / S.fy + margin * tan_y;
    S.focal_max = std::max(S.fx, S.fy);
    S.focal_max_abs = std::abs(S.focal_max);
    S.near_plane = (T)p[P_NEAR];
    S.far_plane = (T)p[P_FAR];
    S.max_tangent = (T)p[P_MAX_TANGENT];
    S.max_sigma_px = (T)p[P_MAX_SIGMA_PX];
    S.cov_floor = (T)p[P_COV_FLOOR];
    S.cov_floor_sq = (T)p[P_COV_FLOOR_SQ];
    S.extent_sigma = (T)p[P_EXTENT_SIGMA];
    S.extent_pad = (T)p[P_EXTENT_PAD];
    S.extent_dilation = (T)p[P_EXTENT_DILATION];
    S.filter = p[P_FILTER_SCALE] != 0.0;
    S.filter_scale = (T)p[P_FILTER_SCALE];
    S.sampling_rate = rate;
    S.dilation = (T)p[P_DILATION];
    S.dilation_sq = (T)p[P_DILATION_SQ];
    S.energy = p[P_ENERGY] != 0.0;
    S.eaa = p[P_EAA] != 0.0;
    S.max_nodes = (int)p[P_MAX_NODES];
    S.gamma = (T)p[P_GAMMA];
    S.single_node_var = (T)(p[P_SINGLE_NODE_SIGMA] * p[P_SINGLE_NODE_SIGMA]);
    S.box_variance = (T)p[P_BOX_VARIANCE];
    S.box_variance_sq = (T)(p[P_BOX_VARIANCE] * p[P_BOX_VARIANCE]);
    S.radius_sigma = (T)p[P_RADIUS_SIGMA];
    S.radius_pad = (T)p[P_RADIUS_PAD];
    return S;
}

// Writes means2d [N, 2], depth [N], cov [N, 4] (the mode's xx, xy, yy, det), opacity [N] (the mode's),
// nodes [N] int32, visible [N] bool, radii [N]; returns the number of visible Gaussians.
template <typename T>
static int64_t project_forward_impl(const ProjectionSettings<T>& S, const ProjectionInputs<T>& in, int threads,
                                    T* means2d, T* depth, T* cov, T* opacity, int32_t* nodes, bool* visible,
                                    T* radii) {
    const int64_t n = in.n;
    int64_t n_visible = 0;
#pragma omp parallel for schedule(static) num_threads(threads) if (n >= PROJECTION_PARALLEL_MIN) \
    reduction(+ : n_visible)
    for (int64_t i = 0; i < n; ++i) {
        ProjectedRow<T> r;
        project_row(S, in, i, &r);
        T u = r.u, v = r.v, z = r.z, xx = r.xx, xy = r.xy, yy = r.yy, det = r.det, o = r.o;
        if (!r.visible) {  // harmless finite values, as the reference's _replace_rows
            u = v = T(-1e6);
            xx = yy = det = T(1);
            xy = T(0);
            o = T(0);
            z = T(0);
        }
        const Footprint<T> f = footprint_of(S, xx, xy, yy, det, o);
        means2d[2 * i] = u;
        means2d[2 * i + 1] = v;
        depth[i] = z;
        cov[4 * i] = f.xx;
        cov[4 * i + 1] = f.xy;
        cov[4 * i + 2] = f.yy;
        cov[4 * i + 3] = f.det;
        opacity[i] = f.opacity;
        nodes[i] = f.nodes;
        visible[i] = r.visible;
        radii[i] = r.visible ? S.radius_sigma * std::sqrt(std::max(xx, yy) + S.dilation) + S.radius_pad : T(0);
        n_visible += r.visible ? 1 : 0;
    }
    return n_visible;
}

// Gradients of means [N, 3], quats [N, 4], scales [N, 3], opacities [N] (written when need_params) and of the
// viewmat's rotation and translation (g_viewmat [12]: W row-major then t, accumulated when need_viewmat) from
// those of the outputs of project_forward_impl (a null incoming gradient counts as zero).
template <typename T>
static void project_backward_impl(const ProjectionSettings<T>& S, const ProjectionInputs<T>& in, int threads,
                                  const bool* visible, const T* g_means2d, const T* g_depth, const T* g_cov,
                                  const T* g_opacity, bool need_params, bool need_viewmat, T* out_means,
                                  T* out_quats, T* out_scales, T* out_opacities, double* g_viewmat) {
    const int64_t n = in.n;
    const int64_t blocks = (n + PROJECTION_BLOCK - 1) / PROJECTION_BLOCK;
    std::vector<double> partial(need_viewmat ? (size_t)blocks * 12 : 0, 0.0);
#pragma omp parallel for schedule(static) num_threads(threads) if (n >= PROJECTION_PARALLEL_MIN)
    for (int64_t b = 0; b < blocks; ++b) {
        double local[12] = {};
        const int64_t end = std::min(n, (b + 1) * PROJECTION_BLOCK);
        for (int64_t i = b * PROJECTION_BLOCK; i < end; ++i) {
            RowGrads<T> g{};
            const T gu = g_means2d ? g_means2d[2 * i] : T(0), gv = g_means2d ? g_means2d[2 * i + 1] : T(0);
            const T gd = g_depth ? g_depth[i] : T(0), go = g_opacity ? g_opacity[i] : T(0);
            const T gxx = g_cov ? g_cov[4 * i] : T(0), gxy = g_cov ? g_cov[4 * i + 1] : T(0);
            const T gyy = g_cov ? g_cov[4 * i + 2] : T(0), gdet = g_cov ? g_cov[4 * i + 3] : T(0);
            // Invisible rows, and rows the rasterizer gave no gradient (not drawn), contribute nothing.
            const bool any = gu != T(0) || gv != T(0) || gd != T(0) || go != T(0) || gxx != T(0) || gxy != T(0) ||
                             gyy != T(0) || gdet != T(0);
            if (visible[i] && any) {
                ProjectedRow<T> r;
                project_row(S, in, i, &r);
                project_row_backward(S, r, gu, gv, gd, gxx, gxy, gyy, gdet, go, need_params, need_viewmat, local,
                                     local + 9, &g);
            }
            if (need_params) {
                for (int k = 0; k < 3; ++k) out_means[3 * i + k] = g.means[k];
                for (int k = 0; k < 4; ++k) out_quats[4 * i + k] = g.quats[k];
                for (int k = 0; k < 3; ++k) out_scales[3 * i + k] = g.scales[k];
                out_opacities[i] = g.opacity;
            }
        }
        if (need_viewmat)
            for (int e = 0; e < 12; ++e) partial[(size_t)b * 12 + e] = local[e];
    }
    if (need_viewmat)
        for (int64_t b = 0; b < blocks; ++b)
            for (int e = 0; e < 12; ++e) g_viewmat[e] += partial[(size_t)b * 12 + e];
}

}  // namespace mipslam_cpu
