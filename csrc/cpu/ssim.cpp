// The fused SSIM on the CPU (rgs/ssim.h): one OpenMP task per strip of rows of one image plane. A task filters its
// rows and the window's halo along x into a buffer of its own, then along y, so the memory beside the outputs is a
// strip's, not a whole image's moments (a 12 MP view's five moments would be ~240 MB a plane).
#include <omp.h>

#include <algorithm>
#include <vector>

#include "rgs/kernels.h"
#include "rgs/ssim.h"

namespace rgs {

namespace {

constexpr int kStripRows = 32;

// Filters the K planes src[k] (each H x W, read through at(k, row, col)) along x for rows [h0, h1) into
// buf[k][row - h0][col], then along y for rows [r0, r1), calling done(row, col, sums) with the K filtered values.
template <int K, typename T, typename At, typename Done>
void filter_strip(int H, int W, int r0, int r1, const SsimWindow<T>& win, At at, Done done, std::vector<T>& buf) {
    const int R = win.radius;
    const int h0 = std::max(0, r0 - R), h1 = std::min(H, r1 + R), rows = h1 - h0;
    buf.assign(size_t(K) * rows * W, T(0));
    std::vector<T> line(static_cast<size_t>(K) * W);
    for (int r = h0; r < h1; ++r) {
        for (int c = 0; c < W; ++c) {
            T v[K];
            at(r, c, v);
            for (int k = 0; k < K; ++k) line[size_t(k) * W + c] = v[k];
        }
        for (int c = 0; c < W; ++c) {
            T acc[K] = {};
            const int lo = std::max(-R, -c), hi = std::min(R, W - 1 - c);  // zero outside the image
            for (int t = lo; t <= hi; ++t) {
                const T w = win.w[t + R];
                for (int k = 0; k < K; ++k) acc[k] += w * line[size_t(k) * W + c + t];
            }
            for (int k = 0; k < K; ++k) buf[(size_t(k) * rows + (r - h0)) * W + c] = acc[k];
        }
    }
    for (int r = r0; r < r1; ++r) {
        const int lo = std::max(-R, -r), hi = std::min(R, H - 1 - r);
        for (int c = 0; c < W; ++c) {
            T acc[K] = {};
            for (int t = lo; t <= hi; ++t) {
                const T w = win.w[t + R];
                for (int k = 0; k < K; ++k) acc[k] += w * buf[(size_t(k) * rows + (r + t - h0)) * W + c];
            }
            done(r, c, acc);
        }
    }
}

// Calls task(p, r0, r1, buf) for every strip [r0, r1) of kStripRows rows of every plane p, in parallel; buf is the
// calling thread's scratch buffer, reused across its strips.
template <typename T, typename Task>
void for_each_strip(int64_t planes, int H, int num_threads, Task task) {
    const int64_t strips = (H + kStripRows - 1) / kStripRows;
#pragma omp parallel num_threads(num_threads)
    {
        std::vector<T> buf;
#pragma omp for schedule(dynamic)
        for (int64_t t = 0; t < planes * strips; ++t) {
            const int r0 = int(t % strips) * kStripRows;
            task(t / strips, r0, std::min(H, r0 + kStripRows), buf);
        }
    }
}

}  // namespace

template <typename T>
void ssim_forward_cpu(int64_t planes, int H, int W, const T* x, const T* y, const SsimWindow<T>& win, T* s, T* d,
                      int num_threads) {
    const int64_t HW = int64_t(H) * W, n = planes * HW;
    for_each_strip<T>(planes, H, num_threads, [&](int64_t p, int r0, int r1, std::vector<T>& buf) {
        const T* xp = x + p * HW;
        const T* yp = y + p * HW;
        filter_strip<5, T>(
            H, W, r0, r1, win, [&](int r, int c, T* v) { ssim_products(xp[r * W + c], yp[r * W + c], v); },
            [&](int r, int c, const T* m) {
                const int64_t i = p * HW + int64_t(r) * W + c;
                T dd[3];
                s[i] = ssim_from_moments(m[0], m[1], m[2], m[3], m[4], win.c1, win.c2, d ? dd : nullptr);
                if (d) d[i] = dd[0], d[n + i] = dd[1], d[2 * n + i] = dd[2];
            },
            buf);
    });
}

template <typename T>
void ssim_backward_cpu(int64_t planes, int H, int W, const T* grad, const T* x, const T* y, const T* d,
                       const SsimWindow<T>& win, T* dx, int num_threads) {
    const int64_t HW = int64_t(H) * W, n = planes * HW;
    for_each_strip<T>(planes, H, num_threads, [&](int64_t p, int r0, int r1, std::vector<T>& buf) {
        filter_strip<3, T>(
            H, W, r0, r1, win,
            [&](int r, int c, T* v) {
                const int64_t i = p * HW + int64_t(r) * W + c;
                const T g = grad[i];
                v[0] = g * d[i], v[1] = g * d[n + i], v[2] = g * d[2 * n + i];
            },
            [&](int r, int c, const T* f) {
                const int64_t i = p * HW + int64_t(r) * W + c;
                dx[i] = ssim_grad_x(x[i], y[i], f[0], f[1], f[2]);
            },
            buf);
    });
}

template void ssim_forward_cpu<float>(int64_t, int, int, const float*, const float*, const SsimWindow<float>&, float*,
                                      float*, int);
template void ssim_forward_cpu<double>(int64_t, int, int, const double*, const double*, const SsimWindow<double>&,
                                       double*, double*, int);
template void ssim_backward_cpu<float>(int64_t, int, int, const float*, const float*, const float*, const float*,
                                       const SsimWindow<float>&, float*, int);
template void ssim_backward_cpu<double>(int64_t, int, int, const double*, const double*, const double*, const double*,
                                        const SsimWindow<double>&, double*, int);

}  // namespace rgs
