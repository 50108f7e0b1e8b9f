// Spherical-harmonics colours on the CPU: one OpenMP iteration per Gaussian over the shared basis.
#include <omp.h>

#include "rgs/kernels.h"
#include "rgs/math.h"

namespace rgs {

template <typename T>
void sh_forward_cpu(int64_t N, int degree, int K, int D, const T* dirs, const T* coeffs, T* colors,
                    int num_threads) {
    const int nb = sh_num_bases(degree);
#pragma omp parallel for schedule(static) num_threads(num_threads)
    for (int64_t i = 0; i < N; ++i) {
        T x, y, z, B[kMaxShCoeffs];
        normalize3(dirs + 3 * i, x, y, z);
        sh_basis(degree, x, y, z, B);
        const T* c = coeffs + i * K * D;
        for (int d = 0; d < D; ++d) {
            T acc = T(0);
            for (int k = 0; k < nb; ++k) acc += B[k] * c[k * D + d];
            colors[i * D + d] = acc;
        }
    }
}

template <typename T>
void sh_backward_cpu(int64_t N, int degree, int K, int D, const T* dirs, const T* coeffs, const T* v_colors,
                     T* v_dirs, T* v_coeffs, int num_threads) {
    const int nb = sh_num_bases(degree);
#pragma omp parallel for schedule(static) num_threads(num_threads)
    for (int64_t i = 0; i < N; ++i) {
        T x, y, z, B[kMaxShCoeffs], vB[kMaxShCoeffs];
        const T n = normalize3(dirs + 3 * i, x, y, z);
        sh_basis(degree, x, y, z, B);
        const T* c = coeffs + i * K * D;
        const T* vc = v_colors + i * D;
        T* vco = v_coeffs + i * K * D;
        for (int k = 0; k < K; ++k) {
            T acc = T(0);
            for (int d = 0; d < D; ++d) {
                vco[k * D + d] = k < nb ? B[k] * vc[d] : T(0);
                if (k < nb) acc += c[k * D + d] * vc[d];
            }
            if (k < nb) vB[k] = acc;
        }
        T vx, vy, vz;
        sh_basis_vjp(degree, x, y, z, vB, vx, vy, vz);
        normalize3_vjp(n, x, y, z, vx, vy, vz, v_dirs + 3 * i);
    }
}

#define RGS_INSTANTIATE(T)                                                                          \
    template void sh_forward_cpu<T>(int64_t, int, int, int, const T*, const T*, T*, int);          \
    template void sh_backward_cpu<T>(int64_t, int, int, int, const T*, const T*, const T*, T*, T*, int);
RGS_INSTANTIATE(float)
RGS_INSTANTIATE(double)
#undef RGS_INSTANTIATE

}  // namespace rgs
