// CUDA launcher declarations (csrc/cuda). Same arguments and shapes as the CPU launchers in kernels.h, with the
// CUDA stream (a cudaStream_t, passed as void* so this header needs no CUDA include) instead of a thread count.
// Launchers that need scratch memory take a DeviceAllocator so the caller (torch's caching allocator in
// bindings.cpp) owns every allocation; all memory must stay valid until the launcher returns.
#pragma once
#include <cstddef>
#include <cstdint>

#include "rgs/ssim.h"
#include "rgs/supervision.h"
#include "rgs/types.h"

namespace rgs {

struct DeviceAllocator {
    void* (*alloc)(size_t bytes, void* ctx);
    void* ctx;
    void* operator()(size_t bytes) const { return alloc(bytes, ctx); }
};

constexpr int kMaxCudaChannels = 64;  // compositing on the GPU supports 1..64 channels

template <typename T>
void project_forward_cuda(int64_t N, const T* means, const T* quats, const T* scales, const T* opacities,
                          const Camera<T>& cam, T* means2d, T* depths, T* conics, int32_t* radii,
                          const FiniteCheck<T>& check, void* stream);

template <typename T>
void project_backward_cuda(int64_t N, const T* means, const T* quats, const T* scales, const Camera<T>& cam,
                           const int32_t* radii, const T* v_means2d, const T* v_depths, const T* v_conics,
                           T* v_means, T* v_quats, T* v_scales, void* stream);

// Counts each Gaussian's tile pairs into offsets [N] as an inclusive prefix sum and returns the total M
// (one device-to-host copy: the only synchronisation of a render). With conics and opacities (both, or both
// null), only the tiles of its rectangle that a Gaussian can reach (rgs::TileReach, the CPU's test).
// With device_count set, M is written there on the device instead and -1 returned: no host sync.
template <typename T>
int64_t count_tile_pairs_cuda(int64_t N, const T* means2d, const int32_t* radii,
                              const T* conics,     // [N, 3] or null
                              const T* opacities,  // [N] or null
                              TileGrid grid,
                              int64_t* offsets,  // [N] out, inclusive prefix sum
                              DeviceAllocator alloc, void* stream,
                              int64_t* device_count);  // [1] out, or null: return M (synchronises)

// Writes 64-bit (tile << 32 | float depth bits) keys, radix-sorts them with the Gaussian indices (stable, so ties
// keep index order), and fills the tile ranges. Without device_count, M is the exact pair count. With it
// (from count_tile_pairs_cuda), M is a capacity: pairs at offsets >= M are dropped, and gauss_ids past
// min(count, M) hold -1 (padding keys sort after every tile; no tile range covers them).
template <typename T>
void bin_tile_pairs_cuda(int64_t N, const T* means2d, const int32_t* radii, const T* conics, const T* opacities,
                         const T* depths, TileGrid grid,
                         const int64_t* offsets, int64_t M, const int64_t* device_count, int32_t* gauss_ids,
                         int32_t* tile_ranges, DeviceAllocator alloc, void* stream);

template <typename T>
void rasterize_forward_cuda(int64_t N, const OutputLayout<T>& layout, int width, int height, const T* means2d,
                            const T* conics,
                            const T* colors, const T* opacities, const int32_t* gauss_ids,
                            const int32_t* tile_ranges, T* image, T* transmittance, int32_t* last_ids,
                            void* stream);

// Gradient outputs must be zero-filled by the caller (the kernel accumulates with atomics).
template <typename T>
void rasterize_backward_cuda(int64_t N, const OutputLayout<T>& layout, int width, int height, const T* means2d,
                             const T* conics,
                             const T* colors, const T* opacities, const int32_t* gauss_ids,
                             const int32_t* tile_ranges, int64_t M, const T* transmittance, const int32_t* last_ids,
                             const T* v_image, const T* v_transmittance, T* v_means2d, T* v_conics, T* v_colors,
                             T* v_opacities, void* stream);

template <typename T>
void sh_forward_cuda(int64_t N, int degree, int K, int D, const T* dirs, const T* coeffs, T* colors, void* stream);

template <typename T>
void sh_backward_cuda(int64_t N, int degree, int K, int D, const T* dirs, const T* coeffs, const T* v_colors,
                      T* v_dirs, T* v_coeffs, void* stream);

// Same as gaussian_colors_cpu; the weights (device memory) are staged in shared memory per block when they fit.
template <typename T>
void gaussian_colors_cuda(int64_t N, int degree, int rest, const T* means, const T* sh_dc, const T* sh_rest,
                          const T* center, const IllumConfig* illum, double bound, const T* weights, T* colors,
                          void* stream);

// Same as illumination_forward_cpu / _backward_cpu; center and the packed weights in device memory (the weights
// staged in shared memory per block when they fit).
template <typename T>
void illumination_forward_cuda(int64_t N, const T* means, const T* center, const IllumConfig& cfg, double bound,
                               const T* weights, T* rgb, T* A, int64_t ld, void* stream);
template <typename T>
void illumination_backward_cuda(int64_t N, const T* means, const T* center, const IllumConfig& cfg, double bound,
                                const T* weights, const T* A, const T* rgb, const T* g_rgb, T* D, T* g_means, int64_t ld,
                                void* stream);

// Same as exposure_tone_cpu; gain in device memory (the frame graph computes it on the GPU).
template <typename T>
void exposure_tone_cuda(int64_t P, int C, int G, const T* image, const T* gain, double knee, T* out, void* stream);

// Same as screen_stats_cpu: one thread per Gaussian.
template <typename T>
void screen_stats_cuda(int64_t N, const T* grad2d, const int32_t* radii, double sx, double sy, float* grad_accum,
                       float* count, float* max_radius, void* stream);

// Same as ssim_forward_cpu / ssim_backward_cpu: one block per 16x16 tile of a plane, the tile and the window's
// halo staged in shared memory.
template <typename T>
void ssim_forward_cuda(int64_t planes, int H, int W, const T* x, const T* y, const SsimWindow<T>& win, T* s, T* d,
                       void* stream);

template <typename T>
void ssim_backward_cuda(int64_t planes, int H, int W, const T* grad, const T* x, const T* y, const T* d,
                        const SsimWindow<T>& win, T* dx, void* stream);

// Same as tone_curve_forward_cpu / tone_curve_backward_cpu: one thread per element; gain in device memory.
template <typename T>
void tone_curve_forward_cuda(int64_t n, const T* x, const T* gain, int64_t C, int64_t inner, double knee, int form_in,
                             int form_out, T* y, void* stream);
template <typename T>
void tone_curve_backward_cuda(int64_t n, const T* x, const T* gain, int64_t C, int64_t inner, double knee,
                              int form_in, int form_out, const T* grad_out, T* grad_x, T* grad_k, void* stream);

// Same as enhance_loss_cpu, in four launches over many blocks (every sum in a fixed order: deterministic); gain, E
// and the scratch in device memory, `scratch` enhance_scratch_cuda(H, W, pool) doubles.
int64_t enhance_scratch_cuda(int64_t H, int64_t W, int pool);
template <typename T>
void enhance_loss_cuda(const T* x, const T* s, int64_t H, int64_t W, int pool, const T* gain, double knee,
                       int form_in, int form_out, const T* E, bool exp_l1, bool scale_invariant, T* cells,
                       double* scratch, T* out, void* stream);

// Same as supervision_forward_cpu / supervision_backward_cpu: one thread per pixel; the forward's partials have
// supervision_rows_cuda(H·W) rows, one a block. Gains, noise and confidence in device memory.
int supervision_rows_cuda(int64_t pixels);
template <typename T>
void supervision_forward_cuda(const SupervisionArgs<T>& a, const T* image, const T* packed, T* x9, T* y9, T* partials,
                              void* stream);
template <typename T>
void supervision_backward_cuda(const SupervisionArgs<T>& a, const T* image, const T* packed, const T* g_x9,
                               const T* g_sums, T* grad_image, void* stream);

// Same as adam_step_cpu: kAdamBatch tensors a launch, one thread per element.
template <typename T>
struct AdamTensor;
template <typename T>
void adam_step_cuda(const AdamTensor<T>* tensors, int count, void* stream);

}  // namespace rgs
