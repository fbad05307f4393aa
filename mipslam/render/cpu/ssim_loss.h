// SSIM of two images and its gradient with respect to the first: the compiled twin of
// mipslam/losses/structural.py's ssim (the readable torch reference it is tested against, tests/test_ssim_loss.py)
// for one float32 image [H, W, C], "same" (zero) padding.
//
// Per pixel p and channel c, with G the separable Gaussian window (taps g, odd count, radius R) and zero padding:
//   mu_x = G*x, mu_y = G*y, e_xx = G*(x x), e_yy = G*(y y), e_xy = G*(x y)
//   a1 = 2 mu_x mu_y + C1, a2 = 2 (e_xy - mu_x mu_y) + C2, b1 = mu_x^2 + mu_y^2 + C1, b2 = e_xx - mu_x^2 + e_yy - mu_y^2 + C2
//   S = a1 a2 / (b1 b2),  mean = sum S / (H W C)
// Backward (analytic): S depends on x only through mu_x, e_xx and e_xy, so with d = 1 / (b1 b2)
//   A = dS/dmu_x = 2 d (mu_y (a2 - a1) + mu_x S (b1 - b2)),  B = dS/de_xx = -S b1 d (= -S / b2),  C = dS/de_xy = 2 a1 d
//   d mean / dx = (G^T*A + 2 x G^T*B + y G^T*C) / (H W C)
// and G^T = G (a symmetric window, g[k] = g[taps - 1 - k], with zero padding: the C entry checks the symmetry). The
// target's moments (mu_y, e_yy) depend on the target alone: the caller may pass them precomputed ([2, H, W, C], from
// `moments`), as mapping scores the same keyframe images thousands of times.
//
// Layout: channels last, so a row is W C interleaved floats and the horizontal blur is a 1D convolution of the row
// with taps C floats apart (a zero margin of R C floats on either side is the zero padding; taps at equal distances
// share a multiply); the vertical blur adds whole rows. Every blur is 8 lanes wide along the row (simd_math.h). The
// images are read and written in place (a row's last vector by its valid lanes only); blurred rows live in scratch,
// allocated once per call. The image is cut into one band of rows per thread; a band streams its rows through two
// rings of horizontally blurred rows (taps rows each): ring 1 holds the blurred x, x x, x y rows, from which each
// row's S, A, B, C follow; ring 2 holds the blurred A, B, C rows, from which each row's gradient follows. A band
// computes the A, B, C of R rows beyond each of its ends (and the blurred rows 2R beyond), which its neighbours also
// compute, instead of waiting at a barrier. The sum of S is accumulated per row (float lanes, then float64) and the
// rows added in order, so the value and the gradient do not depend on the thread count.
#pragma once

#include <algorithm>
#include <cstdint>
#include <cstring>
#include <vector>

#include "simd_math.h"

namespace mipslam_cpu {
namespace ssim {

constexpr int MAX_TAPS = 31;
// Vectors per step of the vertical blurs (2: six independent accumulator chains; faster than 1 in both builds).
constexpr int UNROLL = 2;
// Bands shorter than this are not worth their halo (a band recomputes 2R to 4R rows of its neighbours).
constexpr int64_t MIN_BAND_ROWS = 24;

static inline __attribute__((always_inline)) vf load(const float* p) {
    vf v;
    __builtin_memcpy(&v, p, sizeof(v));
    return v;
}

static inline __attribute__((always_inline)) void store(float* p, vf v) { __builtin_memcpy(p, &v, sizeof(v)); }

struct Geometry {
    int64_t height, width, channels;
    int64_t row;     // W C floats per image row
    int64_t vecs;    // ceil(row / LANES)
    int64_t span;    // vecs LANES: a row buffer's length (the tail past `row` is zero or ignored)
    int64_t margin;  // R C zeros before and after a padded row
    int64_t padded;  // margin + span + margin, rounded up to whole vectors (every buffer starts 32-byte aligned)
    int taps, radius;
    vf g[MAX_TAPS];  // the taps, broadcast once (a broadcast in the inner loops costs the SSE2 build a trip through
                     // memory per use)
    int valid;       // lanes of the last vector inside the row
    vi tail;         // those lanes' mask

    Geometry(int64_t H, int64_t W, int64_t C, const float* window, int taps_)
        : height(H), width(W), channels(C), row(W * C), vecs((W * C + LANES - 1) / LANES), span(vecs * LANES),
          margin((taps_ / 2) * C),
          padded((2 * ((taps_ / 2) * C) + vecs * LANES + LANES - 1) / LANES * LANES), taps(taps_), radius(taps_ / 2) {
        for (int k = 0; k < taps; ++k) g[k] = splat(window[k]);
        valid = (int)(row - (vecs - 1) * LANES);
        for (int l = 0; l < LANES; ++l) tail[l] = l < valid ? -1 : 0;
    }

    // rows [lo, hi] of the image that the vertical taps of row j reach, and their weights
    inline int vertical_taps(int64_t j, int64_t* first, vf* w) const {
        const int64_t lo = std::max<int64_t>(0, j - radius), hi = std::min<int64_t>(height - 1, j + radius);
        for (int64_t i = lo; i <= hi; ++i) w[i - lo] = g[i - j + radius];
        *first = lo;
        return (int)(hi - lo + 1);
    }
};

// out[f] = sum_k g[k] p[f + k C] for f in [0, span): the zero-padded horizontal blur of the padded row p (its data at
// p + margin, zeros in the margins and the tail), as g[R] p[f + R C] + sum_{k<R} g[k] (p[f + k C] + p[f + (2R - k) C])
// (a symmetric window). Four vectors at a time (independent accumulator chains).
static inline void horizontal_blur(const Geometry& G, const float* p, float* out) {
    const int64_t C = G.channels, vecs = G.vecs;
    const int R = G.radius;
    int64_t v = 0;
    for (; v + 4 <= vecs; v += 4) {
        const float* q = p + v * LANES;
        const float* c = q + R * C;
        const vf wc = G.g[R];
        vf s0 = wc * load(c), s1 = wc * load(c + LANES), s2 = wc * load(c + 2 * LANES), s3 = wc * load(c + 3 * LANES);
        for (int k = 0; k < R; ++k) {
            const vf w = G.g[k];
            const float* a = q + k * C;
            const float* b = q + (2 * R - k) * C;
            s0 += w * (load(a) + load(b));
            s1 += w * (load(a + LANES) + load(b + LANES));
            s2 += w * (load(a + 2 * LANES) + load(b + 2 * LANES));
            s3 += w * (load(a + 3 * LANES) + load(b + 3 * LANES));
        }
        store(out + v * LANES, s0);
        store(out + v * LANES + LANES, s1);
        store(out + v * LANES + 2 * LANES, s2);
        store(out + v * LANES + 3 * LANES, s3);
    }
    for (; v < vecs; ++v) {
        const float* q = p + v * LANES;
        vf s = G.g[R] * load(q + R * C);
        for (int k = 0; k < R; ++k) s += G.g[k] * (load(q + k * C) + load(q + (2 * R - k) * C));
        store(out + v * LANES, s);
    }
}

// acc[q][u] = sum_k w[k] rows[k][q span + o + u LANES] for q < Q, u < U: the vertical blur of Q quantities at U
// consecutive vectors (Q U independent accumulator chains).
template <int Q, int U>
static inline __attribute__((always_inline)) void vertical_blur(const float* const* rows, const vf* w, int n,
                                                                int64_t span, int64_t o, vf (&acc)[Q][U]) {
    for (int q = 0; q < Q; ++q)
        for (int u = 0; u < U; ++u) acc[q][u] = splat(0.f);
    for (int k = 0; k < n; ++k) {
        const vf wk = w[k];
        for (int q = 0; q < Q; ++q)
            for (int u = 0; u < U; ++u) acc[q][u] += wk * load(rows[k] + q * span + o + u * LANES);
    }
}

// Blurs every vector of one output row vertically (UNROLL vectors at a time, then the rest one by one) and hands
// each to fn(v, acc), acc[q] the blurred quantity q of vector v.
template <int Q, typename Fn>
static inline __attribute__((always_inline)) void blur_row_vectors(const Geometry& G, const float* const* rows,
                                                                   const vf* w, int n, Fn&& fn) {
    int64_t v = 0;
    for (; v + UNROLL <= G.vecs; v += UNROLL) {
        vf acc[Q][UNROLL];
        vertical_blur<Q, UNROLL>(rows, w, n, G.span, v * LANES, acc);
        for (int u = 0; u < UNROLL; ++u) {
            vf column[Q];
            for (int q = 0; q < Q; ++q) column[q] = acc[q][u];
            fn(v + u, column);
        }
    }
    if (v < G.vecs) {
        vf acc[Q][1];
        vertical_blur<Q, 1>(rows, w, n, G.span, v * LANES, acc);
        vf column[Q];
        for (int q = 0; q < Q; ++q) column[q] = acc[q][0];
        fn(v, column);
    }
}

// A ring of `taps` horizontally blurred rows of Q quantities: row i's quantity q at at(i, q) (span floats).
struct Ring {
    float* base;
    int64_t span;
    int taps, quantities;
    inline float* at(int64_t i, int q) const { return base + ((i % taps) * quantities + q) * span; }
};

// Vector v of an image row that starts at p: the row's last vector reads only the lanes inside the row (zeros in the
// others), so no read leaves the caller's array.
static inline __attribute__((always_inline)) vf load_row(const Geometry& G, const float* p, int64_t v) {
    if (v < G.vecs - 1) return load(p + v * LANES);
    vf x = splat(0.f);
    std::memcpy(&x, p + v * LANES, sizeof(float) * G.valid);
    return x;
}

// Writes vector v of an image row that starts at p (of the last vector, only the lanes inside the row).
static inline __attribute__((always_inline)) void store_row(const Geometry& G, float* p, int64_t v, vf x) {
    if (v < G.vecs - 1)
        store(p + v * LANES, x);
    else
        std::memcpy(p + v * LANES, &x, sizeof(float) * G.valid);
}

// Per-band scratch (floats), carved from one allocation per call.
struct Scratch {
    float *p0, *p1, *p2;  // padded rows [padded]: x, x x, x y (the moments: y, y y)
    float *pa, *pb, *pc;  // padded rows of A, B, C
    Ring ring1, ring2;

    static int64_t floats(const Geometry& G, int quantities1) {
        return (6 * G.padded + (int64_t)G.taps * (quantities1 + 3) * G.span + 15) / 16 * 16;
    }
    Scratch(const Geometry& G, float* base, int quantities1) {
        float* p = base;
        for (float** b : {&p0, &p1, &p2, &pa, &pb, &pc}) {
            *b = p;
            p += G.padded;
        }
        ring1 = Ring{p, G.span, G.taps, quantities1};
        p += (int64_t)G.taps * quantities1 * G.span;
        ring2 = Ring{p, G.span, G.taps, 3};
    }
};

// Rows [0, H) cut into `bands` bands of about equal height: band b is [band_start(b), band_start(b + 1)).
static inline int64_t band_start(int64_t height, int64_t bands, int64_t b) { return height * b / bands; }

static inline int64_t band_count(int64_t height, int threads) {
    return std::max<int64_t>(1, std::min<int64_t>(threads, height / MIN_BAND_ROWS));
}

// The target's moments mu_y = G*y and e_yy = G*(y y), rows [r0, r1), into moments [2, H, W, C].
static void moments_band(const Geometry& G, const float* target, int64_t r0, int64_t r1, Scratch& s,
                         float* moments) {
    const Ring& ring = s.ring1;  // quantities: blurred y, y y
    const int64_t plane = G.height * G.row;
    int64_t next = std::max<int64_t>(0, r0 - G.radius);  // the next row to blur horizontally
    int64_t first;
    vf w[MAX_TAPS];
    const float* rows[MAX_TAPS];
    for (int64_t j = r0; j < r1; ++j) {
        for (const int64_t last = std::min(G.height - 1, j + G.radius); next <= last; ++next) {
            const float* y_row = target + next * G.row;
            for (int64_t v = 0; v < G.vecs; ++v) {
                const vf y = load_row(G, y_row, v);
                store(s.p0 + G.margin + v * LANES, y);
                store(s.p1 + G.margin + v * LANES, y * y);
            }
            horizontal_blur(G, s.p0, ring.at(next, 0));
            horizontal_blur(G, s.p1, ring.at(next, 1));
        }
        const int n = G.vertical_taps(j, &first, w);
        for (int k = 0; k < n; ++k) rows[k] = ring.at(first + k, 0);
        blur_row_vectors<2>(G, rows, w, n, [&](int64_t v, const vf* acc) __attribute__((always_inline)) {
            store_row(G, moments + j * G.row, v, acc[0]);
            store_row(G, moments + plane + j * G.row, v, acc[1]);
        });
    }
}

// Runs body(band, scratch) over the bands on up to `threads` threads, each with zeroed scratch of its own.
template <typename Body>
static void for_bands(const Geometry& G, int threads, int quantities1, Body&& body) {
    const int64_t bands = band_count(G.height, threads);
    const int64_t per_band = Scratch::floats(G, quantities1);
    std::vector<float> scratch((size_t)(bands * per_band + 16), 0.f);  // zero margins and tails, once per call
    float* base = scratch.data();
    while (reinterpret_cast<uintptr_t>(base) % 64 != 0) ++base;  // floats are 4-byte aligned: at most 15 steps
#pragma omp parallel for schedule(static, 1) num_threads((int)bands) if (bands > 1)
    for (int64_t b = 0; b < bands; ++b) {
        Scratch s(G, base + b * per_band, quantities1);
        body(band_start(G.height, bands, b), band_start(G.height, bands, b + 1), s);
    }
}

static void moments(const Geometry& G, const float* target, int threads, float* out) {
    for_bands(G, threads, 2, [&](int64_t r0, int64_t r1, Scratch& s) { moments_band(G, target, r0, r1, s, out); });
}

struct Constants {
    float c1, c2;
    float grad_scale;  // the gradient is grad_scale d(mean S)/dx: the caller's factor over H W C
};

// Band [r0, r1): the sum of S per row into row_sums[r0, r1) and, when GRAD, rows [r0, r1) of the gradient.
template <bool GRAD>
static void ssim_band(const Geometry& G, const float* image, const float* target, const float* target_moments,
                      const Constants& K, int64_t r0, int64_t r1, Scratch& s, double* row_sums, float* grad) {
    const int64_t H = G.height, R = G.radius, plane = H * G.row;
    // rows whose S (and A, B, C) this band computes, and the next row to blur horizontally / to score
    const int64_t s0 = GRAD ? std::max<int64_t>(0, r0 - R) : r0, s1 = GRAD ? std::min(H, r1 + R) : r1;
    int64_t next_h = std::max<int64_t>(0, s0 - R), next_s = s0;
    const vf c1 = splat(K.c1), c2 = splat(K.c2), one = splat(1.f), two = splat(2.f), scale = splat(K.grad_scale);
    int64_t first;
    vf w[MAX_TAPS];
    const float* rows[MAX_TAPS];

    // horizontal blurs of x, x x, x y for image rows up to `last`
    auto blur_through = [&](int64_t last) {
        for (; next_h <= last; ++next_h) {
            const float *x_row = image + next_h * G.row, *y_row = target + next_h * G.row;
            for (int64_t v = 0; v < G.vecs; ++v) {
                const int64_t o = G.margin + v * LANES;
                const vf x = load_row(G, x_row, v), y = load_row(G, y_row, v);
                store(s.p0 + o, x);
                store(s.p1 + o, x * x);
                store(s.p2 + o, x * y);
            }
            horizontal_blur(G, s.p0, s.ring1.at(next_h, 0));
            horizontal_blur(G, s.p1, s.ring1.at(next_h, 1));
            horizontal_blur(G, s.p2, s.ring1.at(next_h, 2));
        }
    };
    // S of rows up to `last` (their sums for rows inside the band) and the horizontally blurred A, B, C
    auto score_through = [&](int64_t last) {
        for (; next_s <= last; ++next_s) {
            const int64_t j = next_s;
            blur_through(std::min(H - 1, j + R));
            const float *my_row = target_moments + j * G.row, *eyy_row = target_moments + plane + j * G.row;
            const int n = G.vertical_taps(j, &first, w);
            for (int k = 0; k < n; ++k) rows[k] = s.ring1.at(first + k, 0);
            vf sum = splat(0.f);
            auto score = [&](int64_t v, vf mx, vf exx, vf exy) __attribute__((always_inline)) {
                const int64_t o = v * LANES;
                const vf my = load_row(G, my_row, v), eyy = load_row(G, eyy_row, v);
                const vf mxx = mx * mx, myy = my * my, mxy = mx * my;
                const vf a1 = two * mxy + c1, a2 = two * (exy - mxy) + c2;
                const vf b1 = mxx + myy + c1, b2 = (exx - mxx) + (eyy - myy) + c2;
                const vf d = one / (b1 * b2);
                vf S = a1 * a2 * d;
                if (v == G.vecs - 1) S = keep(G.tail, S);
                sum += S;
                if (GRAD) {
                    vf A = scale * (two * d * (my * (a2 - a1) + mx * S * (b1 - b2)));
                    vf B = scale * (-(S * b1 * d));
                    vf C = scale * (two * a1 * d);
                    if (v == G.vecs - 1) {  // lanes past the row are the zero padding of the next blur
                        A = keep(G.tail, A);
                        B = keep(G.tail, B);
                        C = keep(G.tail, C);
                    }
                    store(s.pa + G.margin + o, A);
                    store(s.pb + G.margin + o, B);
                    store(s.pc + G.margin + o, C);
                }
            };
            blur_row_vectors<3>(G, rows, w, n, [&](int64_t v, const vf* acc) __attribute__((always_inline)) {
                score(v, acc[0], acc[1], acc[2]);
            });
            if (j >= r0 && j < r1) {
                double total = 0.0;
                for (int l = 0; l < LANES; ++l) total += (double)sum[l];
                row_sums[j] = total;
            }
            if (GRAD) {
                horizontal_blur(G, s.pa, s.ring2.at(j, 0));
                horizontal_blur(G, s.pb, s.ring2.at(j, 1));
                horizontal_blur(G, s.pc, s.ring2.at(j, 2));
            }
        }
    };

    if (!GRAD) {
        score_through(s1 - 1);
        return;
    }
    for (int64_t r = r0; r < r1; ++r) {
        score_through(std::min(H - 1, r + R));
        const float *x_row = image + r * G.row, *y_row = target + r * G.row;
        float* grad_row = grad + r * G.row;
        const int n = G.vertical_taps(r, &first, w);
        for (int k = 0; k < n; ++k) rows[k] = s.ring2.at(first + k, 0);
        auto combine = [&](int64_t v, vf a, vf b, vf c) __attribute__((always_inline)) {
            store_row(G, grad_row, v, a + two * load_row(G, x_row, v) * b + load_row(G, y_row, v) * c);
        };
        blur_row_vectors<3>(G, rows, w, n, [&](int64_t v, const vf* acc) __attribute__((always_inline)) {
            combine(v, acc[0], acc[1], acc[2]);
        });
    }
    (void)s1;
}

// The mean SSIM of image and target [H, W, C] (target_moments [2, H, W, C] of the target, or null: computed here),
// and, when grad is not null, grad_scale times its gradient with respect to the image into grad [H, W, C].
static double evaluate(const Geometry& G, const float* image, const float* target, const float* target_moments,
                       const Constants& K, int threads, float* grad) {
    std::vector<float> computed;
    if (target_moments == nullptr) {
        computed.resize((size_t)(2 * G.height * G.row));
        moments(G, target, threads, computed.data());
        target_moments = computed.data();
    }
    std::vector<double> row_sums((size_t)G.height, 0.0);
    const Constants scaled{K.c1, K.c2, (float)((double)K.grad_scale / (double)(G.height * G.row))};
    for_bands(G, threads, 3, [&](int64_t r0, int64_t r1, Scratch& s) {
        if (grad != nullptr)
            ssim_band<true>(G, image, target, target_moments, scaled, r0, r1, s, row_sums.data(), grad);
        else
            ssim_band<false>(G, image, target, target_moments, scaled, r0, r1, s, row_sums.data(), nullptr);
    });
    double total = 0.0;
    for (const double r : row_sums) total += r;
    return total / (double)(G.height * G.row);
}

}  // namespace ssim
}  // namespace mipslam_cpu
