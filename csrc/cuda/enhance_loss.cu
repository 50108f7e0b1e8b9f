// L_enhance of the default configuration on the GPU (rgs/enhance_loss.h), in four launches, every sum in a fixed
// order (the result is deterministic, as the CPU's):
//   cells   one thread a row of a pool×pool cell (the cell's rows added in order), the cells' first-reduction
//           shares summed per block;
//   scalars one block: the blocks' sums, then m, M, σ, σ_o;
//   pairs   one thread a whole cell: d and A d from its own and its neighbours' cell sums, summed per block;
//   terms   one block: the blocks' sums, then the three terms and their Jacobian in the gain.
// Each pass spreads over the GPU (a fox-dark view's 14,400 cells were one block's serial work before: 63 µs of a
// 3 ms step, experiments/notes/2026-11-30-fused-enhance.md), and the sizes of a 12 MP view's 750k cells with it.
#include "common.cuh"
#include "rgs/enhance_loss.h"
#include "rgs/kernels_cuda.h"

namespace rgs {

constexpr int kThreads = 256;

// The block's sums of v[0..K) into every thread's v (fixed order: lanes by shuffles, then the warps in turn).
template <int K>
__device__ void block_sum(double* v) {
    __shared__ double shared[kThreads / 32][K];
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

// Rows a cell's threads cover (one each up to kThreads; a taller cell's threads take every rows-th row) and cells a
// block holds.
__host__ __device__ inline int cell_threads(int pool) { return pool < kThreads ? pool : kThreads; }
__host__ __device__ inline int block_cells(int pool) { return kThreads / cell_threads(pool); }

template <typename T>
__global__ void __launch_bounds__(kThreads)
enhance_cells_kernel(const T* __restrict__ x, const T* __restrict__ s, int64_t H, int64_t W, int pool, int64_t cw,
                     int64_t cells_n, const T* __restrict__ gain, T knee, int form_in, int form_out,
                     T* __restrict__ cells, double* __restrict__ partials) {
    __shared__ T rows[kThreads][kEnhanceCellValues];
    const int R = cell_threads(pool), local = threadIdx.x / R, r = threadIdx.x % R;
    const int64_t j = int64_t(blockIdx.x) * block_cells(pool) + local;
    const bool active = local < block_cells(pool) && j < cells_n;
    const int64_t nh = H / pool, nw = W / pool;
    T acc[kEnhanceCellValues] = {T(0)};
    if (active)
        for (int rr = r; rr < pool; rr += R) {  // one row when pool <= kThreads
            T row[kEnhanceCellValues];
            enhance_cell_row(x, s, H, W, pool, j / cw, j % cw, rr, gain, knee, form_in, form_out, row);
            for (int k = 0; k < kEnhanceCellValues; ++k) acc[k] += row[k];
        }
    for (int k = 0; k < kEnhanceCellValues; ++k) rows[threadIdx.x][k] = acc[k];
    __syncthreads();
    double share[kEnhanceSums] = {0};
    if (active && r == 0) {  // the cell's rows in order, as enhance_cell adds them
        T cell[kEnhanceCellValues] = {T(0)};
        for (int q = 0; q < R; ++q)
            for (int k = 0; k < kEnhanceCellValues; ++k) cell[k] += rows[threadIdx.x + q][k];
        for (int k = 0; k < kEnhanceCellValues; ++k) cells[j * kEnhanceCellValues + k] = cell[k];
        enhance_add_cell(cell, j / cw < nh && j % cw < nw, pool, share);
    }
    block_sum<kEnhanceSums>(share);
    if (threadIdx.x == 0)
        for (int k = 0; k < kEnhanceSums; ++k) partials[int64_t(blockIdx.x) * kEnhanceSums + k] = share[k];
}

// The blocks' sums of `partials` [blocks, K] into every thread's v (thread t the rows t, t + blockDim, ... in order).
template <int K>
__device__ void sum_partials(const double* __restrict__ partials, int64_t blocks, double* v) {
    for (int k = 0; k < K; ++k) v[k] = 0.0;
    for (int64_t b = threadIdx.x; b < blocks; b += blockDim.x)
        for (int k = 0; k < K; ++k) v[k] += partials[b * K + k];
    block_sum<K>(v);
}

__global__ void __launch_bounds__(kThreads)
enhance_scalars_kernel(const double* __restrict__ partials, int64_t blocks, int64_t H, int64_t W, int pool,
                       bool scale_invariant, double* __restrict__ scalars) {
    double sums[kEnhanceSums];
    sum_partials<kEnhanceSums>(partials, blocks, sums);
    const int64_t nh = H / pool, nw = W / pool;
    if (threadIdx.x == 0)
        enhance_scalars_store(enhance_scalars(sums, H, W, nh * nw, nh * pool == H && nw * pool == W,
                                              scale_invariant), scalars);
}

template <typename T>
__global__ void __launch_bounds__(kThreads)
enhance_pairs_kernel(const T* __restrict__ cells, int64_t cw, int pool, int64_t nh, int64_t nw,
                     const double* __restrict__ scalars, double* __restrict__ partials) {
    const EnhanceScalars<double> sc = enhance_scalars_load(scalars);
    const int64_t j = int64_t(blockIdx.x) * blockDim.x + threadIdx.x;
    double acc[kEnhancePairSums] = {0};
    if (j < nh * nw) enhance_add_pair_at(cells, cw, pool, nh, nw, j / nw, j % nw, sc, acc);
    block_sum<kEnhancePairSums>(acc);
    if (threadIdx.x == 0)
        for (int k = 0; k < kEnhancePairSums; ++k) partials[int64_t(blockIdx.x) * kEnhancePairSums + k] = acc[k];
}

template <typename T>
__global__ void __launch_bounds__(kThreads)
enhance_terms_kernel(const double* __restrict__ partials, int64_t blocks, const double* __restrict__ scalars,
                     int64_t n, const T* __restrict__ E, bool exp_l1, bool scale_invariant, T* __restrict__ out) {
    double acc[kEnhancePairSums];
    sum_partials<kEnhancePairSums>(partials, blocks, acc);
    if (threadIdx.x == 0)
        enhance_terms(enhance_scalars_load(scalars), acc, n, double(E[0]), exp_l1, scale_invariant, out);
}

namespace {
struct EnhanceLayout {
    int64_t cw, cells_n, nh, nw, cell_blocks, pair_blocks;
    EnhanceLayout(int64_t H, int64_t W, int pool)
        : cw((W + pool - 1) / pool), cells_n(((H + pool - 1) / pool) * cw), nh(H / pool), nw(W / pool),
          cell_blocks((cells_n + block_cells(pool) - 1) / block_cells(pool)),
          pair_blocks((nh * nw + kThreads - 1) / kThreads) {}
    // the double scratch: the cells' partials, the scalars, the pairs' partials
    int64_t scalars_at() const { return cell_blocks * kEnhanceSums; }
    int64_t pairs_at() const { return scalars_at() + kEnhanceScalarValues; }
    int64_t size() const { return pairs_at() + pair_blocks * kEnhancePairSums; }
};
}  // namespace

int64_t enhance_scratch_cuda(int64_t H, int64_t W, int pool) { return EnhanceLayout(H, W, pool).size(); }

template <typename T>
void enhance_loss_cuda(const T* x, const T* s, int64_t H, int64_t W, int pool, const T* gain, double knee,
                       int form_in, int form_out, const T* E, bool exp_l1, bool scale_invariant, T* cells,
                       double* scratch, T* out, void* stream) {
    const EnhanceLayout L(H, W, pool);
    double *scalars = scratch + L.scalars_at(), *pairs = scratch + L.pairs_at();
    cudaStream_t st = static_cast<cudaStream_t>(stream);
    enhance_cells_kernel<T><<<unsigned(L.cell_blocks), kThreads, 0, st>>>(
        x, s, H, W, pool, L.cw, L.cells_n, gain, T(knee), form_in, form_out, cells, scratch);
    RGS_CHECK_LAUNCH("enhance_cells");
    enhance_scalars_kernel<<<1, kThreads, 0, st>>>(scratch, L.cell_blocks, H, W, pool, scale_invariant, scalars);
    RGS_CHECK_LAUNCH("enhance_scalars");
    enhance_pairs_kernel<T><<<unsigned(L.pair_blocks), kThreads, 0, st>>>(cells, L.cw, pool, L.nh, L.nw, scalars,
                                                                          pairs);
    RGS_CHECK_LAUNCH("enhance_pairs");
    enhance_terms_kernel<T><<<1, kThreads, 0, st>>>(pairs, L.pair_blocks, scalars, L.nh * L.nw, E, exp_l1,
                                                    scale_invariant, out);
    RGS_CHECK_LAUNCH("enhance_terms");
}

#define RGS_INSTANTIATE(T)                                                                                         \
    template void enhance_loss_cuda<T>(const T*, const T*, int64_t, int64_t, int, const T*, double, int, int,      \
                                       const T*, bool, bool, T*, double*, T*, void*);
RGS_INSTANTIATE(float)
RGS_INSTANTIATE(double)
#undef RGS_INSTANTIATE

}  // namespace rgs
