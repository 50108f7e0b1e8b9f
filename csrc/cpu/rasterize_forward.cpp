// Front-to-back alpha compositing on the CPU (3DGS eq. 3). One OpenMP task per 16x16 tile; inside a tile the
// Gaussians are the outer loop so each is read once, only the pixels of its alpha >= 1/255 box are visited,
// and exp() runs only where σ is below the Gaussian's cutoff. Pixel state stays in tile-local arrays.
#include <omp.h>

#include <vector>

#include "rgs/kernels.h"
#include "rgs/math.h"

namespace rgs {

template <typename T>
void rasterize_forward_cpu(int64_t N, const OutputLayout<T>& layout, int width, int height, const T* means2d,
                           const T* conics, const T* colors, const T* opacities, const int32_t* gauss_ids,
                           const int32_t* tile_ranges, T* image, T* transmittance, int32_t* last_ids,
                           int num_threads) {
    (void)N;
    const int C = layout.C, S = layout.stride();
    constexpr int P = kTileSize * kTileSize;
    const TileGrid grid = make_tile_grid(width, height);
#pragma omp parallel num_threads(num_threads)
    {
        std::vector<T> Tr(P), acc(size_t(P) * C);
        std::vector<int32_t> last(P);
        std::vector<unsigned char> done(P);
#pragma omp for schedule(dynamic, 1)
        for (int t = 0; t < grid.count(); ++t) {
            const int tx0 = (t % grid.tiles_x) * kTileSize, ty0 = (t / grid.tiles_x) * kTileSize;
            const int tx1 = tx0 + kTileSize < width ? tx0 + kTileSize : width;
            const int ty1 = ty0 + kTileSize < height ? ty0 + kTileSize : height;
            const int begin = tile_ranges[2 * t], end = tile_ranges[2 * t + 1];
            int active = (tx1 - tx0) * (ty1 - ty0);
            for (int l = 0; l < P; ++l) {
                Tr[l] = T(1);
                last[l] = begin;
                done[l] = 0;
            }
            for (size_t i = 0; i < acc.size(); ++i) acc[i] = T(0);
            for (int k = begin; k < end && active > 0; ++k) {
                const int32_t g = gauss_ids[k];
                const Vec3<T> conic{conics[3 * g], conics[3 * g + 1], conics[3 * g + 2]};
                const T mx = means2d[2 * g], my = means2d[2 * g + 1], o = opacities[g];
                int x0, y0, x1, y1;
                if (!pixel_box(conic, mx, my, o, tx0, ty0, tx1, ty1, x0, y0, x1, y1)) continue;
                const T cut = sigma_cutoff(o);
                const T* col = colors + int64_t(g) * C;
                for (int y = y0; y <= y1; ++y) {
                    const T dy = T(y) + T(0.5) - my;
                    int xa, xb;
                    if (!row_span(conic, cut, mx, dy, x0, x1, xa, xb)) continue;
                    for (int x = xa; x <= xb; ++x) {
                        const int l = (y - ty0) * kTileSize + (x - tx0);
                        const T dx = T(x) + T(0.5) - mx;
                        const T sigma = pixel_sigma(conic, dx, dy);
                        if (sigma > cut || done[l]) continue;
                        const PixelAlpha<T> pa = alpha_from_sigma(sigma, o, dx, dy);
                        if (pa.alpha == T(0)) continue;
                        const T next_T = Tr[l] * (T(1) - pa.alpha);
                        if (next_T < T(kTransmittanceMin)) {  // saturated: this Gaussian is not composited
                            done[l] = 1;
                            --active;
                            continue;
                        }
                        const T w = pa.alpha * Tr[l];
                        T* a = acc.data() + size_t(l) * C;
                        for (int c = 0; c < C; ++c) a[c] += w * col[c];
                        Tr[l] = next_T;
                        last[l] = k + 1;
                    }
                }
            }
            for (int y = ty0; y < ty1; ++y)
                for (int x = tx0; x < tx1; ++x) {
                    const int l = (y - ty0) * kTileSize + (x - tx0);
                    const int64_t pix = int64_t(y) * width + x;
                    transmittance[pix] = Tr[l];
                    last_ids[pix] = last[l];
                    for (int c = 0; c < C; ++c) image[pix * S + c] = output_value(layout, c, acc[size_t(l) * C + c], Tr[l]);
                    if (layout.alpha) image[pix * S + C] = T(1) - Tr[l];
                }
        }
    }
}

#define RGS_INSTANTIATE(T)                                                                                  \
    template void rasterize_forward_cpu<T>(int64_t, const OutputLayout<T>&, int, int, const T*, const T*,      \
                                           const T*, const T*, const int32_t*, const int32_t*, T*, T*,       \
                                           int32_t*, int);
RGS_INSTANTIATE(float)
RGS_INSTANTIATE(double)
#undef RGS_INSTANTIATE

}  // namespace rgs
