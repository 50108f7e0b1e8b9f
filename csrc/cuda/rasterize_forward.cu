// Front-to-back alpha compositing on the GPU (3DGS eq. 3): one 16x16 thread block per tile, one thread per pixel.
// The tile's Gaussians are staged through shared memory in batches of 256; the per-pixel alpha is the shared
// math's (pixel_alpha), so the CPU and CUDA paths composite identically. The channel count is a template bound
// CMAX (accumulators stay in registers) with the exact C checked at run time.
#include "common.cuh"
#include "rgs/kernels_cuda.h"
#include "rgs/math.h"

namespace rgs {

constexpr int kBlock = kTileSize * kTileSize;

template <typename T, int CMAX>
__global__ void __launch_bounds__(kBlock)
rasterize_forward_kernel(OutputLayout<T> layout, int width, int height, TileGrid grid,
                         const T* __restrict__ means2d,           // [N, 2]
                         const T* __restrict__ conics,            // [N, 3]
                         const T* __restrict__ colors,            // [N, C]
                         const T* __restrict__ opacities,         // [N]
                         const int32_t* __restrict__ gauss_ids,   // [M]
                         const int32_t* __restrict__ tile_ranges, // [tiles, 2]
                         T* __restrict__ image,                   // [H, W, layout.stride()]
                         T* __restrict__ transmittance,           // [H, W]
                         int32_t* __restrict__ last_ids) {        // [H, W]
    __shared__ int32_t s_id[kBlock];
    __shared__ Vec3<T> s_conic[kBlock];
    __shared__ T s_xyo[kBlock][3];  // mean x, mean y, opacity

    const int C = layout.C;
    const int tile = blockIdx.x;
    const int tid = threadIdx.x;
    const int px = (tile % grid.tiles_x) * kTileSize + tid % kTileSize;
    const int py = (tile / grid.tiles_x) * kTileSize + tid / kTileSize;
    const bool inside = px < width && py < height;
    const int begin = tile_ranges[2 * tile], end = tile_ranges[2 * tile + 1];
    const T fx = T(px) + T(0.5), fy = T(py) + T(0.5);

    T Tr = T(1);
    T acc[CMAX];
#pragma unroll
    for (int c = 0; c < CMAX; ++c) acc[c] = T(0);
    int last = begin;
    bool done = !inside;

    for (int base = begin; base < end; base += kBlock) {
        if (__syncthreads_count(done) == kBlock) break;
        const int k = base + tid;
        if (k < end) {
            const int32_t g = gauss_ids[k];
            s_id[tid] = g;
            s_conic[tid] = Vec3<T>{conics[3 * g], conics[3 * g + 1], conics[3 * g + 2]};
            s_xyo[tid][0] = means2d[2 * g];
            s_xyo[tid][1] = means2d[2 * g + 1];
            s_xyo[tid][2] = opacities[g];
        }
        __syncthreads();
        const int count = min(kBlock, end - base);
        for (int j = 0; j < count && !done; ++j) {
            const PixelAlpha<T> pa = pixel_alpha(s_conic[j], s_xyo[j][0], s_xyo[j][1], s_xyo[j][2], fx, fy);
            if (pa.alpha == T(0)) continue;
            const T next_T = Tr * (T(1) - pa.alpha);
            if (next_T < T(kTransmittanceMin)) {  // saturated: this Gaussian is not composited
                done = true;
                break;
            }
            const T w = pa.alpha * Tr;
            const T* col = colors + int64_t(s_id[j]) * C;
#pragma unroll
            for (int c = 0; c < CMAX; ++c)
                if (c < C) acc[c] += w * col[c];
            Tr = next_T;
            last = base + j + 1;
        }
    }
    if (!inside) return;
    const int64_t pix = int64_t(py) * width + px;
    transmittance[pix] = Tr;
    last_ids[pix] = last;
    const int S = layout.stride();
#pragma unroll
    for (int c = 0; c < CMAX; ++c)
        if (c < C) image[pix * S + c] = output_value(layout, c, acc[c], Tr);
    if (layout.alpha) image[pix * S + C] = T(1) - Tr;
}

template <typename T, int CMAX>
static void launch_forward(const OutputLayout<T>& layout, int width, int height, TileGrid grid, const T* means2d, const T* conics,
                           const T* colors, const T* opacities, const int32_t* gauss_ids, const int32_t* tile_ranges,
                           T* image, T* transmittance, int32_t* last_ids, cudaStream_t stream) {
    rasterize_forward_kernel<T, CMAX><<<grid.count(), kBlock, 0, stream>>>(
        layout, width, height, grid, means2d, conics, colors, opacities, gauss_ids, tile_ranges, image, transmittance,
        last_ids);
}

template <typename T>
void rasterize_forward_cuda(int64_t N, const OutputLayout<T>& layout, int width, int height, const T* means2d,
                            const T* conics,
                            const T* colors, const T* opacities, const int32_t* gauss_ids,
                            const int32_t* tile_ranges, T* image, T* transmittance, int32_t* last_ids,
                            void* stream_) {
    (void)N;
    const int C = layout.C;
    const TileGrid grid = make_tile_grid(width, height);
    cudaStream_t stream = (cudaStream_t)stream_;
#define RGS_LAUNCH(CM) \
    launch_forward<T, CM>(layout, width, height, grid, means2d, conics, colors, opacities, gauss_ids, tile_ranges, image, \
                          transmittance, last_ids, stream)
    if (C <= 1) RGS_LAUNCH(1);
    else if (C <= 2) RGS_LAUNCH(2);
    else if (C <= 3) RGS_LAUNCH(3);
    else if (C <= 4) RGS_LAUNCH(4);
    else if (C <= 8) RGS_LAUNCH(8);
    else if (C <= 16) RGS_LAUNCH(16);
    else if (C <= 32) RGS_LAUNCH(32);
    else if (C <= kMaxCudaChannels) RGS_LAUNCH(64);
    else throw std::invalid_argument("CUDA compositing supports at most 64 channels");
#undef RGS_LAUNCH
    RGS_CHECK_LAUNCH("rasterize_forward");
}

#define RGS_INSTANTIATE(T)                                                                                       \
    template void rasterize_forward_cuda<T>(int64_t, const OutputLayout<T>&, int, int, const T*, const T*,       \
                                            const T*, const T*, const int32_t*, const int32_t*, T*, T*, int32_t*, \
                                            void*);
RGS_INSTANTIATE(float)
RGS_INSTANTIATE(double)
#undef RGS_INSTANTIATE

}  // namespace rgs
