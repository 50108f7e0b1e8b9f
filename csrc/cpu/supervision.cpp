// RetinexGS's per-pixel training losses on the CPU (rgs/supervision.h): the reference the CUDA kernels are tested
// against. The forward sums each thread's pixels into its own row of partial sums (the caller adds the rows).
#include <omp.h>

#include <vector>

#include "rgs/kernels.h"
#include "rgs/supervision.h"

namespace rgs {

template <typename T>
void supervision_forward_cpu(const SupervisionArgs<T>& a, const T* image, const T* packed, T* x9, T* y9, T* partials,
                             int rows, int num_threads) {
    const int64_t HW = int64_t(a.H) * a.W;
    for (int64_t i = 0; i < int64_t(rows) * kSums; ++i) partials[i] = T(0);
    // Row r sums the pixels [r·HW/rows, (r+1)·HW/rows): fixed chunks, so the result does not depend on the threads.
#pragma omp parallel for schedule(static) num_threads(num_threads)
    for (int r = 0; r < rows; ++r) {
        T* s = partials + int64_t(r) * kSums;
        for (int64_t p = HW * r / rows; p < HW * (r + 1) / rows; ++p) supervision_forward_pixel(a, p, image, packed, x9, y9, s);
    }
}

template <typename T>
void supervision_backward_cpu(const SupervisionArgs<T>& a, const T* image, const T* packed, const T* g_x9,
                              const T* g_sums, T* grad_image, int num_threads) {
    const int64_t HW = int64_t(a.H) * a.W;
#pragma omp parallel for schedule(static) num_threads(num_threads)
    for (int64_t p = 0; p < HW; ++p) supervision_backward_pixel(a, p, image, packed, g_x9, g_sums, grad_image);
}

#define RGS_INSTANTIATE(T)                                                                                          \
    template void supervision_forward_cpu<T>(const SupervisionArgs<T>&, const T*, const T*, T*, T*, T*, int, int);  \
    template void supervision_backward_cpu<T>(const SupervisionArgs<T>&, const T*, const T*, const T*, const T*, T*, \
                                              int);
RGS_INSTANTIATE(float)
RGS_INSTANTIATE(double)
#undef RGS_INSTANTIATE

}  // namespace rgs
