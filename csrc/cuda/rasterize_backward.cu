// Back-to-front gradient of the compositing on the GPU: one block per tile, one thread per pixel, walking the
// tile's Gaussians from the last contributor back and recovering T_i = T_{i+1} / (1 - α_i). Each Gaussian's
// per-pixel gradients are summed across the warp with shuffles before one atomicAdd per warp; where one lane alone
// is touched (a Gaussian's rim, a small Gaussian) its own values are the sums, and the 5·(6+C) shuffles are skipped.
#include "common.cuh"
#include "rgs/kernels_cuda.h"
#include "rgs/math.h"

namespace rgs {

constexpr int kBlockB = kTileSize * kTileSize;

// The batch's colours are staged in shared memory beside its conics when they fit (training's 6-7 channels);
// wider renders read them from global memory.
template <int CMAX>
constexpr bool kStageColors = CMAX <= 8;
// Three blocks an SM, as before the staging, for training's float kernel (6-7 channels): without the hint ptxas fits the
// CMAX-8 kernel into 64 registers and spills; the hint keeps it at 72 with no spill. Others as ptxas picks (0: no hint).
template <typename T, int CMAX>
constexpr int kMinBlocks = sizeof(T) == 4 && CMAX == 8 ? 3 : 0;

template <typename T, int CMAX>
__global__ void __launch_bounds__(kBlockB, (kMinBlocks<T, CMAX>))
rasterize_backward_kernel(OutputLayout<T> layout, int width, int height, TileGrid grid,
                          const T* __restrict__ means2d,            // [N, 2]
                          const T* __restrict__ conics,             // [N, 3]
                          const T* __restrict__ colors,             // [N, C]
                          const T* __restrict__ opacities,          // [N]
                          const int32_t* __restrict__ gauss_ids,    // [M]
                          const int32_t* __restrict__ tile_ranges,  // [tiles, 2]
                          const T* __restrict__ transmittance,      // [H, W]
                          const int32_t* __restrict__ last_ids,     // [H, W]
                          const T* __restrict__ v_image,            // [H, W, layout.stride()]
                          const T* __restrict__ v_transmittance,    // [H, W] or nullptr
                          T* __restrict__ v_means2d,                // [N, 2] accumulated
                          T* __restrict__ v_conics,                 // [N, 3] accumulated
                          T* __restrict__ v_colors,                 // [N, C] accumulated
                          T* __restrict__ v_opacities) {            // [N] accumulated
    __shared__ int32_t s_id[kBlockB];
    __shared__ Vec3<T> s_conic[kBlockB];
    __shared__ T s_xyo[kBlockB][3];
    __shared__ T s_col[kBlockB][kStageColors<CMAX> ? CMAX : 1];
    __shared__ int s_end;

    const int C = layout.C;
    const int tile = blockIdx.x;
    const int tid = threadIdx.x;
    const int lane = tid & 31;
    const int px = (tile % grid.tiles_x) * kTileSize + tid % kTileSize;
    const int py = (tile / grid.tiles_x) * kTileSize + tid / kTileSize;
    const bool inside = px < width && py < height;
    const int64_t pix = int64_t(py) * width + px;
    const int begin = tile_ranges[2 * tile];
    const T fx = T(px) + T(0.5), fy = T(py) + T(0.5);

    const int last = inside ? last_ids[pix] : begin;
    const T T_final = inside ? transmittance[pix] : T(1);
    const int64_t at = pix * layout.stride();
    const T v_T = inside ? transmittance_grad(layout, v_image + at, v_transmittance ? v_transmittance[pix] : T(0))
                         : T(0);
    T T_run = T_final;
    T v_img[CMAX], behind[CMAX];
#pragma unroll
    for (int c = 0; c < CMAX; ++c) {
        v_img[c] = (inside && c < C) ? v_image[at + c] : T(0);
        behind[c] = T(0);
    }
    // Only pairs before the tile's largest last contributor matter.
    if (tid == 0) s_end = begin;
    __syncthreads();
    atomicMax(&s_end, last);
    __syncthreads();
    const int end = s_end;

    for (int top = end; top > begin; top -= kBlockB) {
        const int base = max(begin, top - kBlockB);
        const int count = top - base;
        __syncthreads();  // the previous batch is no longer read
        if (tid < count) {
            const int32_t g = gauss_ids[base + tid];
            s_id[tid] = g;
            s_conic[tid] = Vec3<T>{conics[3 * g], conics[3 * g + 1], conics[3 * g + 2]};
            s_xyo[tid][0] = means2d[2 * g];
            s_xyo[tid][1] = means2d[2 * g + 1];
            s_xyo[tid][2] = opacities[g];
            if constexpr (kStageColors<CMAX>) {
#pragma unroll
                for (int c = 0; c < CMAX; ++c)
                    if (c < C) s_col[tid][c] = colors[int64_t(g) * C + c];
            }
        }
        __syncthreads();
        for (int j = count - 1; j >= 0; --j) {
            const int k = base + j;
            const Vec3<T> conic = s_conic[j];
            const T o = s_xyo[j][2];
            PixelAlpha<T> pa;
            bool valid = inside && k < last;
            if (valid) {
                pa = pixel_alpha(conic, s_xyo[j][0], s_xyo[j][1], o, fx, fy);
                valid = pa.alpha != T(0);
            }
            const unsigned touched = __ballot_sync(0xffffffffu, valid);
            if (!touched) continue;
            T v_xy[2] = {T(0), T(0)}, v_cn[3] = {T(0), T(0), T(0)}, v_o = T(0), v_col[CMAX];
            const int32_t g = s_id[j];
#pragma unroll
            for (int c = 0; c < CMAX; ++c) v_col[c] = T(0);
            if (valid) {
                const T one_minus = T(1) - pa.alpha;
                const T Ti = T_run / one_minus;
                const T w = pa.alpha * Ti;
                T v_alpha = T(0);
#pragma unroll
                for (int c = 0; c < CMAX; ++c)
                    if (c < C) {
                        const T cc = kStageColors<CMAX> ? s_col[j][c] : colors[int64_t(g) * C + c];
                        v_col[c] = w * v_img[c];
                        v_alpha += v_img[c] * (Ti * cc - behind[c] / one_minus);
                        behind[c] += w * cc;
                    }
                v_alpha -= v_T * T_final / one_minus;
                pixel_alpha_vjp(pa, conic, o, v_alpha, v_xy, v_cn, v_o);
                T_run = Ti;
            }
            // One lane touched: its values are the warp's sums (the branch is the same on every lane).
            int writer = 0;
            if ((touched & (touched - 1)) == 0) {
                writer = __ffs(touched) - 1;
            } else {  // sum over the warp, then one atomic per component from lane 0
                v_xy[0] = warp_sum(v_xy[0]);
                v_xy[1] = warp_sum(v_xy[1]);
                v_cn[0] = warp_sum(v_cn[0]);
                v_cn[1] = warp_sum(v_cn[1]);
                v_cn[2] = warp_sum(v_cn[2]);
                v_o = warp_sum(v_o);
#pragma unroll
                for (int c = 0; c < CMAX; ++c)
                    if (c < C) v_col[c] = warp_sum(v_col[c]);
            }
            if (lane == writer) {
                atomicAdd(v_means2d + 2 * g, v_xy[0]);
                atomicAdd(v_means2d + 2 * g + 1, v_xy[1]);
                atomicAdd(v_conics + 3 * g, v_cn[0]);
                atomicAdd(v_conics + 3 * g + 1, v_cn[1]);
                atomicAdd(v_conics + 3 * g + 2, v_cn[2]);
                atomicAdd(v_opacities + g, v_o);
#pragma unroll
                for (int c = 0; c < CMAX; ++c)
                    if (c < C) atomicAdd(v_colors + int64_t(g) * C + c, v_col[c]);
            }
        }
    }
}

template <typename T, int CMAX>
static void launch_backward(const OutputLayout<T>& layout, int width, int height, TileGrid grid, const T* means2d, const T* conics,
                            const T* colors, const T* opacities, const int32_t* gauss_ids,
                            const int32_t* tile_ranges, const T* transmittance, const int32_t* last_ids,
                            const T* v_image, const T* v_transmittance, T* v_means2d, T* v_conics, T* v_colors,
                            T* v_opacities, cudaStream_t stream) {
    rasterize_backward_kernel<T, CMAX><<<grid.count(), kBlockB, 0, stream>>>(
        layout, width, height, grid, means2d, conics, colors, opacities, gauss_ids, tile_ranges, transmittance, last_ids,
        v_image, v_transmittance, v_means2d, v_conics, v_colors, v_opacities);
}

template <typename T>
void rasterize_backward_cuda(int64_t N, const OutputLayout<T>& layout, int width, int height, const T* means2d,
                             const T* conics,
                             const T* colors, const T* opacities, const int32_t* gauss_ids,
                             const int32_t* tile_ranges, int64_t M, const T* transmittance, const int32_t* last_ids,
                             const T* v_image, const T* v_transmittance, T* v_means2d, T* v_conics, T* v_colors,
                             T* v_opacities, void* stream_) {
    (void)N;
    (void)M;
    const int C = layout.C;
    const TileGrid grid = make_tile_grid(width, height);
    cudaStream_t stream = (cudaStream_t)stream_;
#define RGS_LAUNCH(CM)                                                                                           \
    launch_backward<T, CM>(layout, width, height, grid, means2d, conics, colors, opacities, gauss_ids, tile_ranges,   \
                           transmittance, last_ids, v_image, v_transmittance, v_means2d, v_conics, v_colors,      \
                           v_opacities, stream)
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
    RGS_CHECK_LAUNCH("rasterize_backward");
}

#define RGS_INSTANTIATE(T)                                                                                        \
    template void rasterize_backward_cuda<T>(int64_t, const OutputLayout<T>&, int, int, const T*, const T*,        \
                                             const T*, const T*,                                                 \
                                             const int32_t*, const int32_t*, int64_t, const T*, const int32_t*,    \
                                             const T*, const T*, T*, T*, T*, T*, void*);
RGS_INSTANTIATE(float)
RGS_INSTANTIATE(double)
#undef RGS_INSTANTIATE

}  // namespace rgs
