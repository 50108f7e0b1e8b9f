// Back-to-front gradient of the compositing on the CPU. Each tile walks its Gaussians from the last
// contributor back, recovering T_i = T_{i+1} / (1 - α_i). Gradients land in one slot per (tile, Gaussian)
// pair and are then summed per Gaussian in pair order, so the result is bit-identical for any thread count.
#include <omp.h>

#include <vector>

#include "rgs/kernels.h"
#include "rgs/math.h"

namespace rgs {

template <typename T>
void rasterize_backward_cpu(int64_t N, const OutputLayout<T>& layout, int width, int height, const T* means2d,
                            const T* conics,
                            const T* colors, const T* opacities, const int32_t* gauss_ids,
                            const int32_t* tile_ranges, int64_t M, const T* transmittance, const int32_t* last_ids,
                            const T* v_image, const T* v_transmittance, T* v_means2d, T* v_conics, T* v_colors,
                            T* v_opacities, int num_threads) {
    const TileGrid grid = make_tile_grid(width, height);
    const int C = layout.C, stride = layout.stride();
    const int S = 6 + C;  // slot layout: mean2d (2), conic (3), opacity (1), colours (C)
    std::vector<T> slots(size_t(M) * S, T(0));
#pragma omp parallel num_threads(num_threads)
    {
        // Per-pixel running state of the tile: T after the current Gaussian, the colour behind it, and the
        // pixel's own inputs copied once.
        constexpr int P = kTileSize * kTileSize;
        std::vector<T> T_run(P), T_final(P), v_T(P), behind(size_t(P) * C), v_img(size_t(P) * C);
        std::vector<int32_t> last(P);
#pragma omp for schedule(dynamic, 1)
        for (int t = 0; t < grid.count(); ++t) {
            const int tx0 = (t % grid.tiles_x) * kTileSize, ty0 = (t / grid.tiles_x) * kTileSize;
            const int tx1 = tx0 + kTileSize < width ? tx0 + kTileSize : width;
            const int ty1 = ty0 + kTileSize < height ? ty0 + kTileSize : height;
            const int begin = tile_ranges[2 * t];
            int end = begin;
            for (int y = ty0; y < ty1; ++y)
                for (int x = tx0; x < tx1; ++x) {
                    const int64_t pix = int64_t(y) * width + x;
                    const int l = (y - ty0) * kTileSize + (x - tx0);
                    T_run[l] = T_final[l] = transmittance[pix];
                    v_T[l] = transmittance_grad(layout, v_image + pix * stride,
                                                v_transmittance ? v_transmittance[pix] : T(0));
                    last[l] = last_ids[pix];
                    for (int c = 0; c < C; ++c) {
                        behind[size_t(l) * C + c] = T(0);
                        v_img[size_t(l) * C + c] = v_image[pix * stride + c];
                    }
                    if (last[l] > end) end = last[l];
                }
            for (int k = end - 1; k >= begin; --k) {
                const int32_t g = gauss_ids[k];
                const Vec3<T> conic{conics[3 * g], conics[3 * g + 1], conics[3 * g + 2]};
                const T mx = means2d[2 * g], my = means2d[2 * g + 1], o = opacities[g];
                int x0, y0, x1, y1;
                if (!pixel_box(conic, mx, my, o, tx0, ty0, tx1, ty1, x0, y0, x1, y1)) continue;
                const T cut = sigma_cutoff(o);
                const T* col = colors + int64_t(g) * C;
                T* slot = slots.data() + size_t(k) * S;
                for (int y = y0; y <= y1; ++y) {
                    const T dy = T(y) + T(0.5) - my;
                    int xa, xb;
                    if (!row_span(conic, cut, mx, dy, x0, x1, xa, xb)) continue;
                    for (int x = xa; x <= xb; ++x) {
                        const int l = (y - ty0) * kTileSize + (x - tx0);
                        const T dx = T(x) + T(0.5) - mx;
                        const T sigma = pixel_sigma(conic, dx, dy);
                        if (sigma > cut || k >= last[l]) continue;
                        const PixelAlpha<T> pa = alpha_from_sigma(sigma, o, dx, dy);
                        if (pa.alpha == T(0)) continue;
                        const T one_minus = T(1) - pa.alpha;
                        const T Ti = T_run[l] / one_minus;  // T before this Gaussian
                        const T w = pa.alpha * Ti;
                        const T* vimg = v_img.data() + size_t(l) * C;
                        T* bh = behind.data() + size_t(l) * C;
                        // dC/dα_i = T_i c_i - (Σ_{j>i} w_j c_j) / (1 - α_i)
                        T v_alpha = T(0);
                        for (int c = 0; c < C; ++c) {
                            slot[6 + c] += w * vimg[c];
                            v_alpha += vimg[c] * (Ti * col[c] - bh[c] / one_minus);
                            bh[c] += w * col[c];
                        }
                        // T_final = Π (1 - α_j)  =>  dT_final/dα_i = -T_final / (1 - α_i)
                        v_alpha -= v_T[l] * T_final[l] / one_minus;
                        pixel_alpha_vjp(pa, conic, o, v_alpha, slot, slot + 2, slot[5]);
                        T_run[l] = Ti;
                    }
                }
            }
        }
        // Sum the slots per Gaussian in pair order; Gaussians are split between threads, not pairs.
        const int nt = omp_get_num_threads(), tid = omp_get_thread_num();
        const int64_t g0 = N * tid / nt, g1 = N * (tid + 1) / nt;
        for (int64_t g = g0; g < g1; ++g) {
            v_means2d[2 * g] = v_means2d[2 * g + 1] = T(0);
            v_conics[3 * g] = v_conics[3 * g + 1] = v_conics[3 * g + 2] = T(0);
            v_opacities[g] = T(0);
            for (int c = 0; c < C; ++c) v_colors[g * C + c] = T(0);
        }
        for (int64_t k = 0; k < M; ++k) {
            const int64_t g = gauss_ids[k];
            if (g < g0 || g >= g1) continue;
            const T* s = slots.data() + size_t(k) * S;
            v_means2d[2 * g] += s[0];
            v_means2d[2 * g + 1] += s[1];
            v_conics[3 * g] += s[2];
            v_conics[3 * g + 1] += s[3];
            v_conics[3 * g + 2] += s[4];
            v_opacities[g] += s[5];
            for (int c = 0; c < C; ++c) v_colors[g * C + c] += s[6 + c];
        }
    }
}

#define RGS_INSTANTIATE(T)                                                                                     \
    template void rasterize_backward_cpu<T>(int64_t, const OutputLayout<T>&, int, int, const T*, const T*,      \
                                            const T*, const T*, const int32_t*, const int32_t*, int64_t,        \
                                            const T*, const int32_t*,                                           \
                                            const T*, const T*, T*, T*, T*, T*, int);
RGS_INSTANTIATE(float)
RGS_INSTANTIATE(double)
#undef RGS_INSTANTIATE

}  // namespace rgs
