// Densification's screen-space statistics on the GPU (rgs/screen_stats.h): one thread per Gaussian, one launch
// instead of the ~9 elementwise kernels of the torch form (retinexgs/render/screen_stats.py).
#include "common.cuh"
#include "rgs/kernels_cuda.h"
#include "rgs/screen_stats.h"

namespace rgs {

constexpr int kStatsThreads = 256;

template <typename T>
__global__ void __launch_bounds__(kStatsThreads)
screen_stats_kernel(int64_t N, const T* __restrict__ grad2d, const int32_t* __restrict__ radii, T sx, T sy,
                    float* __restrict__ grad_accum, float* __restrict__ count, float* __restrict__ max_radius) {
    const int64_t i = int64_t(blockIdx.x) * blockDim.x + threadIdx.x;
    if (i < N) screen_stats_one(i, grad2d, radii, sx, sy, grad_accum, count, max_radius);
}

template <typename T>
void screen_stats_cuda(int64_t N, const T* grad2d, const int32_t* radii, double sx, double sy, float* grad_accum,
                       float* count, float* max_radius, void* stream) {
    if (N == 0) return;
    screen_stats_kernel<T><<<num_blocks(N, kStatsThreads), kStatsThreads, 0, static_cast<cudaStream_t>(stream)>>>(
        N, grad2d, radii, T(sx), T(sy), grad_accum, count, max_radius);
    RGS_CHECK_LAUNCH("screen_stats");
}

template void screen_stats_cuda<float>(int64_t, const float*, const int32_t*, double, double, float*, float*, float*,
                                       void*);
template void screen_stats_cuda<double>(int64_t, const double*, const int32_t*, double, double, float*, float*,
                                        float*, void*);

}  // namespace rgs
