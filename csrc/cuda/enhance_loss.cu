// L_enhance of the default configuration on the GPU (rgs/enhance_loss.h): pass 1 one thread a pool×pool cell, pass
// 2 one block over the cells (its sums in a fixed order: the result is deterministic, as the CPU's). Two launches
// where torch's composition is ~60 kernels each way (issue 65: a fox-dark step is launch-bound).
#include "common.cuh"
#include "rgs/enhance_loss.h"
#include "rgs/kernels_cuda.h"

namespace rgs {

constexpr int kCellThreads = 256;
constexpr int kReduceThreads = 1024;

template <typename T>
__global__ void __launch_bounds__(kCellThreads)
enhance_cells_kernel(const T* __restrict__ x, const T* __restrict__ s, int64_t H, int64_t W, int pool, int64_t cw,
                     int64_t cells_n, const T* __restrict__ gain, T knee, int form_in, int form_out,
                     T* __restrict__ cells) {
    const int64_t j = int64_t(blockIdx.x) * blockDim.x + threadIdx.x;
    if (j < cells_n) enhance_cell(x, s, H, W, pool, j / cw, j % cw, gain, knee, form_in, form_out,
                                  cells + j * kEnhanceCellValues);
}

// The block's sums of v[0..K) into every thread's v (fixed order: lanes by shuffles, then the warps in turn).
template <int K>
__device__ void block_sum(double* v, double (*shared)[K]) {
    const int lane = threadIdx.x & 31, warp = threadIdx.x >> 5, warps = blockDim.x >> 5;
    for (int k = 0; k < K; ++k) v[k] = warp_sum(v[k]);
    if (lane == 0)
        for (int k = 0; k < K; ++k) shared[warp][k] = v[k];
    __syncthreads();
    for (int k = 0; k < K; ++k) {
        double total = 0.0;
        for (int w = 0; w < warps; ++w) total += shared[w][k];
        v[k] = total;
    }
    __syncthreads();
}

template <typename T>
__global__ void __launch_bounds__(kReduceThreads)
enhance_reduce_kernel(const T* __restrict__ cells, int64_t H, int64_t W, int pool, int64_t cw, int64_t cells_n,
                      const T* __restrict__ E, bool exp_l1, bool scale_invariant, double* __restrict__ d,
                      T* __restrict__ out) {
    __shared__ double shared[kReduceThreads / 32][kEnhanceSums];
    const int64_t nh = H / pool, nw = W / pool, n = nh * nw;
    double sums[kEnhanceSums] = {0};
    for (int64_t j = threadIdx.x; j < cells_n; j += blockDim.x)
        enhance_add_cell(cells + j * kEnhanceCellValues, j / cw < nh && j % cw < nw, pool, sums);
    block_sum<kEnhanceSums>(sums, shared);
    const EnhanceScalars<double> sc = enhance_scalars(sums, H, W, n, nh * pool == H && nw * pool == W,
                                                      scale_invariant);
    for (int64_t j = threadIdx.x; j < n; j += blockDim.x)
        d[j] = enhance_d(cells + ((j / nw) * cw + j % nw) * kEnhanceCellValues, pool, sc);
    __syncthreads();  // d complete (global memory, one block)
    double acc[kEnhanceSums] = {0};
    for (int64_t j = threadIdx.x; j < n; j += blockDim.x) {
        const int64_t jy = j / nw, jx = j % nw;
        enhance_add_pair(cells + (jy * cw + jx) * kEnhanceCellValues, pool, d[j], enhance_Ad(d, nh, nw, jy, jx), n,
                         acc);
    }
    block_sum<kEnhanceSums>(acc, shared);
    if (threadIdx.x == 0) enhance_terms(sc, acc, n, double(E[0]), exp_l1, scale_invariant, out);
}

template <typename T>
void enhance_loss_cuda(const T* x, const T* s, int64_t H, int64_t W, int pool, const T* gain, double knee,
                       int form_in, int form_out, const T* E, bool exp_l1, bool scale_invariant, T* cells,
                       double* d, T* out, void* stream) {
    const int64_t ch = (H + pool - 1) / pool, cw = (W + pool - 1) / pool, cells_n = ch * cw;
    cudaStream_t st = static_cast<cudaStream_t>(stream);
    enhance_cells_kernel<T><<<num_blocks(cells_n, kCellThreads), kCellThreads, 0, st>>>(
        x, s, H, W, pool, cw, cells_n, gain, T(knee), form_in, form_out, cells);
    RGS_CHECK_LAUNCH("enhance_cells");
    enhance_reduce_kernel<T><<<1, kReduceThreads, 0, st>>>(cells, H, W, pool, cw, cells_n, E, exp_l1,
                                                           scale_invariant, d, out);
    RGS_CHECK_LAUNCH("enhance_reduce");
}

#define RGS_INSTANTIATE(T)                                                                                         \
    template void enhance_loss_cuda<T>(const T*, const T*, int64_t, int64_t, int, const T*, double, int, int,      \
                                       const T*, bool, bool, T*, double*, T*, void*);
RGS_INSTANTIATE(float)
RGS_INSTANTIATE(double)
#undef RGS_INSTANTIATE

}  // namespace rgs
