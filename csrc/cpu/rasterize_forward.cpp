// Front-to-back alpha compositing on the CPU (3DGS eq. 3). One OpenMP task per 16x16 tile; inside a tile the
// Gaussians are the outer loop so each is read once, and only the pixels of its alpha >= 1/255 box are visited.
#include <omp.h>

#include "rgs/kernels.h"
#include "rgs/math.h"

namespace rgs {

template <typename T>
void rasterize_forward_cpu(int64_t N, int C, int width, int height, const T* means2d, const T* conics,
                           const T* colors, const T* opacities, const int32_t* gauss_ids,
                           const int32_t* tile_ranges, T* image, T* transmittance, int32_t* last_ids,
                           int num_threads) {
    (void)N;
    const TileGrid grid = make_tile_grid(width, height);
#pragma omp parallel for schedule(dynamic, 1) num_threads(num_threads)
    for (int t = 0; t < grid.count(); ++t) {
        const int tx0 = (t % grid.tiles_x) * kTileSize, ty0 = (t / grid.tiles_x) * kTileSize;
        const int tx1 = tx0 + kTileSize < width ? tx0 + kTileSize : width;
        const int ty1 = ty0 + kTileSize < height ? ty0 + kTileSize : height;
        const int begin = tile_ranges[2 * t], end = tile_ranges[2 * t + 1];
        bool done[kTileSize * kTileSize];
        int active = 0;
        for (int y = ty0; y < ty1; ++y)
            for (int x = tx0; x < tx1; ++x) {
                const int64_t pix = int64_t(y) * width + x;
                transmittance[pix] = T(1);
                last_ids[pix] = begin;
                for (int c = 0; c < C; ++c) image[pix * C + c] = T(0);
                done[(y - ty0) * kTileSize + (x - tx0)] = false;
                ++active;
            }
        for (int k = begin; k < end && active > 0; ++k) {
            const int32_t g = gauss_ids[k];
            const Vec3<T> conic{conics[3 * g], conics[3 * g + 1], conics[3 * g + 2]};
            const T mx = means2d[2 * g], my = means2d[2 * g + 1], o = opacities[g];
            int x0, y0, x1, y1;
            if (!pixel_box(conic, mx, my, o, tx0, ty0, tx1, ty1, x0, y0, x1, y1)) continue;
            const T* col = colors + int64_t(g) * C;
            for (int y = y0; y <= y1; ++y)
                for (int x = x0; x <= x1; ++x) {
                    bool& pdone = done[(y - ty0) * kTileSize + (x - tx0)];
                    if (pdone) continue;
                    const PixelAlpha<T> pa = pixel_alpha(conic, mx, my, o, T(x) + T(0.5), T(y) + T(0.5));
                    if (pa.alpha == T(0)) continue;
                    const int64_t pix = int64_t(y) * width + x;
                    const T Tr = transmittance[pix];
                    const T next_T = Tr * (T(1) - pa.alpha);
                    if (next_T < T(kTransmittanceMin)) {  // saturated: this Gaussian is not composited
                        pdone = true;
                        --active;
                        continue;
                    }
                    const T w = pa.alpha * Tr;
                    T* out = image + pix * C;
                    for (int c = 0; c < C; ++c) out[c] += w * col[c];
                    transmittance[pix] = next_T;
                    last_ids[pix] = k + 1;
                }
        }
    }
}

#define RGS_INSTANTIATE(T)                                                                                  \
    template void rasterize_forward_cpu<T>(int64_t, int, int, int, const T*, const T*, const T*, const T*,   \
                                           const int32_t*, const int32_t*, T*, T*, int32_t*, int);
RGS_INSTANTIATE(float)
RGS_INSTANTIATE(double)
#undef RGS_INSTANTIATE

}  // namespace rgs
