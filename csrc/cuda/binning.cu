// Tile binning on the GPU: count pairs per Gaussian, prefix-sum them, write 64-bit (tile | depth) keys, radix sort
// only the bits in use, and mark each tile's range in the sorted list. With conics and opacities, a Gaussian pairs
// only with the tiles of its rectangle that it can reach (TileReach: the CPU's test, bit for bit).
// Sync-free mode (a capacity C and a device count): the pair count M never leaves the device; pairs at offsets
// >= C are dropped, and the slots past min(M, C) get padding keys that sort after every real tile.
#include <cub/cub.cuh>

#include "common.cuh"
#include "rgs/kernels_cuda.h"
#include "rgs/math.h"

namespace rgs {

// One warp per Gaussian: its lanes take the tiles of its rectangle in row-major order, 32 at a time. One thread per
// Gaussian looped over the whole rectangle alone: early in training a few large Gaussians cover thousands of tiles
// each at 12 MP (4.0 + 4.3 ms of a 37 ms step in these two kernels at step 300), while their neighbours' threads
// idle. The pairs come out in the same order as that loop's, so the keys are the same, bit for bit.
constexpr int kBinThreads = 256;
constexpr int kBinWarps = kBinThreads / 32;

template <typename T>
__global__ void __launch_bounds__(kBinThreads)
count_pairs_kernel(int64_t N, const T* __restrict__ means2d,    // [N, 2]
                   const int32_t* __restrict__ radii,          // [N, 2]
                   const T* __restrict__ conics,               // [N, 3] or null
                   const T* __restrict__ opacities,            // [N] or null
                   TileGrid grid, int64_t* __restrict__ counts) {  // [N]
    const int64_t i = int64_t(blockIdx.x) * kBinWarps + (threadIdx.x >> 5);
    const int lane = threadIdx.x & 31;
    if (i >= N) return;  // the whole warp: i is the same on every lane
    const TileRect r = gaussian_tile_rect(means2d + 2 * i, radii + 2 * i, grid);
    const int64_t area = r.area();
    if (conics == nullptr || area == 0) {
        if (lane == 0) counts[i] = area;
        return;
    }
    const TileReach reach = TileReach::make(means2d + 2 * i, conics + 3 * i, opacities[i]);
    const int w = r.x1 - r.x0;
    int64_t n = 0;
    for (int64_t t = lane; t < area; t += 32) n += reach.hits(r.x0 + int(t % w), r.y0 + int(t / w)) ? 1 : 0;
    n = warp_sum(n);
    if (lane == 0) counts[i] = n;
}

template <typename T>
__global__ void __launch_bounds__(kBinThreads)
write_keys_kernel(int64_t N, const T* __restrict__ means2d, const int32_t* __restrict__ radii,
                  const T* __restrict__ conics,             // [N, 3] or null
                  const T* __restrict__ opacities,          // [N] or null
                  const T* __restrict__ depths,             // [N]
                  TileGrid grid, const int64_t* __restrict__ offsets,  // [N] inclusive
                  int64_t slots,                            // keys/ids length
                  uint64_t* __restrict__ keys,              // [slots]
                  int32_t* __restrict__ ids) {              // [slots]
    const int64_t i = int64_t(blockIdx.x) * kBinWarps + (threadIdx.x >> 5);
    const int lane = threadIdx.x & 31;
    if (i >= N) return;  // the whole warp
    const TileRect r = gaussian_tile_rect(means2d + 2 * i, radii + 2 * i, grid);
    const int64_t area = r.area();
    if (area == 0) return;
    int64_t k = i == 0 ? 0 : offsets[i - 1];
    if (k >= slots) return;  // past the capacity: this Gaussian's pairs are dropped
    // Depths are >= near > 0, so the float's bit pattern orders like the value.
    const uint64_t depth_bits = __float_as_uint(sort_depth(depths[i]));  // > 0: bits order like values
    const bool cull = conics != nullptr;
    const TileReach reach = cull ? TileReach::make(means2d + 2 * i, conics + 3 * i, opacities[i]) : TileReach{};
    const int w = r.x1 - r.x0;
    const unsigned below = (1u << lane) - 1u;  // the lanes before this one
    for (int64_t base = 0; base < area && k < slots; base += 32) {  // k is the same on every lane
        const int64_t t = base + lane;
        const int tx = r.x0 + int(t % w), ty = r.y0 + int(t / w);
        const bool hit = t < area && (!cull || reach.hits(tx, ty));  // the tiles count_pairs_kernel counted
        const unsigned hits = __ballot_sync(0xffffffffu, hit);
        const int64_t at = k + __popc(hits & below);
        if (hit && at < slots) {  // past the capacity: the rest is dropped
            keys[at] = (uint64_t(ty * grid.tiles_x + tx) << 32) | depth_bits;
            ids[at] = int32_t(i);
        }
        k += __popc(hits);
    }
}

// Slots [min(M, C), C) of a sync-free binning: a key whose tile field is above every real tile (it sorts last and
// tile_ranges_kernel skips it) and the id -1. M is read on the device.
__global__ void pad_keys_kernel(int64_t C, const int64_t* __restrict__ count, uint64_t pad_key,
                                uint64_t* __restrict__ keys, int32_t* __restrict__ ids) {
    const int64_t k = int64_t(blockIdx.x) * blockDim.x + threadIdx.x;
    if (k >= C || k < *count) return;
    keys[k] = pad_key;
    ids[k] = -1;
}

__global__ void tile_ranges_kernel(int64_t M, int32_t n_tiles, const uint64_t* __restrict__ keys,  // [M] sorted
                                   int32_t* __restrict__ ranges) {  // [tiles, 2], zeroed
    const int64_t k = int64_t(blockIdx.x) * blockDim.x + threadIdx.x;
    if (k >= M) return;
    const int64_t tile64 = int64_t(keys[k] >> 32);
    if (tile64 >= n_tiles) return;  // padding of a sync-free binning
    const int32_t tile = int32_t(tile64);
    if (k == 0 || int32_t(keys[k - 1] >> 32) != tile) ranges[2 * tile] = int32_t(k);
    if (k == M - 1 || int32_t(keys[k + 1] >> 32) != tile) ranges[2 * tile + 1] = int32_t(k + 1);
}

template <typename T>
int64_t count_tile_pairs_cuda(int64_t N, const T* means2d, const int32_t* radii, const T* conics, const T* opacities,
                              TileGrid grid, int64_t* offsets, DeviceAllocator alloc, void* stream_,
                              int64_t* device_count) {
    cudaStream_t stream = (cudaStream_t)stream_;
    if (N == 0) {
        if (device_count != nullptr)
            check_cuda(cudaMemsetAsync(device_count, 0, sizeof(int64_t), stream), "zero count");
        return device_count != nullptr ? -1 : 0;
    }
    int64_t* counts = static_cast<int64_t*>(alloc(sizeof(int64_t) * N));
    count_pairs_kernel<T><<<num_blocks(N, kBinWarps), kBinThreads, 0, stream>>>(N, means2d, radii, conics, opacities, grid,
                                                                  counts);
    RGS_CHECK_LAUNCH("count_pairs");
    size_t temp_bytes = 0;
    check_cuda(cub::DeviceScan::InclusiveSum(nullptr, temp_bytes, counts, offsets, N, stream), "scan size");
    void* temp = alloc(temp_bytes);
    check_cuda(cub::DeviceScan::InclusiveSum(temp, temp_bytes, counts, offsets, N, stream), "scan");
    if (device_count != nullptr) {  // sync-free: M stays on the device
        check_cuda(cudaMemcpyAsync(device_count, offsets + N - 1, sizeof(int64_t), cudaMemcpyDeviceToDevice, stream),
                   "copy count");
        return -1;
    }
    int64_t M = 0;
    check_cuda(cudaMemcpyAsync(&M, offsets + N - 1, sizeof(int64_t), cudaMemcpyDeviceToHost, stream), "copy M");
    check_cuda(cudaStreamSynchronize(stream), "sync M");
    return M;
}

template <typename T>
void bin_tile_pairs_cuda(int64_t N, const T* means2d, const int32_t* radii, const T* conics, const T* opacities,
                         const T* depths, TileGrid grid, const int64_t* offsets, int64_t M,
                         const int64_t* device_count, int32_t* gauss_ids, int32_t* tile_ranges,
                         DeviceAllocator alloc, void* stream_) {
    cudaStream_t stream = (cudaStream_t)stream_;
    check_cuda(cudaMemsetAsync(tile_ranges, 0, sizeof(int32_t) * 2 * grid.count(), stream), "zero ranges");
    if (M == 0) return;  // M: the exact count, or the capacity (device_count set)
    const bool padded = device_count != nullptr;
    uint64_t* keys = static_cast<uint64_t*>(alloc(sizeof(uint64_t) * M));
    uint64_t* keys_sorted = static_cast<uint64_t*>(alloc(sizeof(uint64_t) * M));
    int32_t* ids = static_cast<int32_t*>(alloc(sizeof(int32_t) * M));
    if (N > 0) {
        write_keys_kernel<T><<<num_blocks(N, kBinWarps), kBinThreads, 0, stream>>>(N, means2d, radii, conics, opacities, depths,
                                                                     grid, offsets, M, keys, ids);
        RGS_CHECK_LAUNCH("write_keys");
    }
    // Padding needs a tile id above every real one: (1 << tile_bits) > tiles. The exact path keeps >=.
    int tile_bits = 1;
    while ((1ll << tile_bits) < grid.count() + (padded ? 1 : 0)) ++tile_bits;
    if (padded) {
        const uint64_t pad_key = (uint64_t(1) << (32 + tile_bits)) - 1;  // all ones in the sorted bits: sorts last
        pad_keys_kernel<<<num_blocks(M, 256), 256, 0, stream>>>(M, device_count, pad_key, keys, ids);
        RGS_CHECK_LAUNCH("pad_keys");
    }
    size_t temp_bytes = 0;
    check_cuda(cub::DeviceRadixSort::SortPairs(nullptr, temp_bytes, keys, keys_sorted, ids, gauss_ids, M, 0,
                                               32 + tile_bits, stream), "sort size");
    void* temp = alloc(temp_bytes);
    check_cuda(cub::DeviceRadixSort::SortPairs(temp, temp_bytes, keys, keys_sorted, ids, gauss_ids, M, 0,
                                               32 + tile_bits, stream), "sort");
    tile_ranges_kernel<<<num_blocks(M, 256), 256, 0, stream>>>(M, grid.count(), keys_sorted, tile_ranges);
    RGS_CHECK_LAUNCH("tile_ranges");
}

#define RGS_INSTANTIATE(T)                                                                                      \
    template int64_t count_tile_pairs_cuda<T>(int64_t, const T*, const int32_t*, const T*, const T*, TileGrid,   \
                                              int64_t*, DeviceAllocator, void*, int64_t*);                       \
    template void bin_tile_pairs_cuda<T>(int64_t, const T*, const int32_t*, const T*, const T*, const T*,        \
                                         TileGrid, const int64_t*, int64_t, const int64_t*, int32_t*, int32_t*,  \
                                         DeviceAllocator, void*);
RGS_INSTANTIATE(float)
RGS_INSTANTIATE(double)
#undef RGS_INSTANTIATE

}  // namespace rgs
