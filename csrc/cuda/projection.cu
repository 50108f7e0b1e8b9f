// Projection stage on the GPU: one thread per Gaussian over the shared math (csrc/include/rgs/math.h).
#include "common.cuh"
#include "rgs/kernels_cuda.h"
#include "rgs/math.h"

namespace rgs {

template <typename T>
__global__ void project_forward_kernel(int64_t N,
                                       const T* __restrict__ means,      // [N, 3]
                                       const T* __restrict__ quats,      // [N, 4]
                                       const T* __restrict__ scales,     // [N, 3]
                                       const T* __restrict__ opacities,  // [N]
                                       const Camera<T> cam,
                                       T* __restrict__ means2d,          // [N, 2]
                                       T* __restrict__ depths,           // [N]
                                       T* __restrict__ conics,           // [N, 3]
                                       int32_t* __restrict__ radii,      // [N, 2]
                                       const FiniteCheck<T> check) {     // off when check.flag is null
    const int64_t i = int64_t(blockIdx.x) * blockDim.x + threadIdx.x;
    if (i >= N) return;
    if (check.flag != nullptr &&
        !gaussian_inputs_finite(i, means + 3 * i, quats + 4 * i, scales + 3 * i, opacities[i], check))
        *check.flag = 1;
    Projected<T> p;
    const bool ok = project_gaussian(means + 3 * i, quats + 4 * i, scales + 3 * i, opacities[i], cam, p);
    means2d[2 * i] = ok ? p.mean2d.x : T(0);
    means2d[2 * i + 1] = ok ? p.mean2d.y : T(0);
    depths[i] = ok ? p.depth : T(0);
    conics[3 * i] = ok ? p.conic.x : T(0);
    conics[3 * i + 1] = ok ? p.conic.y : T(0);
    conics[3 * i + 2] = ok ? p.conic.z : T(0);
    radii[2 * i] = ok ? p.radius_x : 0;
    radii[2 * i + 1] = ok ? p.radius_y : 0;
}

template <typename T>
__global__ void project_backward_kernel(int64_t N, const T* __restrict__ means, const T* __restrict__ quats,
                                        const T* __restrict__ scales, const Camera<T> cam,
                                        const int32_t* __restrict__ radii,     // [N, 2]
                                        const T* __restrict__ v_means2d,       // [N, 2]
                                        const T* __restrict__ v_depths,        // [N]
                                        const T* __restrict__ v_conics,        // [N, 3]
                                        T* __restrict__ v_means,               // [N, 3]
                                        T* __restrict__ v_quats,               // [N, 4]
                                        T* __restrict__ v_scales) {            // [N, 3]
    const int64_t i = int64_t(blockIdx.x) * blockDim.x + threadIdx.x;
    if (i >= N) return;
    if (radii[2 * i] <= 0 || radii[2 * i + 1] <= 0) {
        for (int k = 0; k < 3; ++k) v_means[3 * i + k] = v_scales[3 * i + k] = T(0);
        for (int k = 0; k < 4; ++k) v_quats[4 * i + k] = T(0);
        return;
    }
    project_gaussian_vjp(means + 3 * i, quats + 4 * i, scales + 3 * i, cam, v_means2d + 2 * i, v_depths[i],
                         v_conics + 3 * i, v_means + 3 * i, v_quats + 4 * i, v_scales + 3 * i);
}

template <typename T>
void project_forward_cuda(int64_t N, const T* means, const T* quats, const T* scales, const T* opacities,
                          const Camera<T>& cam, T* means2d, T* depths, T* conics, int32_t* radii,
                          const FiniteCheck<T>& check, void* stream) {
    if (N == 0) return;
    project_forward_kernel<T><<<num_blocks(N, 256), 256, 0, (cudaStream_t)stream>>>(
        N, means, quats, scales, opacities, cam, means2d, depths, conics, radii, check);
    RGS_CHECK_LAUNCH("project_forward");
}

template <typename T>
void project_backward_cuda(int64_t N, const T* means, const T* quats, const T* scales, const Camera<T>& cam,
                           const int32_t* radii, const T* v_means2d, const T* v_depths, const T* v_conics,
                           T* v_means, T* v_quats, T* v_scales, void* stream) {
    if (N == 0) return;
    project_backward_kernel<T><<<num_blocks(N, 256), 256, 0, (cudaStream_t)stream>>>(
        N, means, quats, scales, cam, radii, v_means2d, v_depths, v_conics, v_means, v_quats, v_scales);
    RGS_CHECK_LAUNCH("project_backward");
}

#define RGS_INSTANTIATE(T)                                                                                        \
    template void project_forward_cuda<T>(int64_t, const T*, const T*, const T*, const T*, const Camera<T>&, T*,   \
                                          T*, T*, int32_t*, const FiniteCheck<T>&, void*);                        \
    template void project_backward_cuda<T>(int64_t, const T*, const T*, const T*, const Camera<T>&, const int32_t*, \
                                           const T*, const T*, const T*, T*, T*, T*, void*);
RGS_INSTANTIATE(float)
RGS_INSTANTIATE(double)
#undef RGS_INSTANTIATE

}  // namespace rgs
