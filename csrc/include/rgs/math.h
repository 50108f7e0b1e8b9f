// The per-Gaussian and per-pixel math of Gaussian splatting, written once and called by both the
// OpenMP (csrc/cpu) and CUDA (csrc/cuda) schedulers. Every forward function has its vector-Jacobian
// product (`*_vjp`) next to it. Equation numbers refer to Kerbl et al., "3D Gaussian Splatting for
// Real-Time Radiance Field Rendering" (SIGGRAPH 2023) and Zwicker et al., "EWA Splatting" (2002).
#pragma once
#include <cmath>
#include <cstring>

#include "rgs/types.h"

namespace rgs {

// ---------------------------------------------------------------------------------------------
// Finiteness by the exponent bits, not std::isfinite: fast-math flags (nvcc --use_fast_math, or a host
// -ffast-math) let a compiler assume there is no NaN/inf and fold isfinite to true.
// ---------------------------------------------------------------------------------------------
RGS_HD bool finite_bits(float x) {
    uint32_t u;
    memcpy(&u, &x, sizeof(u));
    return (u & 0x7f800000u) != 0x7f800000u;
}
RGS_HD bool finite_bits(double x) {
    uint64_t u;
    memcpy(&u, &x, sizeof(u));
    return (u & 0x7ff0000000000000ull) != 0x7ff0000000000000ull;
}
template <typename T>
RGS_HD bool all_finite(const T* values, int64_t n) {
    bool ok = true;
    for (int64_t k = 0; k < n; ++k) ok &= finite_bits(values[k]);
    return ok;
}

// Are Gaussian i's render inputs finite (FiniteCheck: mean, rotation, scale, opacity, its colour row, and for
// i == 0 the background)? Called by the projection of both schedulers when the check is on.
template <typename T>
RGS_HD bool gaussian_inputs_finite(int64_t i, const T* mean, const T* quat, const T* scale, T opacity,
                                   const FiniteCheck<T>& check) {
    bool ok = all_finite(mean, 3) & all_finite(quat, 4) & all_finite(scale, 3) & finite_bits(opacity);
    if (check.colors != nullptr) ok &= all_finite(check.colors + i * check.channels, check.channels);
    if (i == 0 && check.background != nullptr) ok &= all_finite(check.background, check.channels);
    return ok;
}

// ---------------------------------------------------------------------------------------------
// Small fixed-size linear algebra (row-major).
// ---------------------------------------------------------------------------------------------
template <typename T>
struct Vec2 { T x, y; };
template <typename T>
struct Vec3 { T x, y, z; };
template <typename T>
struct Mat2 { T a, b, c, d; };  // [[a, b], [c, d]]
template <typename T>
struct Mat3 { T m[3][3]; };

template <typename T>
RGS_HD Mat3<T> mat3_zero() {
    Mat3<T> r;
    for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j) r.m[i][j] = T(0);
    return r;
}

template <typename T>
RGS_HD Mat3<T> matmul(const Mat3<T>& A, const Mat3<T>& B) {
    Mat3<T> r;
    for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j)
            r.m[i][j] = A.m[i][0] * B.m[0][j] + A.m[i][1] * B.m[1][j] + A.m[i][2] * B.m[2][j];
    return r;
}

template <typename T>
RGS_HD Mat3<T> transpose(const Mat3<T>& A) {
    Mat3<T> r;
    for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j) r.m[i][j] = A.m[j][i];
    return r;
}

template <typename T>
RGS_HD Vec3<T> matvec(const Mat3<T>& A, const Vec3<T>& v) {
    return {A.m[0][0] * v.x + A.m[0][1] * v.y + A.m[0][2] * v.z,
            A.m[1][0] * v.x + A.m[1][1] * v.y + A.m[1][2] * v.z,
            A.m[2][0] * v.x + A.m[2][1] * v.y + A.m[2][2] * v.z};
}

template <typename T>
RGS_HD Vec3<T> matTvec(const Mat3<T>& A, const Vec3<T>& v) {  // A^T v
    return {A.m[0][0] * v.x + A.m[1][0] * v.y + A.m[2][0] * v.z,
            A.m[0][1] * v.x + A.m[1][1] * v.y + A.m[2][1] * v.z,
            A.m[0][2] * v.x + A.m[1][2] * v.y + A.m[2][2] * v.z};
}

// Rotation part and translation of a row-major 4x4 world-to-camera matrix.
template <typename T>
RGS_HD Mat3<T> viewmat_rotation(const T* vm) {
    Mat3<T> R;
    for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j) R.m[i][j] = vm[4 * i + j];
    return R;
}

template <typename T>
RGS_HD Vec3<T> world_to_camera(const T* vm, const Vec3<T>& p) {
    return {vm[0] * p.x + vm[1] * p.y + vm[2] * p.z + vm[3],
            vm[4] * p.x + vm[5] * p.y + vm[6] * p.z + vm[7],
            vm[8] * p.x + vm[9] * p.y + vm[10] * p.z + vm[11]};
}

// ---------------------------------------------------------------------------------------------
// Quaternion (w, x, y, z), not necessarily normalised -> rotation matrix. A zero quaternion maps to
// the identity (q / max(|q|, eps) = 0 gives R = I) and receives no gradient.
// ---------------------------------------------------------------------------------------------
template <typename T>
RGS_HD T quat_norm(const T* q) {
    return sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]);
}

template <typename T>
RGS_HD Mat3<T> quat_to_rotmat(const T* q) {
    const T n = quat_norm(q);
    const T inv = n > T(1e-12) ? T(1) / n : T(0);
    const T w = q[0] * inv, x = q[1] * inv, y = q[2] * inv, z = q[3] * inv;
    Mat3<T> R;
    R.m[0][0] = T(1) - T(2) * (y * y + z * z);
    R.m[0][1] = T(2) * (x * y - w * z);
    R.m[0][2] = T(2) * (x * z + w * y);
    R.m[1][0] = T(2) * (x * y + w * z);
    R.m[1][1] = T(1) - T(2) * (x * x + z * z);
    R.m[1][2] = T(2) * (y * z - w * x);
    R.m[2][0] = T(2) * (x * z - w * y);
    R.m[2][1] = T(2) * (y * z + w * x);
    R.m[2][2] = T(1) - T(2) * (x * x + y * y);
    return R;
}

// v_q (4) from v_R = dL/dR, through the normalisation q / |q|.
template <typename T>
RGS_HD void quat_to_rotmat_vjp(const T* q, const Mat3<T>& G, T* v_q) {
    const T n = quat_norm(q);
    if (!(n > T(1e-12))) {
        v_q[0] = v_q[1] = v_q[2] = v_q[3] = T(0);
        return;
    }
    const T inv = T(1) / n;
    const T w = q[0] * inv, x = q[1] * inv, y = q[2] * inv, z = q[3] * inv;
    const auto& g = G.m;
    // dL/d(normalised q): contract G with dR/dw, dR/dx, dR/dy, dR/dz.
    const T vw = T(2) * (-z * g[0][1] + y * g[0][2] + z * g[1][0] - x * g[1][2] - y * g[2][0] + x * g[2][1]);
    const T vx = T(2) * (y * g[0][1] + z * g[0][2] + y * g[1][0] - T(2) * x * g[1][1] - w * g[1][2] +
                         z * g[2][0] + w * g[2][1] - T(2) * x * g[2][2]);
    const T vy = T(2) * (-T(2) * y * g[0][0] + x * g[0][1] + w * g[0][2] + x * g[1][0] + z * g[1][2] -
                         w * g[2][0] + z * g[2][1] - T(2) * y * g[2][2]);
    const T vz = T(2) * (-T(2) * z * g[0][0] - w * g[0][1] + x * g[0][2] + w * g[1][0] - T(2) * z * g[1][1] +
                         y * g[1][2] + x * g[2][0] + y * g[2][1]);
    // Through the normalisation: (I - q̂ q̂ᵀ) v / |q|.
    const T dot = w * vw + x * vx + y * vy + z * vz;
    v_q[0] = (vw - w * dot) * inv;
    v_q[1] = (vx - x * dot) * inv;
    v_q[2] = (vy - y * dot) * inv;
    v_q[3] = (vz - z * dot) * inv;
}

// ---------------------------------------------------------------------------------------------
// 3D covariance Σ = R S Sᵀ Rᵀ (3DGS eq. 6), S = diag(scale).
// ---------------------------------------------------------------------------------------------
template <typename T>
RGS_HD Mat3<T> covariance_3d(const Mat3<T>& R, const T* s) {
    Mat3<T> M;  // M = R S
    for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j) M.m[i][j] = R.m[i][j] * s[j];
    return matmul(M, transpose(M));
}

// From v_Σ (any 3x3) to v_R and v_s (3).
template <typename T>
RGS_HD void covariance_3d_vjp(const Mat3<T>& R, const T* s, const Mat3<T>& v_sigma, Mat3<T>& v_R, T* v_s) {
    Mat3<T> M;
    for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j) M.m[i][j] = R.m[i][j] * s[j];
    // Σ = M Mᵀ  =>  v_M = (v_Σ + v_Σᵀ) M
    Mat3<T> sym;
    for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j) sym.m[i][j] = v_sigma.m[i][j] + v_sigma.m[j][i];
    const Mat3<T> v_M = matmul(sym, M);
    for (int j = 0; j < 3; ++j) {
        v_s[j] = T(0);
        for (int i = 0; i < 3; ++i) {
            v_R.m[i][j] = v_M.m[i][j] * s[j];
            v_s[j] += v_M.m[i][j] * R.m[i][j];
        }
    }
}

// ---------------------------------------------------------------------------------------------
// EWA projection (3DGS eq. 5, EWA eq. 31): Σ' = J W Σ Wᵀ Jᵀ + 0.3 I, with J the Jacobian of the
// perspective map at the camera-space mean. x/z and y/z are clamped to a guard band 1.3x the image
// half-extent (measured from the principal point) so Gaussians far off-screen do not explode.
// ---------------------------------------------------------------------------------------------
template <typename T>
struct Jacobian {
    T j00, j02, j11, j12;   // J = [[j00, 0, j02], [0, j11, j12]]
    bool clamp_x, clamp_y;  // x/z or y/z hit the guard band (their gradient is then zero)
};

template <typename T>
RGS_HD Jacobian<T> perspective_jacobian(const Camera<T>& cam, const Vec3<T>& p) {
    const T lim_xn = T(kGuardBand) * cam.cx / cam.fx;
    const T lim_xp = T(kGuardBand) * (T(cam.width) - cam.cx) / cam.fx;
    const T lim_yn = T(kGuardBand) * cam.cy / cam.fy;
    const T lim_yp = T(kGuardBand) * (T(cam.height) - cam.cy) / cam.fy;
    const T rz = T(1) / p.z;
    T u = p.x * rz, v = p.y * rz;
    Jacobian<T> J;
    J.clamp_x = u < -lim_xn || u > lim_xp;
    J.clamp_y = v < -lim_yn || v > lim_yp;
    u = u < -lim_xn ? -lim_xn : (u > lim_xp ? lim_xp : u);
    v = v < -lim_yn ? -lim_yn : (v > lim_yp ? lim_yp : v);
    J.j00 = cam.fx * rz;
    J.j02 = -cam.fx * u * rz;
    J.j11 = cam.fy * rz;
    J.j12 = -cam.fy * v * rz;
    return J;
}

// Σ2 = J Σc Jᵀ (2x2, before the low-pass), returned as its three distinct entries (xx, xy, yy).
template <typename T>
RGS_HD Vec3<T> ewa_covariance_2d(const Jacobian<T>& J, const Mat3<T>& S) {
    // rows of J: r0 = (j00, 0, j02), r1 = (0, j11, j12)
    const T a0 = J.j00 * S.m[0][0] + J.j02 * S.m[2][0];
    const T a1 = J.j00 * S.m[0][1] + J.j02 * S.m[2][1];
    const T a2 = J.j00 * S.m[0][2] + J.j02 * S.m[2][2];
    const T b1 = J.j11 * S.m[1][1] + J.j12 * S.m[2][1];
    const T b2 = J.j11 * S.m[1][2] + J.j12 * S.m[2][2];
    return {a0 * J.j00 + a2 * J.j02, a1 * J.j11 + a2 * J.j12, b1 * J.j11 + b2 * J.j12};
}

// From v_Σ2 (given as the symmetric 2x2 [[gxx, gxy], [gxy, gyy]]) to v_Σc (3x3) and the camera-space
// mean's gradient through J (added into v_p).
template <typename T>
RGS_HD void ewa_covariance_2d_vjp(const Camera<T>& cam, const Vec3<T>& p, const Jacobian<T>& J, const Mat3<T>& S,
                                  T gxx, T gxy, T gyy, Mat3<T>& v_S, Vec3<T>& v_p) {
    // J as a full 2x3 matrix.
    const T Jm[2][3] = {{J.j00, T(0), J.j02}, {T(0), J.j11, J.j12}};
    const T G[2][2] = {{gxx, gxy}, {gxy, gyy}};
    // v_Σc = Jᵀ G J
    for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j) {
            T acc = T(0);
            for (int a = 0; a < 2; ++a)
                for (int b = 0; b < 2; ++b) acc += Jm[a][i] * G[a][b] * Jm[b][j];
            v_S.m[i][j] = acc;
        }
    // v_J = G J Σcᵀ + Gᵀ J Σc = 2 G J Σc (G and Σc symmetric)
    T JS[2][3];
    for (int a = 0; a < 2; ++a)
        for (int j = 0; j < 3; ++j) JS[a][j] = Jm[a][0] * S.m[0][j] + Jm[a][1] * S.m[1][j] + Jm[a][2] * S.m[2][j];
    T vJ[2][3];
    for (int a = 0; a < 2; ++a)
        for (int j = 0; j < 3; ++j) vJ[a][j] = T(2) * (G[a][0] * JS[0][j] + G[a][1] * JS[1][j]);
    const T rz = T(1) / p.z, rz2 = rz * rz;
    // j00 = fx/z ; j02 = -fx*u/z with u = x/z (or a clamped constant)
    v_p.z += -cam.fx * rz2 * vJ[0][0] - cam.fy * rz2 * vJ[1][1];
    if (!J.clamp_x) {
        v_p.x += -cam.fx * rz2 * vJ[0][2];
        v_p.z += T(2) * cam.fx * p.x * rz2 * rz * vJ[0][2];
    } else {
        v_p.z += -J.j02 * rz * vJ[0][2];  // d(-fx*u/z)/dz = fx*u/z^2 = -j02/z
    }
    if (!J.clamp_y) {
        v_p.y += -cam.fy * rz2 * vJ[1][2];
        v_p.z += T(2) * cam.fy * p.y * rz2 * rz * vJ[1][2];
    } else {
        v_p.z += -J.j12 * rz * vJ[1][2];
    }
}

// Conic = inverse of the low-passed 2D covariance, stored as (A, B, C) = (inv_xx, inv_xy, inv_yy).
template <typename T>
RGS_HD bool conic_from_cov2d(const Vec3<T>& cov, Vec3<T>& conic) {
    const T det = cov.x * cov.z - cov.y * cov.y;
    if (!(det > T(0))) return false;
    const T inv = T(1) / det;
    conic = {cov.z * inv, -cov.y * inv, cov.x * inv};
    return true;
}

// From v_conic (vA, vB, vC) to v_cov2d as a symmetric matrix (gxx, gxy, gyy):
// d(Σ⁻¹) = -Σ⁻¹ dΣ Σ⁻¹, with B counted once (so it contributes vB/2 to both off-diagonals).
template <typename T>
RGS_HD Vec3<T> conic_from_cov2d_vjp(const Vec3<T>& conic, const Vec3<T>& v_conic) {
    const T A = conic.x, B = conic.y, C = conic.z;
    const T ga = v_conic.x, gb = T(0.5) * v_conic.y, gc = v_conic.z;
    // -[[A,B],[B,C]] [[ga,gb],[gb,gc]] [[A,B],[B,C]]
    const T m00 = A * ga + B * gb, m01 = A * gb + B * gc;
    const T m10 = B * ga + C * gb, m11 = B * gb + C * gc;
    return {-(m00 * A + m01 * B), -(m00 * B + m01 * C), -(m10 * B + m11 * C)};
}

// Screen-space half extents (pixels) of the region where alpha >= 1/255: the ellipse
// dᵀ Σ'⁻¹ d <= 2 ln(255 o) has an axis-aligned bounding box of half widths k sqrt(Σ'_xx), k sqrt(Σ'_yy).
template <typename T>
RGS_HD bool opacity_aware_extent(const Vec3<T>& cov, T opacity, T& ext_x, T& ext_y) {
    // α = min(0.99, o G) >= 1/255  <=>  o G >= 1/255, so the 0.99 clamp does not enter here.
    const T level = T(255) * opacity;
    if (!(level > T(1))) return false;
    const T k = sqrt(T(2) * log(level));
    ext_x = k * sqrt(cov.x);
    ext_y = k * sqrt(cov.z);
    return true;
}

// Tiles touched by the pixel-centre box [mx - ex, mx + ex] x [my - ey, my + ey].
template <typename T>
RGS_HD TileRect tile_rect(T mx, T my, T ex, T ey, const TileGrid& grid) {
    // Pixel i has its centre at i + 0.5, so the box covers pixels floor(m - e - 0.5) .. floor(m + e - 0.5);
    // one pixel of margin on each side keeps rounding from dropping an edge pixel.
    const T ts = T(kTileSize);
    T fx0 = floor((mx - ex - T(1.5)) / ts), fx1 = floor((mx + ex + T(0.5)) / ts) + T(1);
    T fy0 = floor((my - ey - T(1.5)) / ts), fy1 = floor((my + ey + T(0.5)) / ts) + T(1);
    // Clamp in floating point first: huge Gaussians must not overflow int.
    const T gx = T(grid.tiles_x), gy = T(grid.tiles_y);
    fx0 = fx0 < T(0) ? T(0) : (fx0 > gx ? gx : fx0);
    fx1 = fx1 < T(0) ? T(0) : (fx1 > gx ? gx : fx1);
    fy0 = fy0 < T(0) ? T(0) : (fy0 > gy ? gy : fy0);
    fy1 = fy1 < T(0) ? T(0) : (fy1 > gy ? gy : fy1);
    TileRect r{int(fx0), int(fy0), int(fx1), int(fy1)};
    if (r.x1 < r.x0) r.x1 = r.x0;
    if (r.y1 < r.y0) r.y1 = r.y0;
    return r;
}

// Tile rectangle of a projected Gaussian from its integer radii (empty when culled). Binning uses this on both
// schedulers, so the CPU and CUDA paths produce the same (tile, Gaussian) pairs.
template <typename T>
RGS_HD TileRect gaussian_tile_rect(const T* mean2d, const int32_t* radius, const TileGrid& grid) {
    if (radius[0] <= 0 || radius[1] <= 0) return TileRect{0, 0, 0, 0};
    return tile_rect(mean2d[0], mean2d[1], T(radius[0]), T(radius[1]), grid);
}

// ---------------------------------------------------------------------------------------------
// Tile culling of the binning: a Gaussian pairs only with the tiles of its rectangle where it can reach
// alpha >= 1/255 at some pixel centre (the rectangle of a rotated, elongated ellipse holds many tiles it never
// touches; about 30 % of the pairs on the benchmark scenes). A dropped pair has alpha 0 at every pixel of its
// tile, so images and gradients do not change, only the work.
// ---------------------------------------------------------------------------------------------

// Double operations rounded once each, never fused: nvcc contracts a * b + c into an FMA (--fmad, on by default)
// and the host compiler does not (setup.py builds with -ffp-contract=off), so written with these the culling
// test gives the same bits, hence the same tiles, on the CPU and the GPU.
RGS_HD double mul_rn(double a, double b) {
#if defined(__CUDA_ARCH__)
    return __dmul_rn(a, b);
#else
    return a * b;
#endif
}
RGS_HD double add_rn(double a, double b) {
#if defined(__CUDA_ARCH__)
    return __dadd_rn(a, b);
#else
    return a + b;
#endif
}
RGS_HD double div_rn(double a, double b) {
#if defined(__CUDA_ARCH__)
    return __ddiv_rn(a, b);
#else
    return a / b;
#endif
}

// ln(x) for finite x > 0 from rounded +, *, / alone, so the CPU and the GPU agree to the bit (their library logs
// may differ in the last place). x = m 2^e with m in [√½, √2), ln m = 2 atanh(s), s = (m - 1) / (m + 1),
// |s| < 0.172: the series to s^23 leaves a relative error below 1e-15, far inside the margin it is used with.
RGS_HD double log_rn(double x) {
    int e = 0;
    double m = frexp(x, &e);  // x = m 2^e, m in [0.5, 1)
    if (m < 0.70710678118654752440) {
        m = mul_rn(m, 2.0);  // exact
        --e;
    }
    const double s = div_rn(add_rn(m, -1.0), add_rn(m, 1.0));
    const double s2 = mul_rn(s, s);
    // Horner in s² of Σ s^(2k) / (2k + 1), k = 0..11; decimal literals parse to the same doubles everywhere.
    double p = 0.043478260869565216;
    p = add_rn(mul_rn(p, s2), 0.047619047619047616);
    p = add_rn(mul_rn(p, s2), 0.05263157894736842);
    p = add_rn(mul_rn(p, s2), 0.058823529411764705);
    p = add_rn(mul_rn(p, s2), 0.06666666666666667);
    p = add_rn(mul_rn(p, s2), 0.07692307692307693);
    p = add_rn(mul_rn(p, s2), 0.09090909090909091);
    p = add_rn(mul_rn(p, s2), 0.1111111111111111);
    p = add_rn(mul_rn(p, s2), 0.14285714285714285);
    p = add_rn(mul_rn(p, s2), 0.2);
    p = add_rn(mul_rn(p, s2), 0.3333333333333333);
    p = add_rn(mul_rn(p, s2), 1.0);
    return add_rn(mul_rn(double(e), 0.69314718055994530942), mul_rn(mul_rn(2.0, s), p));
}

// Whether a Gaussian can reach alpha >= 1/255 at a pixel centre of tile (tx, ty): per Gaussian make() (one log,
// two divisions), then a cheap hits() per tile of its rectangle. Conservative: in double precision, the minimum
// over the box of the tile's pixel centres of
//   Q(d) = ½ (1 - 2ε)(A dx² + C dy²) + B dx dy   (ε = 1e-5)
// must exceed ln(255 o) + 2e-3 for the tile to be dropped. Q lies below σ(d) by ε (A dx² + C dy²), far more than
// the float32 rounding of σ (and of d = pixel - mean) at any pixel; 2e-3 is the 1e-3 margin of sigma_cutoff
// doubled, which also covers the approximate float exp/log of the GPU build's fast math. So a dropped pair has
// σ > sigma_cutoff(o), i.e. o exp(-σ) < 1/255 (alpha_from_sigma's skip), at every pixel of its tile. The 0.99
// clamp of alpha does not enter: alpha >= 1/255 <=> o exp(-σ) >= 1/255. The minimum of a convex quadratic over
// a box is at the mean when the mean lies inside, else on an edge, where it is at the clamped 1D minimiser.
// Anything not clearly positive definite or not finite keeps every tile.
struct TileReach {
    double mx, my, A, B, C, rA, rC, cut;
    bool all;  // keep every tile

    template <typename T>
    RGS_HD static TileReach make(const T* mean2d, const T* conic, T opacity) {
        TileReach t;
        t.mx = double(mean2d[0]);
        t.my = double(mean2d[1]);
        const double shrink = 1.0 - 2e-5;
        t.A = mul_rn(double(conic[0]), shrink);
        t.B = double(conic[1]);
        t.C = mul_rn(double(conic[2]), shrink);
        const double level = mul_rn(255.0, double(opacity));
        // level <= 1e300 also rejects inf and NaN; the determinant is of the shrunk (still convex) quadratic.
        t.all = !(level > 1.0 && level <= 1e300) || !(t.A > 0.0) || !(t.C > 0.0) ||
                !(add_rn(mul_rn(t.A, t.C), -mul_rn(t.B, t.B)) > 0.0) || !(t.A <= 1e300) || !(t.C <= 1e300) ||
                !(add_rn(t.mx, -t.mx) == 0.0) || !(add_rn(t.my, -t.my) == 0.0);  // finite mean
        t.rA = t.all ? 0.0 : div_rn(1.0, t.A);
        t.rC = t.all ? 0.0 : div_rn(1.0, t.C);
        t.cut = t.all ? 0.0 : add_rn(log_rn(level), 2e-3);
        return t;
    }

    // Q at offset (dx, dy), in the operation order the reference (retinexgs/render/reference.py) mirrors.
    RGS_HD double q(double dx, double dy) const {
        return add_rn(mul_rn(0.5, add_rn(mul_rn(mul_rn(A, dx), dx), mul_rn(mul_rn(C, dy), dy))),
                      mul_rn(mul_rn(B, dx), dy));
    }

    RGS_HD bool hits(int tx, int ty) const {
        if (all) return true;
        // Pixel centres of the tile (exact in double); beyond the image edge the box only grows: conservative.
        const double x0 = double(tx * kTileSize) + 0.5, x1 = x0 + double(kTileSize - 1);
        const double y0 = double(ty * kTileSize) + 0.5, y1 = y0 + double(kTileSize - 1);
        if (mx >= x0 && mx <= x1 && my >= y0 && my <= y1) return true;
        // Edges x = x0, x1: the minimiser over dy is -B dx / C, clamped to the box; then edges y = y0, y1.
        double lo = add_rn(y0, -my), hi = add_rn(y1, -my);
        double dx = add_rn(x0, -mx);
        double dy = mul_rn(mul_rn(-B, dx), rC);
        dy = dy < lo ? lo : (dy > hi ? hi : dy);
        double best = q(dx, dy);
        dx = add_rn(x1, -mx);
        dy = mul_rn(mul_rn(-B, dx), rC);
        dy = dy < lo ? lo : (dy > hi ? hi : dy);
        double s = q(dx, dy);
        best = s < best ? s : best;
        lo = add_rn(x0, -mx);
        hi = add_rn(x1, -mx);
        dy = add_rn(y0, -my);
        dx = mul_rn(mul_rn(-B, dy), rA);
        dx = dx < lo ? lo : (dx > hi ? hi : dx);
        s = q(dx, dy);
        best = s < best ? s : best;
        dy = add_rn(y1, -my);
        dx = mul_rn(mul_rn(-B, dy), rA);
        dx = dx < lo ? lo : (dx > hi ? hi : dx);
        s = q(dx, dy);
        best = s < best ? s : best;
        return !(best > cut);  // NaN keeps the pair
    }
};

// Pairs of one Gaussian: the tiles of its rectangle that it can reach (all of them when conic is null).
template <typename T>
RGS_HD int64_t gaussian_tile_count(const TileRect& r, const T* mean2d, const T* conic, const T* opacity) {
    if (conic == nullptr || r.area() == 0) return r.area();
    const TileReach reach = TileReach::make(mean2d, conic, *opacity);
    int64_t n = 0;
    for (int ty = r.y0; ty < r.y1; ++ty)
        for (int tx = r.x0; tx < r.x1; ++tx) n += reach.hits(tx, ty) ? 1 : 0;
    return n;
}

// ---------------------------------------------------------------------------------------------
// One Gaussian's projection: world-space mean/quat/scale/opacity -> 2D mean, depth, conic, extents.
// Returns false (and the caller writes zero radii) when the Gaussian is culled.
// ---------------------------------------------------------------------------------------------
template <typename T>
struct Projected {
    Vec2<T> mean2d;
    T depth;
    Vec3<T> conic;
    int radius_x, radius_y;
};

template <typename T>
RGS_HD bool project_gaussian(const T* mean, const T* quat, const T* scale, T opacity, const Camera<T>& cam,
                             Projected<T>& out) {
    const Vec3<T> p = world_to_camera(cam.viewmat, Vec3<T>{mean[0], mean[1], mean[2]});
    if (!(p.z >= cam.near_plane && p.z <= cam.far_plane)) return false;  // also rejects NaN
    const Mat3<T> W = viewmat_rotation(cam.viewmat);
    const Mat3<T> sigma = covariance_3d(quat_to_rotmat(quat), scale);
    const Mat3<T> sigma_cam = matmul(matmul(W, sigma), transpose(W));
    const Jacobian<T> J = perspective_jacobian(cam, p);
    Vec3<T> cov = ewa_covariance_2d(J, sigma_cam);
    cov.x += T(kLowPass);
    cov.z += T(kLowPass);
    if (!conic_from_cov2d(cov, out.conic)) return false;
    T ex, ey;
    if (!opacity_aware_extent(cov, opacity, ex, ey)) return false;
    const T rz = T(1) / p.z;
    out.mean2d = {cam.fx * p.x * rz + cam.cx, cam.fy * p.y * rz + cam.cy};
    out.depth = p.z;
    // Entirely off-screen?
    if (out.mean2d.x + ex <= T(0) || out.mean2d.x - ex >= T(cam.width) || out.mean2d.y + ey <= T(0) ||
        out.mean2d.y - ey >= T(cam.height))
        return false;
    if (!(ex < T(1e7) && ey < T(1e7))) return false;  // non-finite or absurd
    out.radius_x = int(ceil(ex));
    out.radius_y = int(ceil(ey));
    return out.radius_x > 0 && out.radius_y > 0;
}

// Gradients of one visible Gaussian's projection: (v_mean2d, v_depth, v_conic) -> (v_mean, v_quat, v_scale).
template <typename T>
RGS_HD void project_gaussian_vjp(const T* mean, const T* quat, const T* scale, const Camera<T>& cam,
                                 const T* v_mean2d, T v_depth, const T* v_conic, T* v_mean, T* v_quat, T* v_scale) {
    const Vec3<T> p = world_to_camera(cam.viewmat, Vec3<T>{mean[0], mean[1], mean[2]});
    const Mat3<T> W = viewmat_rotation(cam.viewmat);
    const Mat3<T> R = quat_to_rotmat(quat);
    const Mat3<T> sigma = covariance_3d(R, scale);
    const Mat3<T> sigma_cam = matmul(matmul(W, sigma), transpose(W));
    const Jacobian<T> J = perspective_jacobian(cam, p);
    Vec3<T> cov = ewa_covariance_2d(J, sigma_cam);
    cov.x += T(kLowPass);
    cov.z += T(kLowPass);
    Vec3<T> conic;
    conic_from_cov2d(cov, conic);

    const Vec3<T> g = conic_from_cov2d_vjp(conic, Vec3<T>{v_conic[0], v_conic[1], v_conic[2]});
    Vec3<T> v_p{T(0), T(0), v_depth};
    const T rz = T(1) / p.z;
    v_p.x += cam.fx * rz * v_mean2d[0];
    v_p.y += cam.fy * rz * v_mean2d[1];
    v_p.z += -(cam.fx * p.x * v_mean2d[0] + cam.fy * p.y * v_mean2d[1]) * rz * rz;
    Mat3<T> v_sigma_cam;
    ewa_covariance_2d_vjp(cam, p, J, sigma_cam, g.x, g.y, g.z, v_sigma_cam, v_p);
    // Σc = W Σ Wᵀ  =>  v_Σ = Wᵀ v_Σc W
    const Mat3<T> v_sigma = matmul(matmul(transpose(W), v_sigma_cam), W);
    Mat3<T> v_R;
    covariance_3d_vjp(R, scale, v_sigma, v_R, v_scale);
    quat_to_rotmat_vjp(quat, v_R, v_quat);
    // p = W mean + t  =>  v_mean = Wᵀ v_p
    const Vec3<T> vm = matTvec(W, v_p);
    v_mean[0] = vm.x;
    v_mean[1] = vm.y;
    v_mean[2] = vm.z;
}

// ---------------------------------------------------------------------------------------------
// Per-pixel alpha (3DGS eq. 2 with the 2D Gaussian G' of eq. 5): α = min(0.99, o exp(-σ)),
// σ = ½ dᵀ Σ'⁻¹ d, d = pixel centre - mean2d. Returns 0 when the contribution is skipped (α < 1/255).
// ---------------------------------------------------------------------------------------------
template <typename T>
struct PixelAlpha {
    T alpha;    // 0 when skipped
    T gauss;    // exp(-σ)
    T dx, dy;   // pixel centre - mean2d
    bool clamped;
};

// σ = ½ dᵀ Σ'⁻¹ d for d = (dx, dy).
template <typename T>
RGS_HD T pixel_sigma(const Vec3<T>& conic, T dx, T dy) {
    return T(0.5) * (conic.x * dx * dx + conic.z * dy * dy) + conic.y * dx * dy;
}

// A σ above which α < 1/255 for sure (the margin absorbs rounding), so exp() can be skipped there;
// below it the exact test in alpha_from_sigma decides.
template <typename T>
RGS_HD T sigma_cutoff(T opacity) {
    return log(T(255) * opacity) + T(1e-3);
}

template <typename T>
RGS_HD PixelAlpha<T> alpha_from_sigma(T sigma, T opacity, T dx, T dy) {
    PixelAlpha<T> r;
    r.dx = dx;
    r.dy = dy;
    r.gauss = exp(-sigma);
    T a = opacity * r.gauss;
    r.clamped = a > T(kAlphaMax);
    if (r.clamped) a = T(kAlphaMax);
    r.alpha = (sigma < T(0) || !(a >= T(kAlphaMin))) ? T(0) : a;
    return r;
}

template <typename T>
RGS_HD PixelAlpha<T> pixel_alpha(const Vec3<T>& conic, T mx, T my, T opacity, T px, T py) {
    const T dx = px - mx, dy = py - my;
    return alpha_from_sigma(pixel_sigma(conic, dx, dy), opacity, dx, dy);
}

// Pixels x in [x_lo, x_hi] of the row with offset dy where σ can be <= cut: σ is a quadratic in dx, so the
// span is the interval between its roots (one pixel of margin; the exact test still runs per pixel).
template <typename T>
RGS_HD bool row_span(const Vec3<T>& conic, T cut, T mx, T dy, int x_lo, int x_hi, int& xa, int& xb) {
    // ½A dx² + B dy dx + (½C dy² - cut) <= 0
    const T A = conic.x, b = conic.y * dy;
    const T disc = b * b - A * (conic.z * dy * dy - T(2) * cut);
    if (!(disc >= T(0)) || !(A > T(0))) return false;
    const T root = sqrt(disc);
    const T lo = floor(mx - T(0.5) + (-b - root) / A) - T(1);
    const T hi = ceil(mx - T(0.5) + (-b + root) / A) + T(1);
    xa = lo < T(x_lo) ? x_lo : int(lo);
    xb = hi > T(x_hi) ? x_hi : int(hi);
    return xa <= xb;
}

// v_alpha -> (v_mean2d, v_conic, v_opacity), accumulated.
template <typename T>
RGS_HD void pixel_alpha_vjp(const PixelAlpha<T>& pa, const Vec3<T>& conic, T opacity, T v_alpha, T* v_mean2d,
                            T* v_conic, T& v_opacity) {
    if (pa.clamped) return;  // α = 0.99 is constant there
    v_opacity += pa.gauss * v_alpha;
    const T v_sigma = -opacity * pa.gauss * v_alpha;
    v_conic[0] += T(0.5) * pa.dx * pa.dx * v_sigma;
    v_conic[1] += pa.dx * pa.dy * v_sigma;
    v_conic[2] += T(0.5) * pa.dy * pa.dy * v_sigma;
    // dσ/dmean = -dσ/dd
    v_mean2d[0] -= (conic.x * pa.dx + conic.y * pa.dy) * v_sigma;
    v_mean2d[1] -= (conic.y * pa.dx + conic.z * pa.dy) * v_sigma;
}

// ---------------------------------------------------------------------------------------------
// The compositing's output at a pixel (3DGS eq. 3 closed by what is behind the Gaussians): with A_c = Σ w_i c_i
// and T the transmittance left,
//   out[c] = A_c + T·bg[c]   (c < n_bg: the channels with a background),   out[c] = A_c   (n_bg <= c < C),
//   out[C] = 1 - T           (only with alpha: the accumulated opacity as one more channel).
// Composited in the kernel, the background and alpha cost no full-size pass of their own, and a loss that wants
// [channels, alpha] in one tensor gets it without a concatenation (issue 65). Its gradient reaches the compositing
// through A_c (one for one) and through T:
//   dL/dT = v_T + Σ_{c<n_bg} v_out[c]·bg[c] - v_out[C]   (the last term only with alpha).
// ---------------------------------------------------------------------------------------------
// (OutputLayout, the layout these read, is in rgs/types.h.)
template <typename T>
RGS_HD T output_value(const OutputLayout<T>& o, int c, T acc, T Tr) {
    return c < o.n_bg ? acc + Tr * o.bg[c] : acc;
}

// dL/dT at a pixel from its output gradient v_out [stride] and the gradient v_T given for T itself.
template <typename T>
RGS_HD T transmittance_grad(const OutputLayout<T>& o, const T* v_out, T v_T) {
    for (int c = 0; c < o.n_bg; ++c) v_T += v_out[c] * o.bg[c];
    return o.alpha ? v_T - v_out[o.C] : v_T;
}

// Axis-aligned pixel box (inclusive, clamped to [lo, hi)) where a Gaussian can reach alpha >= 1/255,
// recovered from its conic and opacity. Used to skip pixels inside a tile; one pixel of margin.
template <typename T>
RGS_HD bool pixel_box(const Vec3<T>& conic, T mx, T my, T opacity, int x_lo, int y_lo, int x_hi, int y_hi,
                      int& x0, int& y0, int& x1, int& y1) {
    const T det = conic.x * conic.z - conic.y * conic.y;
    if (!(det > T(0))) return false;
    const Vec3<T> cov{conic.z / det, -conic.y / det, conic.x / det};
    T ex, ey;
    if (!opacity_aware_extent(cov, opacity, ex, ey)) return false;
    // Pixel i is inside when |i + 0.5 - m| <= e.
    T fx0 = floor(mx - ex - T(0.5)) - T(1), fx1 = ceil(mx + ex - T(0.5)) + T(1);
    T fy0 = floor(my - ey - T(0.5)) - T(1), fy1 = ceil(my + ey - T(0.5)) + T(1);
    fx0 = fx0 < T(x_lo) ? T(x_lo) : fx0;
    fy0 = fy0 < T(y_lo) ? T(y_lo) : fy0;
    fx1 = fx1 > T(x_hi - 1) ? T(x_hi - 1) : fx1;
    fy1 = fy1 > T(y_hi - 1) ? T(y_hi - 1) : fy1;
    if (fx0 > fx1 || fy0 > fy1) return false;
    x0 = int(fx0);
    x1 = int(fx1);
    y0 = int(fy0);
    y1 = int(fy1);
    return true;
}

// ---------------------------------------------------------------------------------------------
// Real spherical harmonics up to degree 3 (the basis 3DGS uses), on the normalised direction.
// ---------------------------------------------------------------------------------------------
namespace sh {
// Scalars rather than arrays: namespace-scope constexpr scalars are usable in CUDA device code.
constexpr double C0 = 0.28209479177387814;
constexpr double C1 = 0.4886025119029199;
constexpr double C2_0 = 1.0925484305920792, C2_1 = -1.0925484305920792, C2_2 = 0.31539156525252005,
                 C2_3 = -1.0925484305920792, C2_4 = 0.5462742152960396;
constexpr double C3_0 = -0.5900435899266435, C3_1 = 2.890611442640554, C3_2 = -0.4570457994644658,
                 C3_3 = 0.3731763325901154, C3_4 = -0.4570457994644658, C3_5 = 1.445305721320277,
                 C3_6 = -0.5900435899266435;
}  // namespace sh

RGS_HD int sh_num_bases(int degree) { return (degree + 1) * (degree + 1); }

// Basis values B[0 .. (degree+1)^2) at the unit direction (x, y, z).
template <typename T>
RGS_HD void sh_basis(int degree, T x, T y, T z, T* B) {
    B[0] = T(sh::C0);
    if (degree < 1) return;
    B[1] = -T(sh::C1) * y;
    B[2] = T(sh::C1) * z;
    B[3] = -T(sh::C1) * x;
    if (degree < 2) return;
    const T xx = x * x, yy = y * y, zz = z * z;
    B[4] = T(sh::C2_0) * x * y;
    B[5] = T(sh::C2_1) * y * z;
    B[6] = T(sh::C2_2) * (T(2) * zz - xx - yy);
    B[7] = T(sh::C2_3) * x * z;
    B[8] = T(sh::C2_4) * (xx - yy);
    if (degree < 3) return;
    B[9] = T(sh::C3_0) * y * (T(3) * xx - yy);
    B[10] = T(sh::C3_1) * x * y * z;
    B[11] = T(sh::C3_2) * y * (T(4) * zz - xx - yy);
    B[12] = T(sh::C3_3) * z * (T(2) * zz - T(3) * xx - T(3) * yy);
    B[13] = T(sh::C3_4) * x * (T(4) * zz - xx - yy);
    B[14] = T(sh::C3_5) * z * (xx - yy);
    B[15] = T(sh::C3_6) * x * (xx - T(3) * yy);
}

// v_dir (at the unit direction) from v_B, the gradient with respect to each basis value.
template <typename T>
RGS_HD void sh_basis_vjp(int degree, T x, T y, T z, const T* vB, T& vx, T& vy, T& vz) {
    vx = vy = vz = T(0);
    if (degree < 1) return;
    vx += -T(sh::C1) * vB[3];
    vy += -T(sh::C1) * vB[1];
    vz += T(sh::C1) * vB[2];
    if (degree < 2) return;
    const T xx = x * x, yy = y * y, zz = z * z;
    vx += T(sh::C2_0) * y * vB[4] - T(2 * sh::C2_2) * x * vB[6] + T(sh::C2_3) * z * vB[7] +
          T(2 * sh::C2_4) * x * vB[8];
    vy += T(sh::C2_0) * x * vB[4] + T(sh::C2_1) * z * vB[5] - T(2 * sh::C2_2) * y * vB[6] -
          T(2 * sh::C2_4) * y * vB[8];
    vz += T(sh::C2_1) * y * vB[5] + T(4 * sh::C2_2) * z * vB[6] + T(sh::C2_3) * x * vB[7];
    if (degree < 3) return;
    vx += T(6 * sh::C3_0) * x * y * vB[9] + T(sh::C3_1) * y * z * vB[10] - T(2 * sh::C3_2) * x * y * vB[11] -
          T(6 * sh::C3_3) * x * z * vB[12] + T(sh::C3_4) * (T(4) * zz - T(3) * xx - yy) * vB[13] +
          T(2 * sh::C3_5) * x * z * vB[14] + T(sh::C3_6) * (T(3) * xx - T(3) * yy) * vB[15];
    vy += T(sh::C3_0) * (T(3) * xx - T(3) * yy) * vB[9] + T(sh::C3_1) * x * z * vB[10] +
          T(sh::C3_2) * (T(4) * zz - xx - T(3) * yy) * vB[11] - T(6 * sh::C3_3) * y * z * vB[12] -
          T(2 * sh::C3_4) * x * y * vB[13] - T(2 * sh::C3_5) * y * z * vB[14] - T(6 * sh::C3_6) * x * y * vB[15];
    vz += T(sh::C3_1) * x * y * vB[10] + T(8 * sh::C3_2) * y * z * vB[11] +
          T(sh::C3_3) * (T(6) * zz - T(3) * xx - T(3) * yy) * vB[12] + T(8 * sh::C3_4) * x * z * vB[13] +
          T(sh::C3_5) * (xx - yy) * vB[14];
}

// Unit direction of d, and the map of a gradient at the unit direction back to d.
template <typename T>
RGS_HD T normalize3(const T* d, T& x, T& y, T& z) {
    const T n = sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2]);
    const T inv = n > T(1e-12) ? T(1) / n : T(0);
    x = d[0] * inv;
    y = d[1] * inv;
    z = d[2] * inv;
    return n;
}

template <typename T>
RGS_HD void normalize3_vjp(T n, T x, T y, T z, T vx, T vy, T vz, T* v_d) {
    if (!(n > T(1e-12))) {
        v_d[0] = v_d[1] = v_d[2] = T(0);
        return;
    }
    const T dot = x * vx + y * vy + z * vz;
    v_d[0] = (vx - x * dot) / n;
    v_d[1] = (vy - y * dot) / n;
    v_d[2] = (vz - z * dot) / n;
}

// One Gaussian's colours from its SH coefficients (3DGS Eq. (1)'s view-dependent colour, per channel):
// colors[d] = sum_k B_k(dir / |dir|) c[k*D + d] over the degree's bases. Shared by the CPU loop and both CUDA
// kernels (the tiled one passes its shared-memory row as c). Unrolled over kMaxShCoeffs so that B stays in
// registers on the GPU.
template <typename T>
RGS_HD void sh_colors_one(int degree, int D, const T* dir, const T* c, T* colors) {
    T x, y, z, B[kMaxShCoeffs] = {};  // zeros past the degree's bases (read by no one; quiets gcc)
    normalize3(dir, x, y, z);
    sh_basis(degree, x, y, z, B);
    const int nb = sh_num_bases(degree);
    for (int d = 0; d < D; ++d) {
        T acc = T(0);
RGS_UNROLL
        for (int k = 0; k < kMaxShCoeffs; ++k)
            if (k < nb) acc += B[k] * c[k * D + d];
        colors[d] = acc;
    }
}

// Its vector-Jacobian product: v_c[k*D + d] = B_k v_colors[d] (0 past the degree's bases, k < K) and v_dir.
// v_c may be c itself (the tiled CUDA kernel writes the gradient over the staged coefficients): each element is
// read before it is written.
template <typename T>
RGS_HD void sh_colors_one_vjp(int degree, int K, int D, const T* dir, const T* c, const T* v_colors, T* v_dir,
                              T* v_c) {
    T x, y, z, B[kMaxShCoeffs] = {}, vB[kMaxShCoeffs];
    const T n = normalize3(dir, x, y, z);
    sh_basis(degree, x, y, z, B);
    const int nb = sh_num_bases(degree);
RGS_UNROLL
    for (int k = 0; k < kMaxShCoeffs; ++k) {
        vB[k] = T(0);
        if (k < K) {
            for (int d = 0; d < D; ++d) {
                const T v = v_colors[d];
                if (k < nb) vB[k] += c[k * D + d] * v;
                v_c[k * D + d] = k < nb ? B[k] * v : T(0);
            }
        }
    }
    for (int k = kMaxShCoeffs; k < K; ++k)  // rows past any basis (K > 16): no gradient
        for (int d = 0; d < D; ++d) v_c[k * D + d] = T(0);
    T vx, vy, vz;
    sh_basis_vjp(degree, x, y, z, vB, vx, vy, vz);
    normalize3_vjp(n, x, y, z, vx, vy, vz, v_dir);
}

}  // namespace rgs
