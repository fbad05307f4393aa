// The feature front-end's guided matching (mipslam/frontend.py, estimate_relative_pose with a prior): the
// twin of frontend._projection_gate + frontend._match_candidates, which stay the readable reference it is
// tested against (tests/test_frontend.py). Same pairs, bit for bit: the gate keeps (keypoint m, projection j)
// where dx * dx + dy * dy <= limit * limit in float64 (scipy's cKDTree test for p = 2), distances are integer
// Hamming counts, ties go to the lower index, and the ratio test compares in float64.
//
// The reference forms every candidate pair (about 130 per keypoint at the default radius) in numpy arrays;
// here a grid of cells one radius wide over the keypoints finds them, and each pair only updates the running
// best of its keypoint (nearest and second-nearest distance) and of its reference point (nearest keypoint).
#pragma once

#include <cmath>
#include <algorithm>
#include <cstdint>
#include <limits>
#include <vector>

namespace mipslam_cpu {
namespace feature_match {

inline int hamming256(const uint8_t* a, const uint8_t* b) {
    int count = 0;
    for (int w = 0; w < 4; ++w) {
        uint64_t x, y;
        __builtin_memcpy(&x, a + 8 * w, 8);
        __builtin_memcpy(&y, b + 8 * w, 8);
        count += __builtin_popcountll(x ^ y);
    }
    return count;
}

// keypoints [M, 2] and projections [P, 2] px (float64), projection_ids [P] (the reference point of each
// projection, in [0, N)), descriptors query [M, 32] and train [N, 32]. Writes the mutual, ratio-tested pairs
// (keypoint, reference point), by keypoint, into pairs [M, 2]; returns their count.
// Every AVX2 CPU has POPCNT, but -mavx2 does not enable it: without it a popcount is a library call.
#if defined(__AVX2__)
__attribute__((target("popcnt")))
#endif
inline int64_t guided_match(const double* keypoints, int64_t M, const double* projections,
                            const int64_t* projection_ids,
                            int64_t P, double limit, const uint8_t* query, const uint8_t* train, int64_t N,
                            double ratio, int64_t max_hamming, int64_t* pairs) {
    if (M == 0 || P == 0 || !(limit >= 0.0)) return 0;
    // Grid over the keypoints' bounding box, cells `limit` wide (at least 1 px and 1/512 of the box: a tiny
    // radius on a large image must not allocate millions of cells).
    double x_min = keypoints[0], x_max = keypoints[0], y_min = keypoints[1], y_max = keypoints[1];
    for (int64_t m = 1; m < M; ++m) {
        x_min = std::fmin(x_min, keypoints[2 * m]);
        x_max = std::fmax(x_max, keypoints[2 * m]);
        y_min = std::fmin(y_min, keypoints[2 * m + 1]);
        y_max = std::fmax(y_max, keypoints[2 * m + 1]);
    }
    const double cell = std::fmax(std::fmax(limit, 1.0), std::fmax(x_max - x_min, y_max - y_min) / 512.0);
    const int64_t nx = static_cast<int64_t>((x_max - x_min) / cell) + 1;
    const int64_t ny = static_cast<int64_t>((y_max - y_min) / cell) + 1;
    std::vector<int64_t> start(nx * ny + 1, 0), members(M);
    auto cell_x = [&](double x) { return std::min<int64_t>(nx - 1, static_cast<int64_t>((x - x_min) / cell)); };
    auto cell_y = [&](double y) { return std::min<int64_t>(ny - 1, static_cast<int64_t>((y - y_min) / cell)); };
    for (int64_t m = 0; m < M; ++m) ++start[cell_y(keypoints[2 * m + 1]) * nx + cell_x(keypoints[2 * m]) + 1];
    for (int64_t c = 0; c < nx * ny; ++c) start[c + 1] += start[c];
    {
        std::vector<int64_t> fill(start.begin(), start.end() - 1);
        for (int64_t m = 0; m < M; ++m) {
            const int64_t c = cell_y(keypoints[2 * m + 1]) * nx + cell_x(keypoints[2 * m]);
            members[fill[c]++] = m;
        }
    }

    constexpr int64_t NONE = -1;
    constexpr int INF = std::numeric_limits<int>::max();
    std::vector<int> best(M, INF), second(M, INF), column_best(N, INF);
    std::vector<int64_t> best_column(M, NONE), column_row(N, NONE);
    const double limit_sq = limit * limit;
    for (int64_t j = 0; j < P; ++j) {
        const double px = projections[2 * j], py = projections[2 * j + 1];
        // the cells the radius box touches, the box widened by a millionth (a pair the float64 test keeps at
        // the border must not fall outside by a rounding of the box); clamped as doubles (a projection can lie
        // far outside the image)
        const double reach = limit + 1e-6 * (std::fabs(px) + std::fabs(py) + limit + 1.0);
        const double gx0 = std::floor((px - reach - x_min) / cell), gx1 = std::floor((px + reach - x_min) / cell);
        const double gy0 = std::floor((py - reach - y_min) / cell), gy1 = std::floor((py + reach - y_min) / cell);
        if (!(gx1 >= 0 && gy1 >= 0 && gx0 <= nx - 1 && gy0 <= ny - 1)) continue;  // also skips NaN
        const int64_t cx0 = static_cast<int64_t>(std::fmax(gx0, 0.0));
        const int64_t cx1 = static_cast<int64_t>(std::fmin(gx1, nx - 1.0));
        const int64_t cy0 = static_cast<int64_t>(std::fmax(gy0, 0.0));
        const int64_t cy1 = static_cast<int64_t>(std::fmin(gy1, ny - 1.0));
        const int64_t n = projection_ids[j];
        const uint8_t* t = train + 32 * n;
        for (int64_t cy = cy0; cy <= cy1; ++cy) {
            for (int64_t cx = cx0; cx <= cx1; ++cx) {
                const int64_t c = cy * nx + cx;
                for (int64_t k = start[c]; k < start[c + 1]; ++k) {
                    const int64_t m = members[k];
                    const double dx = keypoints[2 * m] - px;
                    const double dy = keypoints[2 * m + 1] - py;
                    const double dx2 = dx * dx, dy2 = dy * dy;  // two roundings, then the sum: no fused multiply-add
                    if (!(dx2 + dy2 <= limit_sq)) continue;
                    const int d = hamming256(query + 32 * m, t);
                    // the keypoint's nearest (distance, then lower column) and its second-nearest distance
                    if (d < best[m] || (d == best[m] && n < best_column[m])) {
                        second[m] = best[m];
                        best[m] = d;
                        best_column[m] = n;
                    } else if (d < second[m]) {
                        second[m] = d;
                    }
                    // the reference point's nearest keypoint (distance, then lower row)
                    if (d < column_best[n] || (d == column_best[n] && m < column_row[n])) {
                        column_best[n] = d;
                        column_row[n] = m;
                    }
                }
            }
        }
    }
    int64_t count = 0;
    for (int64_t m = 0; m < M; ++m) {
        if (best_column[m] == NONE) continue;
        const double second_distance = second[m] == INF ? std::numeric_limits<double>::infinity() : second[m];
        const bool distinct = !(static_cast<double>(best[m]) >= ratio * second_distance);
        if (best[m] <= max_hamming && distinct && column_row[best_column[m]] == m) {
            pairs[2 * count] = m;
            pairs[2 * count + 1] = best_column[m];
            ++count;
        }
    }
    return count;
}

}  // namespace feature_match
}  // namespace mipslam_cpu
