// The fused SSIM on the GPU (rgs/ssim.h): one block of 16x16 threads per 16x16 tile of one plane. The tile and the
// window's halo are staged in shared memory (zero outside the image), filtered along x for every staged row, then
// along y per output pixel: 2 kernels a step's SSIM instead of 4 depthwise convolutions and ~20 elementwise ones.
#include <algorithm>

#include "common.cuh"
#include "rgs/kernels_cuda.h"
#include "rgs/ssim.h"

namespace rgs {

namespace {

constexpr int kTile = 16;
constexpr int kSpan = kTile + 2 * kSsimMaxRadius;  // staged rows / columns at the widest window
constexpr int64_t kMaxGridZ = 65535;              // planes per launch (the grid's z limit)

// Stages K values per pixel of the tile's span (load(gy, gx, v) in the image, zero outside) into in[K][kSpan][kSpan],
// filters them along x into h[K][kSpan][kTile] and returns (in f) the K values filtered along y at this thread's
// pixel. Every thread of the block calls it (it synchronises).
template <int K, typename T, typename Load>
__device__ void filter_tile(int H, int W, const SsimWindow<T>& win, Load load, T (*in)[kSpan][kSpan],
                            T (*h)[kSpan][kTile], T* f) {
    const int R = win.radius, span = kTile + 2 * R;
    const int gx0 = int(blockIdx.x) * kTile - R, gy0 = int(blockIdx.y) * kTile - R;
    const int tid = int(threadIdx.y) * kTile + int(threadIdx.x);
    for (int i = tid; i < span * span; i += kTile * kTile) {
        const int r = i / span, c = i % span, gy = gy0 + r, gx = gx0 + c;
        T v[K];
        if (gy >= 0 && gy < H && gx >= 0 && gx < W) {
            load(gy, gx, v);
        } else {
#pragma unroll
            for (int k = 0; k < K; ++k) v[k] = T(0);
        }
#pragma unroll
        for (int k = 0; k < K; ++k) in[k][r][c] = v[k];
    }
    __syncthreads();
    for (int i = tid; i < span * kTile; i += kTile * kTile) {
        const int r = i / kTile, c = i % kTile;
        T acc[K] = {};
        for (int t = 0; t <= 2 * R; ++t) {
            const T w = win.w[t];
#pragma unroll
            for (int k = 0; k < K; ++k) acc[k] += w * in[k][r][c + t];
        }
#pragma unroll
        for (int k = 0; k < K; ++k) h[k][r][c] = acc[k];
    }
    __syncthreads();
#pragma unroll
    for (int k = 0; k < K; ++k) f[k] = T(0);
    for (int t = 0; t <= 2 * R; ++t) {
        const T w = win.w[t];
#pragma unroll
        for (int k = 0; k < K; ++k) f[k] += w * h[k][threadIdx.y + t][threadIdx.x];
    }
}

template <typename T>
__global__ void __launch_bounds__(kTile * kTile)
ssim_forward_kernel(int64_t p0, int H, int W, int64_t n, const T* __restrict__ x, const T* __restrict__ y, SsimWindow<T> win,
                    T* __restrict__ s, T* __restrict__ d) {
    __shared__ T in[2][kSpan][kSpan];  // x and y; the five products are formed while filtering along x
    __shared__ T h[5][kSpan][kTile];
    const int64_t base = (p0 + int64_t(blockIdx.z)) * H * W;
    const int R = win.radius, span = kTile + 2 * R;
    const int gx0 = int(blockIdx.x) * kTile - R, gy0 = int(blockIdx.y) * kTile - R;
    const int tid = int(threadIdx.y) * kTile + int(threadIdx.x);
    for (int i = tid; i < span * span; i += kTile * kTile) {
        const int r = i / span, c = i % span, gy = gy0 + r, gx = gx0 + c;
        const bool inside = gy >= 0 && gy < H && gx >= 0 && gx < W;
        const int64_t j = base + int64_t(gy) * W + gx;
        in[0][r][c] = inside ? x[j] : T(0);
        in[1][r][c] = inside ? y[j] : T(0);
    }
    __syncthreads();
    for (int i = tid; i < span * kTile; i += kTile * kTile) {
        const int r = i / kTile, c = i % kTile;
        T acc[5] = {};
        for (int t = 0; t <= 2 * R; ++t) {
            T v[5];
            ssim_products(in[0][r][c + t], in[1][r][c + t], v);
            const T w = win.w[t];
#pragma unroll
            for (int k = 0; k < 5; ++k) acc[k] += w * v[k];
        }
#pragma unroll
        for (int k = 0; k < 5; ++k) h[k][r][c] = acc[k];
    }
    __syncthreads();
    const int gy = int(blockIdx.y) * kTile + int(threadIdx.y), gx = int(blockIdx.x) * kTile + int(threadIdx.x);
    if (gy >= H || gx >= W) return;
    T m[5] = {};
    for (int t = 0; t <= 2 * R; ++t) {
        const T w = win.w[t];
#pragma unroll
        for (int k = 0; k < 5; ++k) m[k] += w * h[k][threadIdx.y + t][threadIdx.x];
    }
    const int64_t i = base + int64_t(gy) * W + gx;
    T dd[3];
    s[i] = ssim_from_moments(m[0], m[1], m[2], m[3], m[4], win.c1, win.c2, d ? dd : nullptr);
    if (d) d[i] = dd[0], d[n + i] = dd[1], d[2 * n + i] = dd[2];
}

template <typename T>
__global__ void __launch_bounds__(kTile * kTile)
ssim_backward_kernel(int64_t p0, int H, int W, int64_t n, const T* __restrict__ grad, const T* __restrict__ x,
                     const T* __restrict__ y, const T* __restrict__ d, SsimWindow<T> win, T* __restrict__ dx) {
    __shared__ T in[3][kSpan][kSpan];
    __shared__ T h[3][kSpan][kTile];
    const int64_t base = (p0 + int64_t(blockIdx.z)) * H * W;
    T f[3];
    filter_tile<3, T>(
        H, W, win,
        [&](int gy, int gx, T* v) {
            const int64_t j = base + int64_t(gy) * W + gx;
            const T g = grad[j];
            v[0] = g * d[j], v[1] = g * d[n + j], v[2] = g * d[2 * n + j];
        },
        in, h, f);
    const int gy = int(blockIdx.y) * kTile + int(threadIdx.y), gx = int(blockIdx.x) * kTile + int(threadIdx.x);
    if (gy >= H || gx >= W) return;
    const int64_t i = base + int64_t(gy) * W + gx;
    dx[i] = ssim_grad_x(x[i], y[i], f[0], f[1], f[2]);
}

dim3 tiles(int64_t planes, int H, int W) {
    return dim3(unsigned((W + kTile - 1) / kTile), unsigned((H + kTile - 1) / kTile), unsigned(planes));
}

}  // namespace

template <typename T>
void ssim_forward_cuda(int64_t planes, int H, int W, const T* x, const T* y, const SsimWindow<T>& win, T* s, T* d,
                       void* stream) {
    if (planes == 0 || H == 0 || W == 0) return;
    for (int64_t p0 = 0; p0 < planes; p0 += kMaxGridZ) {
        ssim_forward_kernel<T><<<tiles(std::min(kMaxGridZ, planes - p0), H, W), dim3(kTile, kTile), 0,
                                 static_cast<cudaStream_t>(stream)>>>(p0, H, W, planes * int64_t(H) * W, x, y, win, s, d);
        RGS_CHECK_LAUNCH("ssim_forward");
    }
}

template <typename T>
void ssim_backward_cuda(int64_t planes, int H, int W, const T* grad, const T* x, const T* y, const T* d,
                        const SsimWindow<T>& win, T* dx, void* stream) {
    if (planes == 0 || H == 0 || W == 0) return;
    for (int64_t p0 = 0; p0 < planes; p0 += kMaxGridZ) {
        ssim_backward_kernel<T><<<tiles(std::min(kMaxGridZ, planes - p0), H, W), dim3(kTile, kTile), 0,
                                  static_cast<cudaStream_t>(stream)>>>(p0, H, W, planes * int64_t(H) * W, grad, x, y,
                                                                       d, win, dx);
        RGS_CHECK_LAUNCH("ssim_backward");
    }
}

template void ssim_forward_cuda<float>(int64_t, int, int, const float*, const float*, const SsimWindow<float>&, float*,
                                       float*, void*);
template void ssim_forward_cuda<double>(int64_t, int, int, const double*, const double*, const SsimWindow<double>&,
                                        double*, double*, void*);
template void ssim_backward_cuda<float>(int64_t, int, int, const float*, const float*, const float*, const float*,
                                        const SsimWindow<float>&, float*, void*);
template void ssim_backward_cuda<double>(int64_t, int, int, const double*, const double*, const double*,
                                         const double*, const SsimWindow<double>&, double*, void*);

}  // namespace rgs
