// The masked RGB-D L1 loss of a render and its gradients in one pass over the pixels: the compiled twin of
// mipslam/losses/photometric.py's rgbd_l1_loss_and_gradients (the readable reference it is tested against,
// tests/test_rgbd_loss_compiled.py).
//
//   corrected = gain * colour + bias               (the scalar exposure model; gain 1, bias 0 without it)
//   r_c = corrected - colour_gt   on colour-mask pixels, 0 elsewhere        [H, W, C]
//   r_d = depth / max(A, floor) - depth_gt (or depth - depth_gt) on depth-mask pixels, 0 elsewhere   [H, W]
//   L_c = sum |r_c| / (max(n_c, 1) C),  L_d = sum |r_d| / max(n_d, 1),  L = a L_c + (1 - a) L_d
//
// (A the render's opacity, n_c and n_d the masks' pixel counts.) Per-pixel values, the gradient images among
// them, are the torch reference's bit for bit: the same float32 operations in the same order and no fused
// multiply-add (rounded_product). The sums (LaneSums) add in a fixed order of their own, so the loss and the
// exposure's gradients equal the reference's to rounding. One serial SIMD pass: about 0.07 ms at 160x120.
#pragma once

#include <algorithm>
#include <cmath>
#include <cstdint>

#include "check.h"
#include "simd_math.h"

namespace mipslam_cpu {
namespace rgbd_loss {

struct Images {
    const float* color;      // [H, W, C] rendered colour
    const float* depth;      // [H, W] rendered depth, metres
    const float* alpha;      // [H, W] rendered opacity (read only with depth_normalise)
    const float* color_gt;   // [H, W, C]
    const float* depth_gt;   // [H, W] metres
    const uint8_t* mask_color;  // [H, W] bool, the colour term's pixels
    const uint8_t* mask_depth;  // [H, W] bool
    int64_t pixels, channels;
};

struct Options {
    float alpha_color;        // the colour term's weight a, as float32
    float depth_weight;       // 1 - a, computed in float64 and rounded to float32 (as torch rounds Python's 1.0 - a)
    int exposure;             // 1: the scalar exposure model (gain, bias)
    float gain, bias;         // float32, gain = exp(log_gain) as torch computed it
    int depth_normalise;      // 1: the depth term compares depth / max(A, floor)
    float depth_alpha_floor;
};

// Sums: float lanes over blocks of FLUSH vectors, each block's lanes then added into float64 lanes, and those in
// lane order at the end (a fixed order: the result does not depend on the machine's load or thread count).
constexpr int FLUSH = 64;

struct LaneSums {
    double total[LANES] = {};
    vf block = splat(0.f);
    int count = 0;
    inline __attribute__((always_inline)) void add(vf v) {
        block += v;
        if (++count == FLUSH) flush();
    }
    inline void flush() {
        for (int j = 0; j < LANES; ++j) total[j] += (double)block[j];
        block = splat(0.f);
        count = 0;
    }
    inline double sum() {
        flush();
        double s = 0.0;
        for (int j = 0; j < LANES; ++j) s += total[j];
        return s;
    }
};

// a * b rounded to float before anything is added to it: built with -mfma the compiler would otherwise fuse
// gain * colour + bias into one rounding, where torch rounds twice.
static inline __attribute__((always_inline)) vf rounded_product(vf a, vf b) {
    vf p = a * b;
#if defined(__FMA__)
    __asm__("" : "+x"(p));
#endif
    return p;
}

static inline __attribute__((always_inline)) vf load(const float* p) {
    vf v;
    __builtin_memcpy(&v, p, sizeof(v));
    return v;
}

static inline __attribute__((always_inline)) void store(float* p, vf v) { __builtin_memcpy(p, &v, sizeof(v)); }

// sign(r) w: w, -w or 0 (NaN gives 0; a non-finite loss stops the caller before it reads a gradient)
static inline __attribute__((always_inline)) vf signed_weight(vf r, float w) {
    return keep(r > splat(0.f), splat(w)) - keep(r < splat(0.f), splat(w));
}

// LANES flat values of a term from `first` on (fewer at the end: `valid` of them), as vectors; lanes past the
// end read 0 and their mask is false, and are never stored.
static inline __attribute__((always_inline)) vf load_part(const float* x, int64_t first, int valid) {
    if (valid == LANES) return load(x + first);
    vf v = splat(0.f);
    for (int j = 0; j < valid; ++j) v[j] = x[first + j];
    return v;
}

static inline __attribute__((always_inline)) void store_part(float* x, int64_t first, int valid, vf v) {
    if (valid == LANES)
        store(x + first, v);
    else
        for (int j = 0; j < valid; ++j) x[first + j] = v[j];
}

template <int C>
static inline __attribute__((always_inline)) vi mask_part(const uint8_t* mask, int64_t first, int valid) {
    vi m = splati(0);
    for (int j = 0; j < valid; ++j) m[j] = mask[(first + j) / C] != 0 ? -1 : 0;
    return m;
}

// The colour term over the flat [H * W * C] values: sums |r|, g * colour and g (g = sign(r) w) into sums[0..2],
// and writes the gradient g (times the gain with the exposure model) into grad (null: not written).
template <int C, bool EXPOSURE, bool GRAD>
static void colour_term(const Images& im, const Options& o, float w, double* sums, float* grad) {
    const int64_t n = im.pixels * C;
    LaneSums s_abs, s_gain, s_bias;
    const vf gain = splat(o.gain), bias = splat(o.bias);
    for (int64_t k = 0; k < n; k += LANES) {
        const int valid = (int)std::min<int64_t>(LANES, n - k);
        const vf rendered = load_part(im.color, k, valid);
        const vf corrected = EXPOSURE ? rounded_product(gain, rendered) + bias : rendered;
        const vf r = keep(mask_part<C>(im.mask_color, k, valid), corrected - load_part(im.color_gt, k, valid));
        const vf g = signed_weight(r, w);
        s_abs.add(vabs(r));
        if (EXPOSURE) {
            s_gain.add(rounded_product(g, rendered));
            s_bias.add(g);
        }
        if (GRAD) store_part(grad, k, valid, EXPOSURE ? g * gain : g);
    }
    sums[0] = s_abs.sum();
    sums[1] = s_gain.sum();
    sums[2] = s_bias.sum();
}

// The depth term over the [H * W] pixels: returns sum |r|, writes sign(r) w (over max(A, floor) when normalised).
template <bool NORMALISE, bool GRAD>
static double depth_term(const Images& im, const Options& o, float w, float* grad) {
    LaneSums s_abs;
    const vf floor = splat(o.depth_alpha_floor);
    for (int64_t p = 0; p < im.pixels; p += LANES) {
        const int valid = (int)std::min<int64_t>(LANES, im.pixels - p);
        vf rendered = load_part(im.depth, p, valid), divisor = splat(1.f);
        if (NORMALISE) {
            const vf alpha = load_part(im.alpha, p, valid);
            divisor = select(alpha < floor, floor, alpha);  // torch's clamp(min=floor); padded lanes take the floor
            rendered = rendered / divisor;
        }
        const vf r = keep(mask_part<1>(im.mask_depth, p, valid), rendered - load_part(im.depth_gt, p, valid));
        s_abs.add(vabs(r));
        if (GRAD) store_part(grad, p, valid, NORMALISE ? signed_weight(r, w) / divisor : signed_weight(r, w));
    }
    return s_abs.sum();
}

template <int C, bool GRAD>
static void colour_term_for(const Images& im, const Options& o, float w, double* sums, float* grad) {
    if (o.exposure)
        colour_term<C, true, GRAD>(im, o, w, sums, grad);
    else
        colour_term<C, false, GRAD>(im, o, w, sums, grad);
}

template <bool GRAD>
static void colour_term_any(const Images& im, const Options& o, float w, double* sums, float* grad) {
    MIPSLAM_CHECK(im.channels == 1 || im.channels == 3 || im.channels == 4, "mipslam_rgbd_l1: ", im.channels,
                  " colour channels (1, 3 or 4 supported)");
    if (im.channels == 3)
        colour_term_for<3, GRAD>(im, o, w, sums, grad);
    else if (im.channels == 1)
        colour_term_for<1, GRAD>(im, o, w, sums, grad);
    else
        colour_term_for<4, GRAD>(im, o, w, sums, grad);
}

// out: [0] total, [1] colour term, [2] depth term, [3] dL/d log_gain, [4] dL/d bias (0 without exposure);
// counts: [0] colour pixels, [1] depth pixels; grad_color [H, W, C] and grad_depth [H, W] (both or neither null).
static void evaluate(const Images& im, const Options& o, float* out,
                     int64_t* counts, float* grad_color, float* grad_depth) {
    int64_t n_color = 0, n_depth = 0;
    for (int64_t p = 0; p < im.pixels; ++p) {
        n_color += im.mask_color[p] != 0;
        n_depth += im.mask_depth[p] != 0;
    }
    // the reference's normalisers: Python floats max(count, 1) * channels, rounded to float32 by the division
    const float color_norm = (float)((double)(n_color > 0 ? n_color : 1) * (double)im.channels);
    const float depth_norm = (float)(double)(n_depth > 0 ? n_depth : 1);
    const float w_color = o.alpha_color / color_norm;  // (1 * a) / norm, as the reference's chain rule
    const float w_depth = o.depth_weight / depth_norm;
    const bool grad = grad_color != nullptr && grad_depth != nullptr;
    double colour[3];
    double depth_sum;
    if (grad) {
        colour_term_any<true>(im, o, w_color, colour, grad_color);
        depth_sum = o.depth_normalise ? depth_term<true, true>(im, o, w_depth, grad_depth)
                                      : depth_term<false, true>(im, o, w_depth, grad_depth);
    } else {
        colour_term_any<false>(im, o, w_color, colour, nullptr);
        depth_sum = o.depth_normalise ? depth_term<true, false>(im, o, w_depth, nullptr)
                                      : depth_term<false, false>(im, o, w_depth, nullptr);
    }
    const float color_term = (float)colour[0] / color_norm, depth_term_value = (float)depth_sum / depth_norm;
    out[0] = o.alpha_color * color_term + o.depth_weight * depth_term_value;
    out[1] = color_term;
    out[2] = depth_term_value;
    out[3] = o.exposure ? (float)colour[1] * o.gain : 0.f;
    out[4] = o.exposure ? (float)colour[2] : 0.f;
    counts[0] = n_color;
    counts[1] = n_depth;
}

}  // namespace rgbd_loss
}  // namespace mipslam_cpu
