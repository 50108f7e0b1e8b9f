// Plain types and constants shared by the CPU and CUDA schedulers. No torch, no STL containers.
#pragma once
#include <cstdint>

#if defined(__CUDACC__)
#define RGS_HD __host__ __device__ __forceinline__
#else
#define RGS_HD inline
#endif

// RGS_UNROLL: unroll on the GPU (small arrays indexed by the loop stay in registers); nothing on the host.
#if defined(__CUDA_ARCH__)
#define RGS_UNROLL _Pragma("unroll")
#else
#define RGS_UNROLL
#endif

namespace rgs {

constexpr int kTileSize = 16;               // tiles are kTileSize x kTileSize pixels
constexpr double kAlphaMax = 0.99;          // 3DGS: alpha = min(0.99, o * G)
constexpr double kAlphaMin = 1.0 / 255.0;   // contributions below this are skipped
constexpr double kTransmittanceMin = 1e-4;  // a pixel stops once T would fall below this
constexpr double kLowPass = 0.3;            // EWA anti-aliasing: +0.3 on the 2D covariance diagonal
constexpr double kGuardBand = 1.3;          // J clamps x/z, y/z to 1.3x the image's half-extent
constexpr int kMaxShCoeffs = 16;            // SH degree <= 3

// Pinhole camera. viewmat is world-to-camera, row-major 4x4, OpenCV axes (x right, y down, z forward).
// Pixel (i, j) has its centre at (i + 0.5, j + 0.5) in the coordinates that (cx, cy) use.
template <typename T>
struct Camera {
    T viewmat[16];
    T fx, fy, cx, cy;
    int width, height;
    T near_plane, far_plane;
};

// The render call's finiteness check, folded into the projection so that it costs no pass of its own: the
// projection already reads each Gaussian's mean, rotation, scale and opacity, and checks its colour row [C] (and,
// once, the background [C]) beside them. Any NaN or infinity sets *flag to 1 (caller zeroes it; every writer
// writes the same value, so the race is benign). flag == nullptr: no check.
template <typename T>
struct FiniteCheck {
    const T* colors = nullptr;      // [N, C] or nullptr
    int64_t channels = 0;           // C
    const T* background = nullptr;  // [C] or nullptr
    int32_t* flag = nullptr;        // [1] out, 0 = all finite
};

// The depth that orders a tile's Gaussians: float32 precision for every scalar type, ties broken by Gaussian
// index. The GPU sorts 64-bit (tile << 32 | float bits) keys, so the CPU (and the reference) must order by the
// same float32 value, or float64 renders of Gaussians at depths equal to float32 precision would composite
// in different orders on the two devices.
template <typename T>
RGS_HD float sort_depth(T depth) { return static_cast<float>(depth); }

// Tile grid of an image.
struct TileGrid {
    int tiles_x, tiles_y;
    RGS_HD int count() const { return tiles_x * tiles_y; }
};

RGS_HD TileGrid make_tile_grid(int width, int height) {
    return TileGrid{(width + kTileSize - 1) / kTileSize, (height + kTileSize - 1) / kTileSize};
}

// Half-open rectangle of tiles [x0, x1) x [y0, y1).
struct TileRect {
    int x0, y0, x1, y1;
    RGS_HD int area() const { return (x1 - x0) * (y1 - y0); }
};

// What the compositing writes per pixel (rgs/math.h, output_value): C channels, the first n_bg closed by a background,
// and with alpha the accumulated opacity 1 - T as one more.
template <typename T>
struct OutputLayout {
    int C;                 // composited channels (the colours' count)
    int n_bg = 0;          // leading channels with a background, 0..C
    const T* bg = nullptr; // [n_bg] (device memory on the GPU)
    bool alpha = false;    // out[C] = 1 - T
    RGS_HD int stride() const { return C + (alpha ? 1 : 0); }
};

// Shape of the illumination field's MLP (IlluminationField's constructor arguments; rgs/gaussian_colors.h).
struct IllumConfig {
    int pos_freqs, dir_freqs, hidden, depth, dir_hidden;
};

}  // namespace rgs
