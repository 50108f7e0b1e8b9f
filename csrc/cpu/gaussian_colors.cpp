// Per-Gaussian colours (SH reflectance + illumination MLP) on the CPU: one OpenMP iteration per Gaussian.
#include <omp.h>

#include "rgs/gaussian_colors.h"
#include "rgs/kernels.h"

namespace rgs {

template <typename T>
void gaussian_colors_cpu(int64_t N, int degree, int rest, const T* means, const T* sh_dc, const T* sh_rest,
                         const T* center, const IllumConfig* illum, double bound, const T* weights, T* colors,
                         int num_threads) {
    if (N == 0) return;
    const ColorArgs<T> a = make_color_args<T>(degree, rest, center, bound);
    const IllumConfig cfg = illum ? *illum : IllumConfig{0, 0, 0, 1, 0};
    const IllumLayout L = illum_layout(cfg);
    const int C = illum ? 6 : 3;
    dispatch_illum_widths(illum, [&](auto h, auto dh) {
        constexpr int H = decltype(h)::value, DH = decltype(dh)::value;
#pragma omp parallel for schedule(static) num_threads(num_threads)
        for (int64_t i = 0; i < N; ++i) {
            T out[6];
            gaussian_colors<T, H, DH>(i, a, cfg, L, means, sh_dc, sh_rest, weights, out);
            for (int c = 0; c < C; ++c) colors[i * C + c] = out[c];
        }
    });
}

#define RGS_INSTANTIATE(T)                                                                                 \
    template void gaussian_colors_cpu<T>(int64_t, int, int, const T*, const T*, const T*, const T*,       \
                                         const IllumConfig*, double, const T*, T*, int);
RGS_INSTANTIATE(float)
RGS_INSTANTIATE(double)
#undef RGS_INSTANTIATE

}  // namespace rgs
