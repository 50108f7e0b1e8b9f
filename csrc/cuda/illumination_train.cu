// The illumination field's MLP in training on the GPU (rgs/illumination_train.h): one thread per Gaussian, the packed
// weights staged in shared memory per block (as gaussian_colors.cu), the saved activations and the output gradients
// in [rows, N] buffers so that a warp's stores are consecutive.
#include "common.cuh"
#include "rgs/illumination_train.h"
#include "rgs/kernels_cuda.h"

namespace rgs {

constexpr int kIllumThreads = 128;
constexpr int kMaxIllumDevices = 64;

// The block's copy of the weights in shared memory (16-byte copies), or the global buffer when kShared is off.
template <typename T, bool kShared>
__device__ __forceinline__ const T* staged_weights(const T* __restrict__ weights, int64_t total, unsigned char* smem) {
    if constexpr (!kShared) {
        return weights;
    } else {
        const uint4* src = reinterpret_cast<const uint4*>(weights);
        uint4* dst = reinterpret_cast<uint4*>(smem);
        const int n16 = int(total * int64_t(sizeof(T)) / 16);
#pragma unroll 4
        for (int k = threadIdx.x; k < n16; k += blockDim.x) dst[k] = src[k];
        __syncthreads();  // before any thread returns
        return reinterpret_cast<const T*>(smem);
    }
}

template <typename T, int H, int DH, bool kShared>
__global__ void __launch_bounds__(kIllumThreads)
illumination_forward_kernel(int64_t N, IllumTrainArgs<T> a, IllumConfig cfg, IllumLayout L, IllumTrainLayout S,
                            const T* __restrict__ means, const T* __restrict__ weights, T* __restrict__ rgb,
                            T* __restrict__ A, int64_t ld) {
    extern __shared__ __align__(16) unsigned char smem_raw[];
    const T* W = staged_weights<T, kShared>(weights, L.total, smem_raw);
    const int64_t i = int64_t(blockIdx.x) * blockDim.x + threadIdx.x;
    if (i >= N) return;
    illumination_forward_one<T, H, DH>(i, ld, a, cfg, L, S, means, W, rgb, A);
}

template <typename T, int H, int DH, bool kShared>
__global__ void __launch_bounds__(kIllumThreads)
illumination_backward_kernel(int64_t N, IllumTrainArgs<T> a, IllumConfig cfg, IllumLayout L, IllumTrainLayout S,
                             const T* __restrict__ means, const T* __restrict__ weights, const T* __restrict__ A,
                             const T* __restrict__ rgb, const T* __restrict__ g_rgb, T* __restrict__ D,
                             T* __restrict__ g_means, int64_t ld) {
    extern __shared__ __align__(16) unsigned char smem_raw[];
    const T* W = staged_weights<T, kShared>(weights, L.total, smem_raw);
    const int64_t i = int64_t(blockIdx.x) * blockDim.x + threadIdx.x;
    if (i >= N) return;
    illumination_backward_one<T, H, DH>(i, ld, a, cfg, L, S, means, W, A, rgb, g_rgb, D, g_means);
}

// Raises a kernel's dynamic shared-memory limit past the default 48 KB, once per kernel and device.
template <typename Kernel>
void allow_illum_shared(Kernel kernel, size_t bytes, int device, size_t* allowed) {
    const bool known = device >= 0 && device < kMaxIllumDevices;
    if (bytes <= 48 * 1024 || (known && allowed[device] >= bytes)) return;
    check_cuda(cudaFuncSetAttribute(kernel, cudaFuncAttributeMaxDynamicSharedMemorySize, int(bytes)),
               "illumination (shared memory limit)");
    if (known) allowed[device] = bytes;
}

// Calls launch(kernel-independent bits): the widths' specialisation, whether the weights fit shared memory.
template <typename T, typename F>
void illum_launch(int64_t N, const IllumConfig& cfg, F&& launch) {
    const IllumLayout L = illum_layout(cfg);
    int device = 0, max_shared = 0;
    check_cuda(cudaGetDevice(&device), "illumination (device)");
    check_cuda(cudaDeviceGetAttribute(&max_shared, cudaDevAttrMaxSharedMemoryPerBlockOptin, device),
               "illumination (shared memory size)");
    const size_t bytes = size_t(L.total) * sizeof(T);
    const bool shared = bytes <= size_t(max_shared);
    dispatch_illum_widths(&cfg, [&](auto h, auto dh) {
        constexpr int H = decltype(h)::value, DH = decltype(dh)::value;
        if constexpr (H >= 0) {
            if (shared)
                launch(std::integral_constant<int, H>{}, std::integral_constant<int, DH>{}, std::true_type{}, bytes,
                       device);
            else
                launch(std::integral_constant<int, H>{}, std::integral_constant<int, DH>{}, std::false_type{}, size_t(0),
                       device);
        }
    });
}

template <typename T>
void illumination_forward_cuda(int64_t N, const T* means, const T* center, const IllumConfig& cfg, double bound,
                               const T* weights, T* rgb, T* A, int64_t ld, void* stream) {
    if (N == 0) return;
    const IllumTrainArgs<T> a{center, T(1) / T(bound), T(bound)};
    const IllumLayout L = illum_layout(cfg);
    const IllumTrainLayout S = illum_train_layout(cfg);
    illum_launch<T>(N, cfg, [&](auto h, auto dh, auto sh, size_t bytes, int device) {
        constexpr int H = decltype(h)::value, DH = decltype(dh)::value;
        constexpr bool kShared = decltype(sh)::value;
        static size_t allowed[kMaxIllumDevices] = {};
        auto kernel = illumination_forward_kernel<T, H, DH, kShared>;
        if constexpr (kShared) allow_illum_shared(kernel, bytes, device, allowed);
        kernel<<<num_blocks(N, kIllumThreads), kIllumThreads, bytes, static_cast<cudaStream_t>(stream)>>>(
            N, a, cfg, L, S, means, weights, rgb, A, ld);
    });
    RGS_CHECK_LAUNCH("illumination_forward");
}

template <typename T>
void illumination_backward_cuda(int64_t N, const T* means, const T* center, const IllumConfig& cfg, double bound,
                                const T* weights, const T* A, const T* rgb, const T* g_rgb, T* D, T* g_means, int64_t ld,
                                void* stream) {
    if (N == 0) return;
    const IllumTrainArgs<T> a{center, T(1) / T(bound), T(bound)};
    const IllumLayout L = illum_layout(cfg);
    const IllumTrainLayout S = illum_train_layout(cfg);
    illum_launch<T>(N, cfg, [&](auto h, auto dh, auto sh, size_t bytes, int device) {
        constexpr int H = decltype(h)::value, DH = decltype(dh)::value;
        constexpr bool kShared = decltype(sh)::value;
        static size_t allowed[kMaxIllumDevices] = {};
        auto kernel = illumination_backward_kernel<T, H, DH, kShared>;
        if constexpr (kShared) allow_illum_shared(kernel, bytes, device, allowed);
        kernel<<<num_blocks(N, kIllumThreads), kIllumThreads, bytes, static_cast<cudaStream_t>(stream)>>>(
            N, a, cfg, L, S, means, weights, A, rgb, g_rgb, D, g_means, ld);
    });
    RGS_CHECK_LAUNCH("illumination_backward");
}

#define RGS_INSTANTIATE(T)                                                                                          \
    template void illumination_forward_cuda<T>(int64_t, const T*, const T*, const IllumConfig&, double, const T*,  \
                                               T*, T*, int64_t, void*);                                                     \
    template void illumination_backward_cuda<T>(int64_t, const T*, const T*, const IllumConfig&, double, const T*, \
                                                const T*, const T*, const T*, T*, T*, int64_t, void*);
RGS_INSTANTIATE(float)
RGS_INSTANTIATE(double)
#undef RGS_INSTANTIATE

}  // namespace rgs
