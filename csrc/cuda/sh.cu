// Spherical-harmonics colours on the GPU: one thread per Gaussian over the shared basis; coefficient rows
// staged through shared memory (tiled kernels) unless a row is too wide, then read directly.
#include "common.cuh"
#include "rgs/kernels_cuda.h"
#include "rgs/math.h"

namespace rgs {

template <typename T>
__global__ void sh_forward_kernel(int64_t N, int degree, int K, int D,
                                  const T* __restrict__ dirs,    // [N, 3]
                                  const T* __restrict__ coeffs,  // [N, K, D]
                                  T* __restrict__ colors) {      // [N, D]
    const int64_t i = int64_t(blockIdx.x) * blockDim.x + threadIdx.x;
    if (i >= N) return;
    sh_colors_one(degree, D, dirs + 3 * i, coeffs + i * K * D, colors + i * D);
}

template <typename T>
__global__ void sh_backward_kernel(int64_t N, int degree, int K, int D, const T* __restrict__ dirs,
                                   const T* __restrict__ coeffs, const T* __restrict__ v_colors,  // [N, D]
                                   T* __restrict__ v_dirs,                                         // [N, 3]
                                   T* __restrict__ v_coeffs) {                                     // [N, K, D]
    const int64_t i = int64_t(blockIdx.x) * blockDim.x + threadIdx.x;
    if (i >= N) return;
    sh_colors_one_vjp(degree, K, D, dirs + 3 * i, coeffs + i * K * D, v_colors + i * D, v_dirs + 3 * i,
                      v_coeffs + i * K * D);
}

// Tiled variants. One thread per Gaussian reading its own K*D coefficients strides the warp over 32 rows
// of 48 values: every load and store touches 32 cache lines and the backward spent 5 ms of a 12 ms
// forward+backward at 3M Gaussians on it. Here a block first copies its Gaussians' contiguous [count, K*D] slab
// into shared memory with consecutive threads on consecutive words (and writes v_coeffs back the same way);
// rows are padded to an odd stride so that the per-thread row accesses hit 32 different banks. The basis loops
// are unrolled over kMaxShCoeffs so B and vB stay in registers.
template <typename T>
__device__ __forceinline__ int sh_tile_stride(int KD) { return KD | 1; }

// Each thread issues kShTileBatch independent loads before it stores any: with one load per loop iteration every
// thread waited a full memory latency per word, and the forward took 0.50 ms at 3M Gaussians for 0.58 GB.
constexpr int kShTileBatch = 16;

template <typename T>
__device__ __forceinline__ void sh_tile_load(const T* __restrict__ src, int count, int KD, T* tile) {
    const int S = sh_tile_stride<T>(KD), total = count * KD;
    for (int base = threadIdx.x; base < total; base += kShTileBatch * blockDim.x) {
        T v[kShTileBatch];
#pragma unroll
        for (int u = 0; u < kShTileBatch; ++u) {
            const int e = base + u * blockDim.x;
            v[u] = e < total ? src[e] : T(0);
        }
#pragma unroll
        for (int u = 0; u < kShTileBatch; ++u) {
            const int e = base + u * blockDim.x;
            if (e < total) tile[(e / KD) * S + e % KD] = v[u];
        }
    }
}

template <typename T>
__global__ void sh_forward_tiled_kernel(int64_t N, int degree, int K, int D,
                                        const T* __restrict__ dirs,    // [N, 3]
                                        const T* __restrict__ coeffs,  // [N, K, D]
                                        T* __restrict__ colors) {      // [N, D]
    extern __shared__ unsigned char sh_smem[];
    T* tile = reinterpret_cast<T*>(sh_smem);  // [blockDim, stride]
    const int KD = K * D, S = sh_tile_stride<T>(KD);
    const int64_t g0 = int64_t(blockIdx.x) * blockDim.x;
    const int count = int(min(int64_t(blockDim.x), N - g0));
    sh_tile_load(coeffs + g0 * KD, count, KD, tile);
    __syncthreads();
    const int t = threadIdx.x;
    if (t >= count) return;  // no barrier follows
    const int64_t i = g0 + t;
    sh_colors_one(degree, D, dirs + 3 * i, tile + t * S, colors + i * D);
}

template <typename T>
__global__ void sh_backward_tiled_kernel(int64_t N, int degree, int K, int D,
                                         const T* __restrict__ dirs,      // [N, 3]
                                         const T* __restrict__ coeffs,    // [N, K, D]
                                         const T* __restrict__ v_colors,  // [N, D]
                                         T* __restrict__ v_dirs,          // [N, 3] out
                                         T* __restrict__ v_coeffs) {      // [N, K, D] out
    extern __shared__ unsigned char sh_smem[];
    T* tile = reinterpret_cast<T*>(sh_smem);  // [blockDim, stride]: coeffs in, v_coeffs out
    const int KD = K * D, S = sh_tile_stride<T>(KD);
    const int64_t g0 = int64_t(blockIdx.x) * blockDim.x;
    const int count = int(min(int64_t(blockDim.x), N - g0));
    sh_tile_load(coeffs + g0 * KD, count, KD, tile);
    __syncthreads();
    const int t = threadIdx.x;
    if (t < count) {  // this thread's row only: no other thread reads it before the barrier
        const int64_t i = g0 + t;
        T* row = tile + t * S;
        sh_colors_one_vjp(degree, K, D, dirs + 3 * i, row, v_colors + i * D, v_dirs + 3 * i, row);
    }
    __syncthreads();
    T* dst = v_coeffs + g0 * KD;
    for (int e = threadIdx.x; e < count * KD; e += blockDim.x) dst[e] = tile[(e / KD) * S + e % KD];
}

// Threads per block and shared bytes of the tiled kernels, or 0 threads when a row does not fit (many channels):
// those calls take the direct kernels.
template <typename T>
static int sh_tile_threads(int K, int D, size_t& smem) {
    const int threads = sizeof(T) == 4 ? 128 : 64;
    smem = size_t(threads) * size_t((K * D) | 1) * sizeof(T);
    return (K <= kMaxShCoeffs && smem <= 48 * 1024) ? threads : 0;
}

template <typename T>
void sh_forward_cuda(int64_t N, int degree, int K, int D, const T* dirs, const T* coeffs, T* colors, void* stream) {
    if (N == 0) return;
    size_t smem = 0;
    if (const int threads = sh_tile_threads<T>(K, D, smem)) {
        sh_forward_tiled_kernel<T><<<num_blocks(N, threads), threads, smem, (cudaStream_t)stream>>>(
            N, degree, K, D, dirs, coeffs, colors);
        RGS_CHECK_LAUNCH("sh_forward");
        return;
    }
    sh_forward_kernel<T><<<num_blocks(N, 256), 256, 0, (cudaStream_t)stream>>>(N, degree, K, D, dirs, coeffs, colors);
    RGS_CHECK_LAUNCH("sh_forward");
}

template <typename T>
void sh_backward_cuda(int64_t N, int degree, int K, int D, const T* dirs, const T* coeffs, const T* v_colors,
                      T* v_dirs, T* v_coeffs, void* stream) {
    if (N == 0) return;
    size_t smem = 0;
    if (const int threads = sh_tile_threads<T>(K, D, smem)) {
        sh_backward_tiled_kernel<T><<<num_blocks(N, threads), threads, smem, (cudaStream_t)stream>>>(
            N, degree, K, D, dirs, coeffs, v_colors, v_dirs, v_coeffs);
        RGS_CHECK_LAUNCH("sh_backward");
        return;
    }
    sh_backward_kernel<T><<<num_blocks(N, 256), 256, 0, (cudaStream_t)stream>>>(N, degree, K, D, dirs, coeffs,
                                                                                v_colors, v_dirs, v_coeffs);
    RGS_CHECK_LAUNCH("sh_backward");
}

#define RGS_INSTANTIATE(T)                                                                                   \
    template void sh_forward_cuda<T>(int64_t, int, int, int, const T*, const T*, T*, void*);                 \
    template void sh_backward_cuda<T>(int64_t, int, int, int, const T*, const T*, const T*, T*, T*, void*);
RGS_INSTANTIATE(float)
RGS_INSTANTIATE(double)
#undef RGS_INSTANTIATE

}  // namespace rgs
