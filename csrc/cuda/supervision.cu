// RetinexGS's per-pixel training losses on the GPU (rgs/supervision.h): one thread per pixel each way; the forward's
// block reduces its threads' sums through warp shuffles and writes one row of partial sums (the caller adds the
// rows, in one order: deterministic).
#include "common.cuh"
#include "rgs/kernels_cuda.h"
#include "rgs/supervision.h"

namespace rgs {

constexpr int kSupThreads = 256;

template <typename T>
__global__ void __launch_bounds__(kSupThreads)
supervision_forward_kernel(SupervisionArgs<T> a, const T* __restrict__ image, const T* __restrict__ packed,
                           T* __restrict__ x9, T* __restrict__ y9, T* __restrict__ partials) {
    const int64_t HW = int64_t(a.H) * a.W;
    const int64_t p = int64_t(blockIdx.x) * blockDim.x + threadIdx.x;
    T s[kSums];
#pragma unroll
    for (int j = 0; j < kSums; ++j) s[j] = T(0);
    if (p < HW) supervision_forward_pixel(a, p, image, packed, x9, y9, s);
    __shared__ T warp_sums[kSupThreads / 32][kSums];
    const int lane = threadIdx.x & 31, warp = threadIdx.x >> 5;
#pragma unroll
    for (int j = 0; j < kSums; ++j) {
        const T v = warp_sum(s[j]);
        if (lane == 0) warp_sums[warp][j] = v;
    }
    __syncthreads();
    if (threadIdx.x < kSums) {
        T v = T(0);
#pragma unroll
        for (int w = 0; w < kSupThreads / 32; ++w) v += warp_sums[w][threadIdx.x];
        partials[int64_t(blockIdx.x) * kSums + threadIdx.x] = v;
    }
}

template <typename T>
__global__ void __launch_bounds__(kSupThreads)
supervision_backward_kernel(SupervisionArgs<T> a, const T* __restrict__ image, const T* __restrict__ packed,
                            const T* __restrict__ g_x9, const T* __restrict__ g_sums, T* __restrict__ grad_image) {
    const int64_t p = int64_t(blockIdx.x) * blockDim.x + threadIdx.x;
    if (p < int64_t(a.H) * a.W) supervision_backward_pixel(a, p, image, packed, g_x9, g_sums, grad_image);
}

int supervision_rows_cuda(int64_t pixels) { return num_blocks(pixels, kSupThreads); }

template <typename T>
void supervision_forward_cuda(const SupervisionArgs<T>& a, const T* image, const T* packed, T* x9, T* y9, T* partials,
                              void* stream) {
    const int64_t HW = int64_t(a.H) * a.W;
    if (HW == 0) return;
    supervision_forward_kernel<T><<<num_blocks(HW, kSupThreads), kSupThreads, 0, static_cast<cudaStream_t>(stream)>>>(
        a, image, packed, x9, y9, partials);
    RGS_CHECK_LAUNCH("supervision_forward");
}

template <typename T>
void supervision_backward_cuda(const SupervisionArgs<T>& a, const T* image, const T* packed, const T* g_x9,
                               const T* g_sums, T* grad_image, void* stream) {
    const int64_t HW = int64_t(a.H) * a.W;
    if (HW == 0) return;
    supervision_backward_kernel<T><<<num_blocks(HW, kSupThreads), kSupThreads, 0, static_cast<cudaStream_t>(stream)>>>(
        a, image, packed, g_x9, g_sums, grad_image);
    RGS_CHECK_LAUNCH("supervision_backward");
}

#define RGS_INSTANTIATE(T)                                                                                            \
    template void supervision_forward_cuda<T>(const SupervisionArgs<T>&, const T*, const T*, T*, T*, T*, void*);      \
    template void supervision_backward_cuda<T>(const SupervisionArgs<T>&, const T*, const T*, const T*, const T*, T*, \
                                               void*);
RGS_INSTANTIATE(float)
RGS_INSTANTIATE(double)
#undef RGS_INSTANTIATE

}  // namespace rgs
