// The illumination field's MLP in training on the CPU: one OpenMP iteration per Gaussian (rgs/illumination_train.h).
#include <omp.h>

#include "rgs/illumination_train.h"
#include "rgs/kernels.h"

namespace rgs {

template <typename T>
static IllumTrainArgs<T> train_args(const T* center, double bound) {
    return IllumTrainArgs<T>{center, T(1) / T(bound), T(bound)};
}

// f(H, DH, i) for every Gaussian i, with cfg's widths' specialisation (gaussian_colors.h), on OpenMP threads.
template <typename F>
static void for_each_gaussian(int64_t N, const IllumConfig& cfg, int num_threads, F&& f) {
    dispatch_illum_widths(&cfg, [&](auto h, auto dh) {
#pragma omp parallel for schedule(static) num_threads(num_threads)
        for (int64_t i = 0; i < N; ++i) f(h, dh, i);
    });
}

template <typename T>
void illumination_forward_cpu(int64_t N, const T* means, const T* center, const IllumConfig& cfg, double bound,
                              const T* weights, T* rgb, T* A, int64_t ld, int num_threads) {
    const IllumTrainArgs<T> a = train_args(center, bound);
    const IllumLayout L = illum_layout(cfg);
    const IllumTrainLayout S = illum_train_layout(cfg);
    for_each_gaussian(N, cfg, num_threads, [&](auto h, auto dh, int64_t i) {
        illumination_forward_one<T, decltype(h)::value, decltype(dh)::value>(i, ld, a, cfg, L, S, means, weights, rgb,
                                                                             A);
    });
}

template <typename T>
void illumination_backward_cpu(int64_t N, const T* means, const T* center, const IllumConfig& cfg, double bound,
                               const T* weights, const T* A, const T* rgb, const T* g_rgb, T* D, T* g_means, int64_t ld,
                               int num_threads) {
    const IllumTrainArgs<T> a = train_args(center, bound);
    const IllumLayout L = illum_layout(cfg);
    const IllumTrainLayout S = illum_train_layout(cfg);
    for_each_gaussian(N, cfg, num_threads, [&](auto h, auto dh, int64_t i) {
        illumination_backward_one<T, decltype(h)::value, decltype(dh)::value>(i, ld, a, cfg, L, S, means, weights, A,
                                                                              rgb, g_rgb, D, g_means);
    });
}

#define RGS_INSTANTIATE(T)                                                                                          \
    template void illumination_forward_cpu<T>(int64_t, const T*, const T*, const IllumConfig&, double, const T*, T*, \
                                              T*, int64_t, int);                                                           \
    template void illumination_backward_cpu<T>(int64_t, const T*, const T*, const IllumConfig&, double, const T*,   \
                                               const T*, const T*, const T*, T*, T*, int64_t, int);
RGS_INSTANTIATE(float)
RGS_INSTANTIATE(double)
#undef RGS_INSTANTIATE

}  // namespace rgs
