// Launcher declarations of every kernel, one block per pipeline stage. Arguments are raw pointers to
// contiguous row-major arrays; shapes are given in the comments (N Gaussians, C channels, K SH bases,
// D SH channels, M tile/Gaussian intersections, H x W image). Only csrc/bindings.cpp knows torch.
// The CPU launchers are instantiated for float and double; the CUDA ones take a cudaStream_t as void*.
#pragma once
#include <cstdint>

#include "rgs/ssim.h"
#include "rgs/supervision.h"
#include "rgs/types.h"

namespace rgs {

// ---- projection ------------------------------------------------------------------------------
template <typename T>
void project_forward_cpu(int64_t N,
                         const T* means,      // [N, 3] world space
                         const T* quats,      // [N, 4] (w, x, y, z), any norm
                         const T* scales,     // [N, 3] standard deviations along the local axes
                         const T* opacities,  // [N] in [0, 1]
                         const Camera<T>& cam,
                         T* means2d,          // [N, 2] out, pixels
                         T* depths,           // [N] out, camera z
                         T* conics,           // [N, 3] out, inverse 2D covariance (A, B, C)
                         int32_t* radii,      // [N, 2] out, pixel half extents; 0 = culled
                         const FiniteCheck<T>& check,  // optional NaN/inf check of the render inputs
                         int num_threads);

template <typename T>
void project_backward_cpu(int64_t N, const T* means, const T* quats, const T* scales, const Camera<T>& cam,
                          const int32_t* radii,    // [N, 2] from the forward
                          const T* v_means2d,      // [N, 2]
                          const T* v_depths,       // [N]
                          const T* v_conics,       // [N, 3]
                          T* v_means,              // [N, 3] out
                          T* v_quats,              // [N, 4] out
                          T* v_scales,             // [N, 3] out
                          int num_threads);

// ---- tile binning ----------------------------------------------------------------------------
// Counts the (tile, Gaussian) pairs of every Gaussian; returns the total M. With conics and opacities (both, or
// both null), only the tiles of its rectangle that a Gaussian can reach (rgs::TileReach).
template <typename T>
int64_t count_tile_pairs_cpu(int64_t N,
                             const T* means2d,    // [N, 2]
                             const int32_t* radii,  // [N, 2]
                             const T* conics,     // [N, 3] or null
                             const T* opacities,  // [N] or null
                             TileGrid grid,
                             int64_t* offsets,  // [N + 1] out, exclusive prefix sum of the counts
                             int num_threads);

// Fills the pairs ordered by tile, then depth, then Gaussian index (conics/opacities as for the count).
// M below offsets[N] (a capacity) keeps only the pairs at offsets < M: the highest-index Gaussians' are dropped.
template <typename T>
void bin_tile_pairs_cpu(int64_t N, const T* means2d, const int32_t* radii,
                        const T* conics,     // [N, 3] or null
                        const T* opacities,  // [N] or null
                        const T* depths,     // [N]
                        TileGrid grid,
                        const int64_t* offsets,  // [N + 1] from count_tile_pairs_cpu
                        int64_t M,               // pairs to store: offsets[N], or less to drop the rest
                        int32_t* gauss_ids,      // [M] out, Gaussian index of each pair
                        int32_t* tile_ranges,    // [tiles, 2] out, [begin, end) of each tile's pairs
                        int num_threads);

// ---- compositing -----------------------------------------------------------------------------
template <typename T>
void rasterize_forward_cpu(int64_t N,
                           const OutputLayout<T>& layout,  // C channels, background, alpha (rgs/math.h)
                           int width, int height,
                           const T* means2d,           // [N, 2]
                           const T* conics,            // [N, 3]
                           const T* colors,            // [N, C]
                           const T* opacities,         // [N]
                           const int32_t* gauss_ids,   // [M]
                           const int32_t* tile_ranges, // [tiles, 2]
                           T* image,                   // [H, W, layout.stride()] out
                           T* transmittance,           // [H, W] out, T after the last contributor
                           int32_t* last_ids,          // [H, W] out, end of the contributing pairs
                           int num_threads);

template <typename T>
void rasterize_backward_cpu(int64_t N, const OutputLayout<T>& layout, int width, int height, const T* means2d,
                            const T* conics,
                            const T* colors, const T* opacities, const int32_t* gauss_ids,
                            const int32_t* tile_ranges, int64_t M,
                            const T* transmittance,     // [H, W] from the forward
                            const int32_t* last_ids,    // [H, W] from the forward
                            const T* v_image,           // [H, W, layout.stride()]
                            const T* v_transmittance,   // [H, W] (or nullptr)
                            T* v_means2d,               // [N, 2] out
                            T* v_conics,                // [N, 3] out
                            T* v_colors,                // [N, C] out
                            T* v_opacities,             // [N] out
                            int num_threads);

// ---- spherical harmonics ---------------------------------------------------------------------
template <typename T>
void sh_forward_cpu(int64_t N, int degree, int K, int D,
                    const T* dirs,    // [N, 3] view directions, any norm
                    const T* coeffs,  // [N, K, D]
                    T* colors,        // [N, D] out
                    int num_threads);

template <typename T>
void sh_backward_cpu(int64_t N, int degree, int K, int D, const T* dirs, const T* coeffs,
                     const T* v_colors,  // [N, D]
                     T* v_dirs,          // [N, 3] out
                     T* v_coeffs,        // [N, K, D] out (bases above the degree get 0)
                     int num_threads);

// ---- per-Gaussian colours of a trained scene (inference) --------------------------------------
// Reflectance max(SH(means - center) + 0.5, 0) and, with illum != nullptr, the illumination MLP's 3 channels
// (rgs/gaussian_colors.h; weights packed by pack_illum_weights in that layout).
template <typename T>
void gaussian_colors_cpu(int64_t N, int degree,
                         int rest,                  // SH bases in sh_rest (K - 1)
                         const T* means,            // [N, 3]
                         const T* sh_dc,            // [N, 3]
                         const T* sh_rest,          // [N, rest, 3] (unused when degree = 0)
                         const T* center,           // [3] camera centre (host memory)
                         const IllumConfig* illum,  // MLP shape, or nullptr for the reflectance only
                         double bound,              // positions are divided by this before encoding
                         const T* weights,          // [illum_layout(*illum).total] (or nullptr)
                         T* colors,                 // [N, 3 or 6] out
                         int num_threads);

// ---- the illumination field's MLP in training (rgs/illumination_train.h) --------------------------
// Forward: rgb [N, 3] and the saved activations A [a_width, N] of IlluminationField at the Gaussians' centres seen
// from `center`. Backward: the Linear layers' output gradients D [d_width, N] and the centres' gradient.
template <typename T>
void illumination_forward_cpu(int64_t N, const T* means, const T* center, const IllumConfig& cfg, double bound,
                              const T* weights, T* rgb, T* A, int64_t ld, int num_threads);
template <typename T>
void illumination_backward_cpu(int64_t N, const T* means, const T* center, const IllumConfig& cfg, double bound,
                               const T* weights, const T* A, const T* rgb, const T* g_rgb, T* D, T* g_means, int64_t ld,
                               int num_threads);

// ---- densification's screen-space statistics (rgs/screen_stats.h) --------------------------------
// Adds one view's statistics in place: grad_accum, count (where both radii > 0) and max_radius, all float32.
template <typename T>
void screen_stats_cpu(int64_t N, const T* grad2d, const int32_t* radii, double sx, double sy, float* grad_accum,
                      float* count, float* max_radius, int num_threads);

// ---- the enhancement's exposure tone (inference) ------------------------------------------------
// out = srgb(s(gain · lin(R̂ ∘ L̂))) per channel, s the highlight shoulder (rgs/tone.h).
template <typename T>
void exposure_tone_cpu(int64_t P,         // pixels
                       int C,             // channels per pixel of image (>= 6)
                       int G,             // gains: 1 (one) or 3 (per channel)
                       const T* image,    // [P, C]: R̂ in channels 0-2, L̂ in 3-5
                       const T* gain,     // [G]
                       double knee,       // the shoulder's knee in linear light (>= 1: none, the clip)
                       T* out,            // [P, 3] out
                       int num_threads);

// ---- the training loss's fused SSIM (rgs/ssim.h) ------------------------------------------------
// s = SSIM map of x against y per plane (zero padding, the window win); with d != nullptr also the partials
// dS/dmx, dS/dexx, dS/dexy that ssim_backward reads.
template <typename T>
void ssim_forward_cpu(int64_t planes,            // images x channels
                      int H, int W,
                      const T* x, const T* y,    // [planes, H, W] each
                      const SsimWindow<T>& win,
                      T* s,                      // [planes, H, W] out
                      T* d,                      // [3, planes, H, W] out, or nullptr
                      int num_threads);

// dx = dLoss/dx from grad = dLoss/dS and the forward's partials d (y gets no gradient: it is the target).
template <typename T>
void ssim_backward_cpu(int64_t planes, int H, int W,
                       const T* grad,            // [planes, H, W]
                       const T* x, const T* y,   // [planes, H, W] each
                       const T* d,               // [3, planes, H, W]
                       const SsimWindow<T>& win,
                       T* dx,                    // [planes, H, W] out
                       int num_threads);

// ---- training's tone curve (rgs/tone_curve.h) ---------------------------------------------------
// y[i] = srgb_o(s(gain[c] · lin_i(x[i]))), c = (i / inner) % C (C = 1: one gain); forms: rgs::CurveForm.
template <typename T>
void tone_curve_forward_cpu(int64_t n, const T* x, const T* gain, int64_t C, int64_t inner, double knee, int form_in,
                            int form_out, T* y, int num_threads);

// grad_x[i] = grad_out[i]·dy/dx (if grad_x is not null), grad_k[i] = grad_out[i]·dy/dk per element (if not null).
template <typename T>
void tone_curve_backward_cpu(int64_t n, const T* x, const T* gain, int64_t C, int64_t inner, double knee, int form_in,
                             int form_out, const T* grad_out, T* grad_x, T* grad_k, int num_threads);

// ---- L_enhance of the default configuration (rgs/enhance_loss.h) ---------------------------------------------
// x = R̂∘L̂ and s (the view L_spa compares with) [H, W, 3], gain [3], E [1]; H, W >= pool. cells: scratch
// [ceil(H/pool)·ceil(W/pool), kEnhanceCellValues]; out [kEnhanceOut]: (spa, exp, col), then d(term)/d(gain_c).
template <typename T>
void enhance_loss_cpu(const T* x, const T* s, int64_t H, int64_t W, int pool, const T* gain, double knee, int form_in,
                      int form_out, const T* E, bool exp_l1, bool scale_invariant, T* cells, T* out, int num_threads);

// ---- the training loss's supervision, L_TV and depth prior (rgs/supervision.h) -------------------------------
// x9, y9: [9, H, W] out (the SSIM's stacks); partials: [rows, kSums] out, row r the sums over pixels
// [r·HW/rows, (r+1)·HW/rows) (the caller adds the rows).
template <typename T>
void supervision_forward_cpu(const SupervisionArgs<T>& a, const T* image, const T* packed, T* x9, T* y9, T* partials,
                             int rows, int num_threads);

// grad_image [H, W, ci] out, from g_x9 [9, H, W] (or null) and g_sums [kSums].
template <typename T>
void supervision_backward_cpu(const SupervisionArgs<T>& a, const T* image, const T* packed, const T* g_x9,
                              const T* g_sums, T* grad_image, int num_threads);

// ---- Adam's step (rgs/adam.h) -------------------------------------------------------------------------
template <typename T>
struct AdamTensor;
template <typename T>
void adam_step_cpu(const AdamTensor<T>* tensors, int count, int num_threads);

}  // namespace rgs
