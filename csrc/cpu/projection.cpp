// Projection stage on the CPU: one OpenMP iteration per Gaussian over the shared math.
#include <omp.h>

#include "rgs/kernels.h"
#include "rgs/math.h"

namespace rgs {

template <typename T>
void project_forward_cpu(int64_t N, const T* means, const T* quats, const T* scales, const T* opacities,
                         const Camera<T>& cam, T* means2d, T* depths, T* conics, int32_t* radii,
                         const FiniteCheck<T>& check, int num_threads) {
    int32_t bad = 0;
#pragma omp parallel for schedule(static) num_threads(num_threads) reduction(| : bad)
    for (int64_t i = 0; i < N; ++i) {
        if (check.flag != nullptr && !gaussian_inputs_finite(i, means + 3 * i, quats + 4 * i, scales + 3 * i,
                                                             opacities[i], check))
            bad = 1;
        Projected<T> p;
        if (project_gaussian(means + 3 * i, quats + 4 * i, scales + 3 * i, opacities[i], cam, p)) {
            means2d[2 * i] = p.mean2d.x;
            means2d[2 * i + 1] = p.mean2d.y;
            depths[i] = p.depth;
            conics[3 * i] = p.conic.x;
            conics[3 * i + 1] = p.conic.y;
            conics[3 * i + 2] = p.conic.z;
            radii[2 * i] = p.radius_x;
            radii[2 * i + 1] = p.radius_y;
        } else {
            means2d[2 * i] = means2d[2 * i + 1] = T(0);
            depths[i] = T(0);
            conics[3 * i] = conics[3 * i + 1] = conics[3 * i + 2] = T(0);
            radii[2 * i] = radii[2 * i + 1] = 0;
        }
    }
    if (check.flag != nullptr && bad) *check.flag = 1;
}

template <typename T>
void project_backward_cpu(int64_t N, const T* means, const T* quats, const T* scales, const Camera<T>& cam,
                          const int32_t* radii, const T* v_means2d, const T* v_depths, const T* v_conics,
                          T* v_means, T* v_quats, T* v_scales, int num_threads) {
#pragma omp parallel for schedule(static) num_threads(num_threads)
    for (int64_t i = 0; i < N; ++i) {
        if (radii[2 * i] <= 0 || radii[2 * i + 1] <= 0) {  // culled: no gradient
            for (int k = 0; k < 3; ++k) v_means[3 * i + k] = v_scales[3 * i + k] = T(0);
            for (int k = 0; k < 4; ++k) v_quats[4 * i + k] = T(0);
            continue;
        }
        project_gaussian_vjp(means + 3 * i, quats + 4 * i, scales + 3 * i, cam, v_means2d + 2 * i, v_depths[i],
                             v_conics + 3 * i, v_means + 3 * i, v_quats + 4 * i, v_scales + 3 * i);
    }
}

#define RGS_INSTANTIATE(T)                                                                                     \
    template void project_forward_cpu<T>(int64_t, const T*, const T*, const T*, const T*, const Camera<T>&, T*, \
                                         T*, T*, int32_t*, const FiniteCheck<T>&, int);                        \
    template void project_backward_cpu<T>(int64_t, const T*, const T*, const T*, const Camera<T>&,             \
                                          const int32_t*, const T*, const T*, const T*, T*, T*, T*, int);
RGS_INSTANTIATE(float)
RGS_INSTANTIATE(double)
#undef RGS_INSTANTIATE

}  // namespace rgs
