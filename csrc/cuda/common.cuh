// CUDA-only helpers shared by the kernels of csrc/cuda: launch checks and warp reductions.
#pragma once
#include <cuda_runtime.h>

#include <stdexcept>
#include <string>

namespace rgs {

inline void check_cuda(cudaError_t err, const char* what) {
    if (err != cudaSuccess) throw std::runtime_error(std::string("retinexgs CUDA error in ") + what + ": " +
                                                     cudaGetErrorString(err));
}

#define RGS_CHECK_LAUNCH(name) ::rgs::check_cuda(cudaGetLastError(), name)

inline int num_blocks(int64_t n, int threads) { return int((n + threads - 1) / threads); }

template <typename T>
__device__ __forceinline__ T warp_sum(T v) {
#pragma unroll
    for (int offset = 16; offset > 0; offset >>= 1) v += __shfl_down_sync(0xffffffffu, v, offset);
    return v;
}

// One butterfly round of warp_sum16: each lane keeps one half of its 2·HALF values (the upper half where its lane
// bit 2·HALF is set) and adds its partner's copy of that half, so HALF shuffles fold 2·HALF values to HALF.
template <int HALF, typename T>
__device__ __forceinline__ void warp_fold(T (&v)[16], int lane) {
    const bool upper = lane & (2 * HALF);
#pragma unroll
    for (int i = 0; i < HALF; ++i) {
        const T send = upper ? v[i] : v[i + HALF];
        const T keep = upper ? v[i + HALF] : v[i];
        v[i] = keep + __shfl_xor_sync(0xffffffffu, send, 2 * HALF);
    }
}

// Sums 16 values over the warp in 16 shuffles (warp_sum on each would take 80): returns, in lanes l and l ^ 1
// alike, the warp's sum of value (l >> 1) & 15, so sixteen lanes can then store the sixteen sums at once.
template <typename T>
__device__ __forceinline__ T warp_sum16(T (&v)[16], int lane) {
    warp_fold<8>(v, lane);
    warp_fold<4>(v, lane);
    warp_fold<2>(v, lane);
    warp_fold<1>(v, lane);
    return v[0] + __shfl_xor_sync(0xffffffffu, v[0], 1);
}

}  // namespace rgs
