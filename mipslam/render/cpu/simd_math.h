// SIMD building blocks of the CPU rasterizer: an 8-lane float vector type and vector exp / erf.
//
// The vectors are GCC/Clang generic vectors (`vector_size(32)`): arithmetic on them is SIMD by
// construction. Built with -mavx2 -mfma each `vf` operation is one ymm instruction; built for the
// x86-64 baseline the compiler lowers each one to two SSE2 (xmm) instructions. No libm call is
// made per pixel: exp and erf below are polynomial, branch-free and work on all lanes at once.
//
// Accuracy (measured against float64 references, see tests/test_render_cpu.py):
//   vexp: relative error < 3e-7 on [-80, 80] (Cody-Waite reduction to |r| <= ln2/2, degree-5
//         polynomial fitted by reweighted least squares, max relative error 7.5e-8 before rounding);
//         the argument is clamped to [-80, 80], so no lane takes the slow subnormal path.
//   vexp2_unclamped: the centre-sample path's 2^t (log2 e folded into the conic), relative error
//         < 3e-7 for its arguments t in [-6.5, 0].
//   verf: absolute error < 7e-7 everywhere, < 3e-7 for |x| >= 1/2 (1 - exp(-x^2) t Q(t), see below;
//         the error near 0 is the rounding of exp and Q near 1, not the fit's 1.4e-7).
#pragma once

#include <cstdint>

#if defined(__AVX__)
#include <immintrin.h>
#endif

namespace mipslam_cpu {

constexpr int LANES = 8;
typedef float vf __attribute__((vector_size(32), aligned(32)));
typedef int32_t vi __attribute__((vector_size(32), aligned(32)));
typedef uint32_t vu __attribute__((vector_size(32), aligned(32)));

static inline __attribute__((always_inline)) vf splat(float x) { return vf{} + x; }
static inline __attribute__((always_inline)) vi splati(int32_t x) { return vi{} + x; }

#if defined(__AVX__)
// Explicit instructions where the generic form would cost a compare and a blend (same semantics:
// min/max return the second operand when either is NaN, exactly like `a < b ? a : b`).
static inline __attribute__((always_inline)) vf select(vi mask, vf a, vf b) {
    return (vf)_mm256_blendv_ps((__m256)b, (__m256)a, (__m256)mask);
}
static inline __attribute__((always_inline)) vf vmin(vf a, vf b) { return (vf)_mm256_min_ps((__m256)a, (__m256)b); }
static inline __attribute__((always_inline)) vf vmax(vf a, vf b) { return (vf)_mm256_max_ps((__m256)a, (__m256)b); }
static inline __attribute__((always_inline)) bool any_lane(vi m) {
    return !_mm256_testz_si256((__m256i)m, (__m256i)m);
}
#else
static inline __attribute__((always_inline)) vf select(vi mask, vf a, vf b) { return mask ? a : b; }
static inline __attribute__((always_inline)) vf vmin(vf a, vf b) { return a < b ? a : b; }
static inline __attribute__((always_inline)) vf vmax(vf a, vf b) { return a > b ? a : b; }
static inline bool any_lane(vi m) {
    int32_t r = 0;
    for (int i = 0; i < LANES; ++i) r |= m[i];
    return r != 0;
}
#endif
static inline __attribute__((always_inline)) vi selecti(vi mask, vi a, vi b) { return (vi)select(mask, (vf)a, (vf)b); }
// zero where the mask is false (one AND instead of a blend)
static inline __attribute__((always_inline)) vf keep(vi mask, vf a) { return (vf)(mask & (vi)a); }
static inline __attribute__((always_inline)) vf vabs(vf a) { return (vf)((vi)a & splati(0x7fffffff)); }
// sign(a) in {-1, 0, +1} like torch.sign
static inline __attribute__((always_inline)) vf vsign(vf a) {
    return select(a > splat(0.f), splat(1.f), select(a < splat(0.f), splat(-1.f), splat(0.f)));
}

static inline float hsum(vf v) {
    float s = 0.f;
    for (int i = 0; i < LANES; ++i) s += v[i];
    return s;
}
static inline int32_t hmax_i(vi v) {
    int32_t r = v[0];
    for (int i = 1; i < LANES; ++i) r = v[i] > r ? v[i] : r;
    return r;
}

// 2^t for t in [-126, 127]; other lanes give unspecified values (callers mask or clamp them).
// t = n + r with n = round(t), |r| <= 1/2; 2^n is built in the exponent bits by the 1.5 * 2^23 rounding
// trick with the bias 127 folded into the constant (no float->int conversion); 2^r by a degree-5
// polynomial (max relative error 7.5e-8) in Estrin form (short dependency chain).
static inline __attribute__((always_inline)) vf vexp2_unclamped(vf t) {
    const vf shifter = splat(12582912.f + 127.f);
    const vf biased = t + shifter;  // n + 127 in the low mantissa bits
    const vf r = t - (biased - shifter);
    const vf r2 = r * r;
    const vf p01 = splat(0.693146967026062f) * r + splat(1.0000000716534305f);
    const vf p23 = splat(0.05550713336706294f) * r + splat(0.24022119727903957f);
    const vf p45 = splat(0.0013276451558468932f) * r + splat(0.009675541171212429f);
    const vf p = p01 + r2 * (p23 + r2 * p45);
    return p * (vf)((vu)biased << 23);
}

constexpr float LOG2E = 1.44269504088896341f;

// exp(x) with x clamped to [-80, 80] (exp(-80) = 1.8e-35 is still a normal float: no slow subnormal path).
// Cody-Waite: x = n ln2 + r with ln2 split in an exact high part and a remainder, so r is accurate for
// large |x| too; e^r on |r| <= ln2/2 by a degree-5 polynomial (max relative error 7.5e-8), Estrin form.
static inline __attribute__((always_inline)) vf vexp(vf x) {
    x = vmin(vmax(x, splat(-80.f)), splat(80.f));
    const vf shifter = splat(12582912.f + 127.f);
    const vf biased = x * splat(LOG2E) + shifter;
    const vf n = biased - shifter;
    const vf r = (x - n * splat(0.693359375f)) - n * splat(-2.12194440e-4f);
    const vf r2 = r * r;
    const vf p01 = splat(9.999996919357242e-1f) * r + splat(1.0000000716534307f);
    const vf p23 = splat(1.6667574918421377e-1f) * r + splat(4.999889485966238e-1f);
    const vf p45 = splat(8.297642317540248e-3f) * r + splat(4.191538128558668e-2f);
    const vf p = p01 + r2 * (p23 + r2 * p45);
    return p * (vf)((vu)biased << 23);
}

// erf(x); also returns exp(-x^2) (the derivative up to 2/sqrt(pi)), which the backward reuses.
// One branch for every lane (Abramowitz & Stegun 7.1.26 form, refitted): erf(|x|) = 1 - exp(-x^2) t Q(t),
// t = 1 / (1 + 0.3275911 |x|), Q of degree 5 fitted to erfcx on [0, 6] with Q(1) = 1 (so erf(0) = 0 up
// to rounding); the sign is copied from x. Evaluating a second polynomial for |x| < 1 (as before session
// 11) halved the error near 0 but cost 4 % of an `eaa` forward (docs/renderer_cpu.md 6d).
static inline __attribute__((always_inline)) vf verf(vf x, vf* exp_minus_x2) {
    const vf ax = vabs(x);
    const vf em = vexp(-(x * x));
    *exp_minus_x2 = em;
    const vf t = splat(1.f) / (splat(0.3275911f) * ax + splat(1.f));
    vf q = splat(5.7715368503963305e-05f);
    q = q * t + splat(1.0611450154171356f);
    q = q * t + splat(-1.4526861287426138f);
    q = q * t + splat(1.4210006641482937f);
    q = q * t + splat(-0.28431526262691814f);
    q = q * t + splat(0.25479799643559864f);
    const vf erf_abs = vmax(splat(1.f) - em * (q * t), splat(0.f));  // rounding near 0 must not flip the sign
    return (vf)((vi)erf_abs | ((vi)x & splati(int32_t(0x80000000u))));
}

static inline __attribute__((always_inline)) vf verf(vf x) {
    vf unused;
    return verf(x, &unused);
}

}  // namespace mipslam_cpu
