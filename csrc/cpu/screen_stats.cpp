// Densification's screen-space statistics on the CPU (rgs/screen_stats.h): one OpenMP iteration per Gaussian.
#include <omp.h>

#include "rgs/kernels.h"
#include "rgs/screen_stats.h"

namespace rgs {

template <typename T>
void screen_stats_cpu(int64_t N, const T* grad2d, const int32_t* radii, double sx, double sy, float* grad_accum,
                      float* count, float* max_radius, int num_threads) {
#pragma omp parallel for schedule(static) num_threads(num_threads)
    for (int64_t i = 0; i < N; ++i) screen_stats_one(i, grad2d, radii, T(sx), T(sy), grad_accum, count, max_radius);
}

template void screen_stats_cpu<float>(int64_t, const float*, const int32_t*, double, double, float*, float*, float*,
                                      int);
template void screen_stats_cpu<double>(int64_t, const double*, const int32_t*, double, double, float*, float*,
                                       float*, int);

}  // namespace rgs
