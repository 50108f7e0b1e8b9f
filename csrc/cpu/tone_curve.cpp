// Training's tone curve on the CPU (rgs/tone_curve.h): one OpenMP iteration per element.
#include <omp.h>

#include "rgs/kernels.h"
#include "rgs/tone_curve.h"

namespace rgs {

template <typename T>
void tone_curve_forward_cpu(int64_t n, const T* x, const T* gain, int64_t C, int64_t inner, double knee, int form_in,
                            int form_out, T* y, int num_threads) {
    const T kn = T(knee);
#pragma omp parallel for schedule(static) num_threads(num_threads)
    for (int64_t i = 0; i < n; ++i) y[i] = tone_curve(x[i], gain[tone_curve_channel(i, C, inner)], kn, form_in, form_out);
}

template <typename T>
void tone_curve_backward_cpu(int64_t n, const T* x, const T* gain, int64_t C, int64_t inner, double knee, int form_in,
                             int form_out, const T* grad_out, T* grad_x, T* grad_k, int num_threads) {
    const T kn = T(knee);
#pragma omp parallel for schedule(static) num_threads(num_threads)
    for (int64_t i = 0; i < n; ++i)
        tone_curve_backward_one(i, x, gain, C, inner, kn, form_in, form_out, grad_out, grad_x, grad_k);
}

#define RGS_INSTANTIATE(T)                                                                                        \
    template void tone_curve_forward_cpu<T>(int64_t, const T*, const T*, int64_t, int64_t, double, int, int, T*,  \
                                            int);                                                                 \
    template void tone_curve_backward_cpu<T>(int64_t, const T*, const T*, int64_t, int64_t, double, int, int,     \
                                             const T*, T*, T*, int);
RGS_INSTANTIATE(float)
RGS_INSTANTIATE(double)
#undef RGS_INSTANTIATE

}  // namespace rgs
