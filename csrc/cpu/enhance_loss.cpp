// L_enhance of the default configuration on the CPU (rgs/enhance_loss.h): the reference the CUDA kernels are
// tested against. Pass 1 one OpenMP iteration a cell; pass 2 in one thread, in the cells' order (deterministic).
#include <omp.h>

#include "rgs/enhance_loss.h"
#include "rgs/kernels.h"

namespace rgs {

template <typename T>
void enhance_loss_cpu(const T* x, const T* s, int64_t H, int64_t W, int pool, const T* gain, double knee, int form_in,
                      int form_out, const T* E, bool exp_l1, bool scale_invariant, T* cells, T* out,
                      int num_threads) {
    const int64_t ch = (H + pool - 1) / pool, cw = (W + pool - 1) / pool, nh = H / pool, nw = W / pool;
    const T kn = T(knee);
#pragma omp parallel for schedule(static) num_threads(num_threads)
    for (int64_t j = 0; j < ch * cw; ++j)
        enhance_cell(x, s, H, W, pool, j / cw, j % cw, gain, kn, form_in, form_out, cells + j * kEnhanceCellValues);
    double sums[kEnhanceSums] = {0};
    for (int64_t j = 0; j < ch * cw; ++j)
        enhance_add_cell(cells + j * kEnhanceCellValues, j / cw < nh && j % cw < nw, pool, sums);
    const int64_t n = nh * nw;
    const EnhanceScalars<double> sc = enhance_scalars(sums, H, W, n, nh * pool == H && nw * pool == W,
                                                      scale_invariant);
    double acc[kEnhancePairSums] = {0};
    for (int64_t j = 0; j < n; ++j) enhance_add_pair_at(cells, cw, pool, nh, nw, j / nw, j % nw, sc, acc);
    enhance_terms(sc, acc, n, double(E[0]), exp_l1, scale_invariant, out);
}

#define RGS_INSTANTIATE(T)                                                                                         \
    template void enhance_loss_cpu<T>(const T*, const T*, int64_t, int64_t, int, const T*, double, int, int,       \
                                      const T*, bool, bool, T*, T*, int);
RGS_INSTANTIATE(float)
RGS_INSTANTIATE(double)
#undef RGS_INSTANTIATE

}  // namespace rgs
