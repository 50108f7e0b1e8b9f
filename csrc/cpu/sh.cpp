// Spherical-harmonics colours on the CPU: one OpenMP iteration per Gaussian over the shared basis.
#include <omp.h>

#include "rgs/kernels.h"
#include "rgs/math.h"

namespace rgs {

template <typename T>
void sh_forward_cpu(int64_t N, int degree, int K, int D, const T* dirs, const T* coeffs, T* colors,
                    int num_threads) {
#pragma omp parallel for schedule(static) num_threads(num_threads)
    for (int64_t i = 0; i < N; ++i) sh_colors_one(degree, D, dirs + 3 * i, coeffs + i * K * D, colors + i * D);
}

template <typename T>
void sh_backward_cpu(int64_t N, int degree, int K, int D, const T* dirs, const T* coeffs, const T* v_colors,
                     T* v_dirs, T* v_coeffs, int num_threads) {
#pragma omp parallel for schedule(static) num_threads(num_threads)
    for (int64_t i = 0; i < N; ++i)
        sh_colors_one_vjp(degree, K, D, dirs + 3 * i, coeffs + i * K * D, v_colors + i * D, v_dirs + 3 * i,
                          v_coeffs + i * K * D);
}

#define RGS_INSTANTIATE(T)                                                                          \
    template void sh_forward_cpu<T>(int64_t, int, int, int, const T*, const T*, T*, int);          \
    template void sh_backward_cpu<T>(int64_t, int, int, int, const T*, const T*, const T*, T*, T*, int);
RGS_INSTANTIATE(float)
RGS_INSTANTIATE(double)
#undef RGS_INSTANTIATE

}  // namespace rgs
