// Spherical-harmonics colours on the GPU: one thread per Gaussian over the shared basis.
#include "common.cuh"
#include "rgs/kernels_cuda.h"
#include "rgs/math.h"

namespace rgs {

template <typename T>
__global__ void sh_forward_kernel(int64_t N, int degree, int K, int D,
                                  const T* __restrict__ dirs,    // [N, 3]
                                  const T* __restrict__ coeffs,  // [N, K, D]
                                  T* __restrict__ colors) {      // [N, D]
    const int64_t i = int64_t(blockIdx.x) * blockDim.x + threadIdx.x;
    if (i >= N) return;
    T x, y, z, B[kMaxShCoeffs];
    normalize3(dirs + 3 * i, x, y, z);
    sh_basis(degree, x, y, z, B);
    const int nb = sh_num_bases(degree);
    const T* c = coeffs + i * K * D;
    for (int d = 0; d < D; ++d) {
        T acc = T(0);
        for (int k = 0; k < nb; ++k) acc += B[k] * c[k * D + d];
        colors[i * D + d] = acc;
    }
}

template <typename T>
__global__ void sh_backward_kernel(int64_t N, int degree, int K, int D, const T* __restrict__ dirs,
                                   const T* __restrict__ coeffs, const T* __restrict__ v_colors,  // [N, D]
                                   T* __restrict__ v_dirs,                                         // [N, 3]
                                   T* __restrict__ v_coeffs) {                                     // [N, K, D]
    const int64_t i = int64_t(blockIdx.x) * blockDim.x + threadIdx.x;
    if (i >= N) return;
    T x, y, z, B[kMaxShCoeffs], vB[kMaxShCoeffs];
    const T n = normalize3(dirs + 3 * i, x, y, z);
    sh_basis(degree, x, y, z, B);
    const int nb = sh_num_bases(degree);
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

template <typename T>
void sh_forward_cuda(int64_t N, int degree, int K, int D, const T* dirs, const T* coeffs, T* colors, void* stream) {
    if (N == 0) return;
    sh_forward_kernel<T><<<num_blocks(N, 256), 256, 0, (cudaStream_t)stream>>>(N, degree, K, D, dirs, coeffs, colors);
    RGS_CHECK_LAUNCH("sh_forward");
}

template <typename T>
void sh_backward_cuda(int64_t N, int degree, int K, int D, const T* dirs, const T* coeffs, const T* v_colors,
                      T* v_dirs, T* v_coeffs, void* stream) {
    if (N == 0) return;
    sh_backward_kernel<T><<<num_blocks(N, 256), 256, 0, (cudaStream_t)stream>>>(N, degree, K, D, dirs, coeffs,
                                                                                v_colors, v_dirs, v_coeffs);
    RGS_CHECK_LAUNCH("sh_backward");
}

#define RGS_INSTANTIATE(T)                                                                                   \
    template void sh_forward_cuda<T>(int64_t, int, int, int, const T*, const T*, T*, void*);                 \
    template void sh_backward_cuda<T>(int64_t, int, int, int, const T*, const T*, const T*, T*, T*, void*);
RGS_INSTANTIATE(float)
RGS_INSTANTIATE(double)
#undef RGS_INSTANTIATE

}  // namespace rgs
