// Tile binning on the CPU. Deterministic for any thread count: pairs are written at per-Gaussian offsets,
// bucketed by tile with a stable counting sort, then each tile's list is sorted by (depth, Gaussian index).
// With conics and opacities, the tiles of a Gaussian's rectangle that it cannot reach are skipped (TileReach,
// the same test as on the GPU).
#include <omp.h>

#include <algorithm>
#include <vector>

#include "rgs/kernels.h"
#include "rgs/math.h"

namespace rgs {

template <typename T>
int64_t count_tile_pairs_cpu(int64_t N, const T* means2d, const int32_t* radii, const T* conics,
                             const T* opacities, TileGrid grid, int64_t* offsets, int num_threads) {
    // Dynamic: with culling, a Gaussian costs one test per tile of its rectangle.
#pragma omp parallel for schedule(dynamic, 1024) num_threads(num_threads)
    for (int64_t i = 0; i < N; ++i)
        offsets[i + 1] = gaussian_tile_count(gaussian_tile_rect(means2d + 2 * i, radii + 2 * i, grid), means2d + 2 * i,
                                             conics ? conics + 3 * i : nullptr, opacities ? opacities + i : nullptr);
    offsets[0] = 0;
    for (int64_t i = 0; i < N; ++i) offsets[i + 1] += offsets[i];
    return offsets[N];
}

template <typename T>
void bin_tile_pairs_cpu(int64_t N, const T* means2d, const int32_t* radii, const T* conics, const T* opacities,
                        const T* depths, TileGrid grid, const int64_t* offsets, int64_t M, int32_t* gauss_ids,
                        int32_t* tile_ranges, int num_threads) {
    const int n_tiles = grid.count();
    std::vector<int32_t> pair_tile(M), pair_gauss(M);
#pragma omp parallel for schedule(dynamic, 1024) num_threads(num_threads)
    for (int64_t i = 0; i < N; ++i) {
        const TileRect r = gaussian_tile_rect(means2d + 2 * i, radii + 2 * i, grid);
        if (r.area() == 0) continue;
        const bool cull = conics != nullptr;
        const TileReach reach = cull ? TileReach::make(means2d + 2 * i, conics + 3 * i, opacities[i]) : TileReach{};
        int64_t k = offsets[i];
        // k < M: M below the total (a capacity) drops the pairs at offsets >= M, as on the GPU.
        for (int ty = r.y0; ty < r.y1 && k < M; ++ty)
            for (int tx = r.x0; tx < r.x1 && k < M; ++tx) {
                if (cull && !reach.hits(tx, ty)) continue;
                pair_tile[k] = ty * grid.tiles_x + tx;
                pair_gauss[k] = int32_t(i);
                ++k;
            }
    }
    // Stable counting sort by tile keeps Gaussian order inside each tile.
    std::vector<int64_t> start(n_tiles + 1, 0);
    for (int64_t k = 0; k < M; ++k) ++start[pair_tile[k] + 1];
    for (int t = 0; t < n_tiles; ++t) start[t + 1] += start[t];
    std::vector<int64_t> fill(start.begin(), start.end() - 1);
    for (int64_t k = 0; k < M; ++k) gauss_ids[fill[pair_tile[k]]++] = pair_gauss[k];
#pragma omp parallel for schedule(dynamic, 4) num_threads(num_threads)
    for (int t = 0; t < n_tiles; ++t) {
        tile_ranges[2 * t] = int32_t(start[t]);
        tile_ranges[2 * t + 1] = int32_t(start[t + 1]);
        std::stable_sort(gauss_ids + start[t], gauss_ids + start[t + 1],
                         [depths](int32_t a, int32_t b) { return sort_depth(depths[a]) < sort_depth(depths[b]); });
    }
}

#define RGS_INSTANTIATE(T)                                                                                  \
    template int64_t count_tile_pairs_cpu<T>(int64_t, const T*, const int32_t*, const T*, const T*, TileGrid,  \
                                             int64_t*, int);                                                    \
    template void bin_tile_pairs_cpu<T>(int64_t, const T*, const int32_t*, const T*, const T*, const T*,       \
                                        TileGrid, const int64_t*, int64_t, int32_t*, int32_t*, int);
RGS_INSTANTIATE(float)
RGS_INSTANTIATE(double)
#undef RGS_INSTANTIATE

}  // namespace rgs
