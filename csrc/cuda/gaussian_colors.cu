// Per-Gaussian colours (SH reflectance + illumination MLP) on the GPU: one thread per Gaussian; every block first
// copies the packed MLP weights into shared memory (62 KB in float32 for the default widths), so each layer reads
// them as broadcasts instead of from L2.
#include "common.cuh"
#include "rgs/gaussian_colors.h"
#include "rgs/kernels_cuda.h"

namespace rgs {

constexpr int kColorThreads = 128;
constexpr int kMaxDevices = 64;

template <typename T, int H, int DH, bool kShared>
__global__ void __launch_bounds__(kColorThreads)
gaussian_colors_kernel(int64_t N, ColorArgs<T> a, IllumConfig cfg, IllumLayout L, int C,
                       const T* __restrict__ means,    // [N, 3]
                       const T* __restrict__ sh_dc,    // [N, 3]
                       const T* __restrict__ sh_rest,  // [N, rest, 3]
                       const T* __restrict__ weights,  // [L.total] device memory
                       T* __restrict__ colors) {       // [N, C]
    extern __shared__ __align__(16) unsigned char smem_raw[];
    const T* W = weights;
    if constexpr (kShared) {
        // 16-byte copies, several in flight per thread: a scalar loop would pay one L2 round trip per element.
        // L.total is a multiple of 4 elements and weights is 16-byte aligned (checked by the binding).
        const uint4* src = reinterpret_cast<const uint4*>(weights);
        uint4* dst = reinterpret_cast<uint4*>(smem_raw);
        const int n16 = int(L.total * int64_t(sizeof(T)) / 16);
#pragma unroll 4
        for (int k = threadIdx.x; k < n16; k += blockDim.x) dst[k] = src[k];
        __syncthreads();  // before any thread returns
        W = reinterpret_cast<const T*>(smem_raw);
    }
    const int64_t i = int64_t(blockIdx.x) * blockDim.x + threadIdx.x;
    if (i >= N) return;
    T out[6];
    gaussian_colors<T, H, DH>(i, a, cfg, L, means, sh_dc, sh_rest, W, out);
    for (int c = 0; c < C; ++c) colors[i * C + c] = out[c];
}

// Raises the shared-weights kernel's dynamic shared-memory limit (the default cap is 48 KB), remembered per
// instantiation and device so that it costs one driver call.
template <typename T, int H, int DH>
void allow_shared_bytes(size_t bytes, int device) {
    static size_t allowed[kMaxDevices] = {};
    const bool known = device >= 0 && device < kMaxDevices;
    if (bytes <= 48 * 1024 || (known && allowed[device] >= bytes)) return;
    check_cuda(cudaFuncSetAttribute(gaussian_colors_kernel<T, H, DH, true>,
                                    cudaFuncAttributeMaxDynamicSharedMemorySize, int(bytes)),
               "gaussian_colors (shared memory limit)");
    if (known) allowed[device] = bytes;
}

template <typename T>
void gaussian_colors_cuda(int64_t N, int degree, int rest, const T* means, const T* sh_dc, const T* sh_rest,
                          const T* center, const IllumConfig* illum, double bound, const T* weights, T* colors,
                          void* stream) {
    if (N == 0) return;
    const ColorArgs<T> a = make_color_args<T>(degree, rest, center, bound);
    const IllumConfig cfg = illum ? *illum : IllumConfig{0, 0, 0, 1, 0};
    const IllumLayout L = illum_layout(cfg);
    const int C = illum ? 6 : 3;
    int device = 0, max_shared = 0;
    check_cuda(cudaGetDevice(&device), "gaussian_colors (device)");
    check_cuda(cudaDeviceGetAttribute(&max_shared, cudaDevAttrMaxSharedMemoryPerBlockOptin, device),
               "gaussian_colors (shared memory size)");
    const size_t bytes = illum ? size_t(L.total) * sizeof(T) : 0;
    // Weights too large for shared memory are read from global memory (through L1/L2) instead.
    const bool shared = illum && bytes <= size_t(max_shared);
    dispatch_illum_widths(illum, [&](auto h, auto dh) {
        constexpr int H = decltype(h)::value, DH = decltype(dh)::value;
        const int blocks = num_blocks(N, kColorThreads);
        auto* s = static_cast<cudaStream_t>(stream);
        if (shared) {
            allow_shared_bytes<T, H, DH>(bytes, device);
            gaussian_colors_kernel<T, H, DH, true><<<blocks, kColorThreads, bytes, s>>>(N, a, cfg, L, C, means, sh_dc,
                                                                                       sh_rest, weights, colors);
        } else {
            gaussian_colors_kernel<T, H, DH, false><<<blocks, kColorThreads, 0, s>>>(N, a, cfg, L, C, means, sh_dc,
                                                                                    sh_rest, weights, colors);
        }
    });
    RGS_CHECK_LAUNCH("gaussian_colors");
}

#define RGS_INSTANTIATE(T)                                                                                  \
    template void gaussian_colors_cuda<T>(int64_t, int, int, const T*, const T*, const T*, const T*,       \
                                          const IllumConfig*, double, const T*, T*, void*);
RGS_INSTANTIATE(float)
RGS_INSTANTIATE(double)
#undef RGS_INSTANTIATE

}  // namespace rgs
