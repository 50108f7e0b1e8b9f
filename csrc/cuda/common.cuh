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

}  // namespace rgs
