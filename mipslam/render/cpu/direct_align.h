// Direct RGB-D alignment: Gauss-Newton on intensity and depth residuals of reference points against a target
// image pyramid. The compiled twin of mipslam/geometry/direct.py's align_direct (the readable reference it is
// tested against, tests/test_direct_alignment.py): the same objective, robust scales, step control and
// constants (passed in from Python), with float32 residuals as there; sums in float over blocks of points,
// added up in float64. The per-point work (residuals, block sums) runs on ``threads`` threads for levels of at
// least PARALLEL_MIN points: every block is summed as in a serial run and the blocks are added up in order, so the
// result's bits do not depend on the thread count; the medians stay serial.
//
// Conventions as there: T is the target camera from the reference camera, [4, 4] row-major float64; a point
// X' = T X projects to u' = (fx x / z + cx, fy y / z + cy) with pixel centres at integer coordinates; the
// target's channels [7, h, w] are intensity, its u and v derivatives, depth (metres), its u and v
// derivatives, and 1 where the depth and its derivatives are usable. The increment is a left one,
// T <- exp(delta) T, delta = [rho, phi].
#pragma once

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <vector>

#include "check.h"

namespace mipslam_cpu {
namespace direct {

// Levels with fewer points run serially (a parallel region costs more than it saves there).
constexpr int64_t PARALLEL_MIN = 4096;

// Order of the constants vector (mipslam/render/cpu/backend.py, _DIRECT_CONSTANTS).
enum Constant { HUBER_K, MAD_TO_SIGMA, MIN_SCALE_INTENSITY, MIN_SCALE_DEPTH, MAX_HALVINGS, MIN_POINTS,
                SERIES_ANGLE_SQ, DEPTH_NOISE_POWER, NUM_CONSTANTS };

struct Level {
    const float* points;     // [n, 3] reference camera frame, metres
    const float* intensity;  // [n]
    int64_t n;
    const float* channels;   // [7, height, width]
    int64_t height, width;
    float fx, fy, cx, cy;    // this level's intrinsics (float32, as the reference's tensors)
};

// The target's seven channels interleaved per pixel (padded to eight floats): a bilinear sample reads four
// 32-byte records instead of 28 scattered floats.
static std::vector<float> interleave(const Level& L) {
    const int64_t plane = L.width * L.height;
    std::vector<float> out((size_t)plane * 8, 0.f);
    for (int c = 0; c < 7; ++c) {
        const float* ch = L.channels + c * plane;
        for (int64_t i = 0; i < plane; ++i) out[(size_t)i * 8 + c] = ch[i];
    }
    return out;
}

// Both terms at every reference point (structure of arrays); points outside a term carry mask 0.
struct Residuals {
    std::vector<float> x, y, z;         // X'
    std::vector<float> rc, rd;          // r_c, r_d
    std::vector<float> gcx, gcy, gcz;   // d r_c / d X'
    std::vector<float> gdx, gdy, gdz;   // d r_d / d X'
    std::vector<uint8_t> mc, md;
    int64_t count_c = 0, count_d = 0;

    void resize(int64_t n) {
        for (auto* v : {&x, &y, &z, &rc, &rd, &gcx, &gcy, &gcz, &gdx, &gdy, &gdz}) v->resize((size_t)n);
        mc.resize((size_t)n);
        md.resize((size_t)n);
    }
    int64_t count() const { return count_c + count_d; }
};

// Lower median (torch.median's convention) of values[0, n); reorders them.
static inline float lower_median(float* values, int64_t n) {
    float* mid = values + (n - 1) / 2;
    std::nth_element(values, mid, values + n);
    return *mid;
}

// Bilinear sample of the seven channels (``pixels``: interleave's records) at (u, v), coordinates clamped into
// the image (grid_sample's border padding with align_corners: pixel centres at integers); NaN reads pixel 0.
static inline void sample_channels(const Level& L, const float* pixels, float u, float v, float out[7]) {
    const float max_u = (float)(L.width - 1), max_v = (float)(L.height - 1);
    if (!(u >= 0.f)) u = 0.f;
    if (u > max_u) u = max_u;
    if (!(v >= 0.f)) v = 0.f;
    if (v > max_v) v = max_v;
    const int64_t x0 = (int64_t)std::floor(u), y0 = (int64_t)std::floor(v);
    const int64_t x1 = std::min<int64_t>(x0 + 1, L.width - 1), y1 = std::min<int64_t>(y0 + 1, L.height - 1);
    const float ax = u - (float)x0, ay = v - (float)y0;
    const float w00 = (1.f - ax) * (1.f - ay), w01 = ax * (1.f - ay), w10 = (1.f - ax) * ay, w11 = ax * ay;
    const float* p00 = pixels + 8 * (y0 * L.width + x0);
    const float* p01 = pixels + 8 * (y0 * L.width + x1);
    const float* p10 = pixels + 8 * (y1 * L.width + x0);
    const float* p11 = pixels + 8 * (y1 * L.width + x1);
    for (int c = 0; c < 7; ++c) out[c] = w00 * p00[c] + w01 * p01[c] + w10 * p10[c] + w11 * p11[c];
}

// The residuals of both terms at motion T (float32 maths, as the reference), the intensity term's median
// offset removed (a brightness change between the views is not motion).
static void evaluate(const Level& L, const float* pixels, const double T[16], Residuals* res,
                     std::vector<float>* scratch, int threads, float depth_noise_power) {
    const float R[9] = {(float)T[0], (float)T[1], (float)T[2], (float)T[4], (float)T[5],
                        (float)T[6], (float)T[8], (float)T[9], (float)T[10]};
    const float t[3] = {(float)T[3], (float)T[7], (float)T[11]};
    const int64_t n = L.n;
    res->resize(n);
    const float max_u = (float)(L.width - 1), max_v = (float)(L.height - 1);
    int64_t count_c = 0, count_d = 0;
#pragma omp parallel for schedule(static) num_threads(threads) if (n >= PARALLEL_MIN) reduction(+ : count_c, count_d)
    for (int64_t i = 0; i < n; ++i) {
        const float px = L.points[3 * i], py = L.points[3 * i + 1], pz = L.points[3 * i + 2];
        const float x = R[0] * px + R[1] * py + R[2] * pz + t[0];
        const float y = R[3] * px + R[4] * py + R[5] * pz + t[1];
        const float z = R[6] * px + R[7] * py + R[8] * pz + t[2];
        const bool front = z > 1e-3f;
        const float inv_z = 1.f / (front ? z : 1.f);
        const float xz = x * inv_z, yz = y * inv_z;
        const float u = L.fx * xz + L.cx, v = L.fy * yz + L.cy;
        const bool inside = front && u >= 0.f && u <= max_u && v >= 0.f && v <= max_v;
        float s[7];
        sample_channels(L, pixels, u, v, s);
        const float fx_z = L.fx * inv_z, fy_z = L.fy * inv_z;
        res->x[i] = x;
        res->y[i] = y;
        res->z[i] = z;
        res->rc[i] = s[0] - L.intensity[i];
        float pu = s[1] * fx_z, pv = s[2] * fy_z;
        res->gcx[i] = pu;
        res->gcy[i] = pv;
        res->gcz[i] = 0.f - (pu * xz + pv * yz);
        res->rd[i] = s[3] - z;
        pu = s[4] * fx_z;
        pv = s[5] * fy_z;
        res->gdx[i] = pu;
        res->gdy[i] = pv;
        res->gdz[i] = -1.f - (pu * xz + pv * yz);
        if (depth_noise_power > 0.f) {  // depth residuals in units of z^p (the reference's _residuals)
            const float noise = depth_noise_power == 2.f ? inv_z * inv_z  // the common case, without pow
                                                         : std::pow(inv_z, depth_noise_power);
            res->rd[i] *= noise;
            res->gdx[i] *= noise;
            res->gdy[i] *= noise;
            res->gdz[i] *= noise;
        }
        const bool depth_ok = inside && s[6] > 0.999f;
        res->mc[i] = inside ? 1 : 0;
        res->md[i] = depth_ok ? 1 : 0;
        count_c += inside ? 1 : 0;
        count_d += depth_ok ? 1 : 0;
    }
    res->count_c = count_c;
    res->count_d = count_d;
    if (count_c > 0) {
        scratch->clear();
        for (int64_t i = 0; i < n; ++i)
            if (res->mc[i]) scratch->push_back(res->rc[i]);
        const float offset = lower_median(scratch->data(), (int64_t)scratch->size());
#pragma omp parallel for schedule(static) num_threads(threads) if (n >= PARALLEL_MIN)
        for (int64_t i = 0; i < n; ++i) res->rc[i] -= offset;
    }
}

// MAD_TO_SIGMA x the median absolute residual of one term over its mask, floored (the floor without points).
static double robust_scale(const std::vector<float>& r, const std::vector<uint8_t>& mask, double mad, double floor,
                           std::vector<float>* scratch) {
    scratch->clear();
    for (size_t i = 0; i < r.size(); ++i)
        if (mask[i]) scratch->push_back(std::fabs(r[i]));
    if (scratch->empty()) return floor;
    return std::max(mad * (double)lower_median(scratch->data(), (int64_t)scratch->size()), floor);
}

struct Term {
    const std::vector<float>* r;
    const std::vector<float>* gx;
    const std::vector<float>* gy;
    const std::vector<float>* gz;
    const std::vector<uint8_t>* mask;
    int64_t count;
    double weight, scale;
};

static inline void terms_of(const Residuals& res, double alpha, const double scales[2], Term out[2]) {
    out[0] = Term{&res.rc, &res.gcx, &res.gcy, &res.gcz, &res.mc, res.count_c, alpha, scales[0]};
    out[1] = Term{&res.rd, &res.gdx, &res.gdy, &res.gdz, &res.md, res.count_d, 1.0 - alpha, scales[1]};
}

// Sums body(i, partial) over i in [0, n) into out[K]: float partial sums over blocks of BLOCK points (the
// compiler keeps them in registers), added up in float64 in block order whatever the thread count.
template <int K, typename Body>
static void blocked_sum(int64_t n, int threads, double out[K], Body&& body) {
    constexpr int64_t BLOCK = 256;
    const int64_t blocks = (n + BLOCK - 1) / BLOCK;
    std::vector<float> partials((size_t)(blocks * K), 0.f);
#pragma omp parallel for schedule(static) num_threads(threads) if (n >= PARALLEL_MIN)
    for (int64_t block = 0; block < blocks; ++block) {
        float partial[K] = {0.f};
        const int64_t end = std::min(n, (block + 1) * BLOCK);
        for (int64_t i = block * BLOCK; i < end; ++i) body(i, partial);
        std::copy(partial, partial + K, partials.begin() + block * K);
    }
    std::fill(out, out + K, 0.0);
    for (int64_t block = 0; block < blocks; ++block)
        for (int k = 0; k < K; ++k) out[k] += partials[(size_t)(block * K + k)];
}

// The weighted objective at fixed scales: Huber's rho averaged over each term's points.
static double cost(const Residuals& res, double alpha, const double scales[2], const double* C, int threads) {
    Term terms[2];
    terms_of(res, alpha, scales, terms);
    const float k = (float)C[HUBER_K];
    double total = 0.0;
    for (const Term& term : terms) {
        if (term.weight <= 0.0 || term.count == 0) continue;
        const float scale = (float)term.scale;
        const std::vector<float>& r = *term.r;
        const std::vector<uint8_t>& mask = *term.mask;
        double sum[1];
        blocked_sum<1>((int64_t)r.size(), threads, sum, [&](int64_t i, float* local) {
            const float a = std::fabs(r[i] / scale);
            const float rho = a <= k ? 0.5f * a * a : k * (a - 0.5f * k);
            local[0] += mask[i] ? rho : 0.f;
        });
        total += term.weight * sum[0] / (double)term.count;
    }
    return total;
}

// H [6, 6] and b [6] of the IRLS step at fixed scales (delta = -H^-1 b); Jacobian rows [g, X' x g].
static void normal_equations(const Residuals& res, double alpha, const double scales[2], const double* C,
                             int threads, double H[36], double b[6]) {
    std::fill(H, H + 36, 0.0);
    std::fill(b, b + 6, 0.0);
    Term terms[2];
    terms_of(res, alpha, scales, terms);
    const float k = (float)C[HUBER_K];
    for (const Term& term : terms) {
        if (term.weight <= 0.0 || term.count == 0) continue;
        const double factor = term.weight / (term.scale * term.scale * (double)term.count);
        const float scale = (float)term.scale;
        const std::vector<float>& r = *term.r;
        const std::vector<uint8_t>& mask = *term.mask;
        const std::vector<float>&gx = *term.gx, &gy = *term.gy, &gz = *term.gz;
        double acc[27];  // the upper triangle of H (21 entries, row by row), then b (6); Huber weights, the
                         // term's factor applied after the sum
        blocked_sum<27>((int64_t)r.size(), threads, acc, [&](int64_t i, float* local) {
            const float a = std::fabs(r[i] / scale);
            const float w = mask[i] ? (a <= k ? 1.f : k / std::max(a, 1e-12f)) : 0.f;
            const float X = res.x[i], Y = res.y[i], Z = res.z[i];
            const float J[6] = {gx[i], gy[i], gz[i], Y * gz[i] - Z * gy[i], Z * gx[i] - X * gz[i],
                                X * gy[i] - Y * gx[i]};
            int e = 0;
            for (int p = 0; p < 6; ++p) {
                const float wj = w * J[p];
                for (int q = p; q < 6; ++q) local[e++] += wj * J[q];
                local[21 + p] += wj * r[i];
            }
        });
        for (double& value : acc) value *= factor;
        int e = 0;
        for (int p = 0; p < 6; ++p) {
            for (int q = p; q < 6; ++q, ++e) {
                H[6 * p + q] += acc[e];
                if (q != p) H[6 * q + p] += acc[e];
            }
            b[p] += acc[21 + p];
        }
    }
}

// Solves A x = y (6 x 6, partial pivoting); false when A is singular or the result is not finite.
static bool solve6(const double A_in[36], const double y[6], double x[6]) {
    double A[6][7];
    for (int i = 0; i < 6; ++i) {
        for (int j = 0; j < 6; ++j) A[i][j] = A_in[6 * i + j];
        A[i][6] = y[i];
    }
    for (int c = 0; c < 6; ++c) {
        int pivot = c;
        for (int i = c + 1; i < 6; ++i)
            if (std::fabs(A[i][c]) > std::fabs(A[pivot][c])) pivot = i;
        if (!(std::fabs(A[pivot][c]) > 0.0)) return false;
        if (pivot != c)
            for (int j = 0; j < 7; ++j) std::swap(A[c][j], A[pivot][j]);
        for (int i = c + 1; i < 6; ++i) {
            const double f = A[i][c] / A[c][c];
            for (int j = c; j < 7; ++j) A[i][j] -= f * A[c][j];
        }
    }
    for (int i = 5; i >= 0; --i) {
        double s = A[i][6];
        for (int j = i + 1; j < 6; ++j) s -= A[i][j] * x[j];
        x[i] = s / A[i][i];
    }
    for (int i = 0; i < 6; ++i)
        if (!std::isfinite(x[i])) return false;
    return true;
}

// exp(delta) T for a twist delta = [rho, phi] (mipslam/geometry/se3.py's se3_exp in float64).
static void exp_times(const double delta[6], const double T[16], double series_angle_sq, double out[16]) {
    const double *rho = delta, *phi = delta + 3;
    const double theta2 = phi[0] * phi[0] + phi[1] * phi[1] + phi[2] * phi[2];
    double a, b, c;
    if (theta2 < series_angle_sq) {
        a = 1.0 - theta2 / 6.0 + theta2 * theta2 / 120.0;
        b = 0.5 - theta2 / 24.0 + theta2 * theta2 / 720.0;
        c = 1.0 / 6.0 - theta2 / 120.0 + theta2 * theta2 / 5040.0;
    } else {
        const double t = std::sqrt(theta2);
        a = std::sin(t) / t;
        b = (1.0 - std::cos(t)) / theta2;
        c = (t - std::sin(t)) / (theta2 * t);
    }
    const double K[9] = {0.0, -phi[2], phi[1], phi[2], 0.0, -phi[0], -phi[1], phi[0], 0.0};
    double K2[9];
    for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j) K2[3 * i + j] = K[3 * i] * K[j] + K[3 * i + 1] * K[3 + j] + K[3 * i + 2] * K[6 + j];
    double E[16] = {0.0};
    for (int i = 0; i < 3; ++i) {
        double trans = 0.0;
        for (int j = 0; j < 3; ++j) {
            const double eye = i == j ? 1.0 : 0.0;
            E[4 * i + j] = eye + a * K[3 * i + j] + b * K2[3 * i + j];
            trans += (eye + b * K[3 * i + j] + c * K2[3 * i + j]) * rho[j];
        }
        E[4 * i + 3] = trans;
    }
    E[15] = 1.0;
    for (int i = 0; i < 4; ++i)
        for (int j = 0; j < 4; ++j) {
            double s = 0.0;
            for (int m = 0; m < 4; ++m) s += E[4 * i + m] * T[4 * m + j];
            out[4 * i + j] = s;
        }
}

struct Outcome {
    int64_t steps = 0, points = 0;
    bool ran = false;
};

// Coarse to fine over the levels: Gauss-Newton steps (at most ``iterations`` a level) at robust scales fixed
// per step, each accepted only if it lowers the cost (halved up to MAX_HALVINGS times otherwise).
static Outcome align(const std::vector<Level>& levels, double T[16], int64_t iterations, double alpha,
                     double convergence, const double* C, int threads) {
    Outcome outcome;
    Residuals res, after;
    std::vector<float> scratch;
    const int64_t min_points = (int64_t)C[MIN_POINTS];
    for (const Level& L : levels) {
        if (L.n < min_points) continue;
        const std::vector<float> pixels = interleave(L);
        evaluate(L, pixels.data(), T, &res, &scratch, threads, (float)C[DEPTH_NOISE_POWER]);
        for (int64_t it = 0; it < iterations; ++it) {
            if (res.count() < min_points) break;
            const double scales[2] = {
                robust_scale(res.rc, res.mc, C[MAD_TO_SIGMA], C[MIN_SCALE_INTENSITY], &scratch),
                robust_scale(res.rd, res.md, C[MAD_TO_SIGMA], C[MIN_SCALE_DEPTH], &scratch)};
            double H[36], b[6], delta[6];
            normal_equations(res, alpha, scales, C, threads, H, b);
            double diag = 0.0;
            for (int p = 0; p < 6; ++p) diag = std::max(diag, std::fabs(H[7 * p]));
            for (int p = 0; p < 6; ++p) H[7 * p] += 1e-9 * std::max(diag, 1e-12);
            double minus_b[6];
            for (int p = 0; p < 6; ++p) minus_b[p] = -b[p];
            if (!solve6(H, minus_b, delta)) break;
            outcome.ran = true;
            outcome.points = res.count();
            const double before = cost(res, alpha, scales, C, threads);
            bool accepted = false;
            double candidate[16];
            for (int64_t h = 0; h <= (int64_t)C[MAX_HALVINGS]; ++h) {
                exp_times(delta, T, C[SERIES_ANGLE_SQ], candidate);
                evaluate(L, pixels.data(), candidate, &after, &scratch, threads, (float)C[DEPTH_NOISE_POWER]);
                if (after.count() >= min_points && cost(after, alpha, scales, C, threads) < before) {
                    accepted = true;
                    break;
                }
                for (double& d : delta) d *= 0.5;
            }
            ++outcome.steps;
            if (!accepted) break;
            std::copy(candidate, candidate + 16, T);
            std::swap(res, after);
            double norm2 = 0.0;
            for (double d : delta) norm2 += d * d;
            if (std::sqrt(norm2) < convergence) break;
        }
    }
    return outcome;
}

}  // namespace direct
}  // namespace mipslam_cpu
