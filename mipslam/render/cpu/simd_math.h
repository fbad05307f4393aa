// SIMD building blocks of the CPU rasterizer: an 8-lane float vector type and vector exp / erf.
//
// The vectors are GCC/Clang generic vectors (`vector_size(32)`): arithmetic on them is SIMD by
// construction. Built with -mavx2 -mfma each `vf` operation is one ymm instruction; built for the
// x86-64 baseline the compiler lowers each one to two SSE2 (xmm) instructions. No libm call is
// made per pixel: exp and erf below are polynomial, branch-free and work on all lanes at once.
//
// Accuracy (measured against float64 references, see tests/test_render_cpu.py):
//   vexp: relative error < 3e-7 on [-80, 80] (Cody-Waite reduction to |r| <= ln2/2, degree-6
//         polynomial fitted by reweighted least squares, max relative error 1.9e-9 before rounding);
//         the argument is clamped to [-80, 80], so no lane takes the slow subnormal path.
//   verf: absolute error < 2e-7 everywhere (|x| < 1: x P(x^2), degree 6; |x| >= 1:
//         1 - exp(-x^2) Q(1/|x|) with Q a degree-7 fit of erfcx on [1, 4]; beyond 4 erf = 1 in float).
#pragma once

#include <cstdint>

namespace mipslam_cpu {

constexpr int LANES = 8;
typedef float vf __attribute__((vector_size(32), aligned(32)));
typedef int32_t vi __attribute__((vector_size(32), aligned(32)));

static inline __attribute__((always_inline)) vf splat(float x) { return vf{} + x; }
static inline __attribute__((always_inline)) vi splati(int32_t x) { return vi{} + x; }
static inline __attribute__((always_inline)) vf select(vi mask, vf a, vf b) { return mask ? a : b; }
static inline __attribute__((always_inline)) vi selecti(vi mask, vi a, vi b) { return mask ? a : b; }
static inline __attribute__((always_inline)) vf vmin(vf a, vf b) { return a < b ? a : b; }
static inline __attribute__((always_inline)) vf vmax(vf a, vf b) { return a > b ? a : b; }
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
static inline bool any_lane(vi m) {
    int32_t r = 0;
    for (int i = 0; i < LANES; ++i) r |= m[i];
    return r != 0;
}
static inline int32_t hmax_i(vi v) {
    int32_t r = v[0];
    for (int i = 1; i < LANES; ++i) r = v[i] > r ? v[i] : r;
    return r;
}

// exp(x), x clamped to [-80, 80] (exp(-80) = 1.8e-35 is still a normal float).
static inline __attribute__((always_inline)) vf vexp(vf x) {
    x = vmin(vmax(x, splat(-80.f)), splat(80.f));
    const vf t = x * splat(1.44269504088896341f);
    // round to nearest by the 1.5 * 2^23 trick (|t| < 2^22; needs IEEE semantics, no -ffast-math)
    const vf n = (t + splat(12582912.f)) - splat(12582912.f);
    vf r = x - n * splat(0.693359375f);      // ln2 split into an exact high part ...
    r = r - n * splat(-2.12194440e-4f);      // ... and the remainder (Cody-Waite)
    vf p = splat(1.38368300298475e-3f);
    p = p * r + splat(8.37481571512344e-3f);
    p = p * r + splat(4.166822585464257e-2f);
    p = p * r + splat(1.666642017118457e-1f);
    p = p * r + splat(4.9999992078550737e-1f);
    p = p * r + splat(1.0000000363228003f);
    p = p * r + splat(1.0000000005542478f);
    const vi e = (__builtin_convertvector(n, vi) + splati(127)) << 23;
    return p * (vf)e;
}

// erf(x); also returns exp(-x^2) (the derivative up to 2/sqrt(pi)), which the backward reuses.
static inline __attribute__((always_inline)) vf verf(vf x, vf* exp_minus_x2) {
    const vf ax = vabs(x);
    const vf x2 = x * x;
    const vf em = vexp(-x2);
    *exp_minus_x2 = em;
    // |x| < 1: erf(x) = x P(x^2)
    vf p = splat(7.8894776323709670e-05f);
    p = p * x2 + splat(-8.0209570028451360e-04f);
    p = p * x2 + splat(5.1895497001182428e-03f);
    p = p * x2 + splat(-2.6854453125699021e-02f);
    p = p * x2 + splat(1.1283600421807521e-01f);
    p = p * x2 + splat(-3.7612627166024482e-01f);
    p = p * x2 + splat(1.1283791659240794e+00f);
    const vf small = x * p;
    // |x| >= 1: erf(|x|) = 1 - exp(-x^2) erfcx(|x|), erfcx(|x|) = Q(1/|x|) fitted on [1, 4]
    const vf t = splat(1.f) / vmin(vmax(ax, splat(1.f)), splat(4.f));
    vf q = splat(-1.7826805668086879e-02f);
    q = q * t + splat(1.2071316508969691e-01f);
    q = q * t + splat(-3.5445957883591761e-01f);
    q = q * t + splat(5.7613344573631919e-01f);
    q = q * t + splat(-5.0612492066825587e-01f);
    q = q * t + splat(5.1064970437738028e-02f);
    q = q * t + splat(5.5773327126949956e-01f);
    q = q * t + splat(3.5005926035938889e-04f);
    const vf large_abs = splat(1.f) - em * q;
    const vf large = select(x < splat(0.f), -large_abs, large_abs);
    return select(ax < splat(1.f), small, large);
}

static inline __attribute__((always_inline)) vf verf(vf x) {
    vf unused;
    return verf(x, &unused);
}

}  // namespace mipslam_cpu
