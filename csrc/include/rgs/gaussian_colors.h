// Per-Gaussian colours of a trained RetinexGS scene for one camera, forward only (inference): the SH reflectance
// colour max(SH(dir) + 0.5, 0) (3 channels) and, optionally, the illumination field's MLP (3 more channels:
// sigmoid(head(trunk(PE(x / bound)), PE(unit dir)))), written once per Gaussian as the [N, C] buffer the
// rasterizer takes. Mirrors GaussianModel.colors and IlluminationField.forward (retinexgs/model) operation by
// operation, so float64 agrees with torch to rounding and float32 to a few ulps of the encodings.
//
// The MLP weights are one flat buffer (see IllumLayout), each Linear stored transposed ([in, out], so one input
// feeds all outputs from contiguous memory) followed by its bias, every block starting at a multiple of 4
// elements (16-byte aligned vector loads on the GPU). H and DH are compile-time hidden / head widths (0: runtime
// widths up to kMaxIllumWidth, activations in local memory); with them set the activations live in registers.
#pragma once
#include <cmath>
#include <cstdint>
#include <type_traits>

#include "rgs/math.h"
#include "rgs/types.h"

namespace rgs {

// RGS_UNROLL (rgs/types.h) keeps the activations in registers on the GPU. RGS_SIMD, on the innermost loops over a
// layer's outputs only: unrolled on the GPU, vectorised on the CPU (gcc would otherwise keep them scalar: acc may
// alias w).
#if defined(__CUDA_ARCH__)
#define RGS_SIMD _Pragma("unroll")
#elif defined(_OPENMP)
#define RGS_SIMD _Pragma("omp simd")
#else
#define RGS_SIMD
#endif

constexpr int kMaxIllumWidth = 128;   // widest layer of the runtime-width path (local memory: 2 x this per thread)
constexpr int kMaxIllumFreqs = 16;    // most octaves of either encoding
constexpr double kPi = 3.14159265358979323846;

RGS_HD int encoded_width(int n_freqs) { return 3 * (2 * n_freqs + 1); }
RGS_HD int64_t pad4(int64_t n) { return (n + 3) / 4 * 4; }

// Offsets (in elements) of each layer's transposed weight and bias in the flat buffer. Layer l < depth is the
// trunk's l-th Linear; then the head's first (in: hidden + PE(d)) and last (in: dir_hidden, out: 3) Linear.
struct IllumLayout {
    int64_t trunk0_w, trunk0_b;      // [enc_x, hidden], [hidden]
    int64_t trunk_w, trunk_b;        // first of depth-1 blocks [hidden, hidden] + [hidden], each trunk_stride long
    int64_t trunk_stride;
    int64_t head0_w, head0_b;        // [hidden + enc_d, dir_hidden], [dir_hidden]
    int64_t head1_w, head1_b;        // [dir_hidden, 3], [3]
    int64_t total;                   // elements of the whole buffer
};

// Host only: the launchers compute it once and pass it by value.
inline IllumLayout illum_layout(const IllumConfig& c) {
    IllumLayout L;
    const int64_t h = c.hidden, dh = c.dir_hidden;
    L.trunk0_w = 0;
    L.trunk0_b = pad4(encoded_width(c.pos_freqs) * h);
    L.trunk_stride = pad4(h * h) + pad4(h);
    L.trunk_w = L.trunk0_b + pad4(h);
    L.trunk_b = L.trunk_w + pad4(h * h);
    L.head0_w = L.trunk_w + L.trunk_stride * (c.depth - 1);
    L.head0_b = L.head0_w + pad4((h + encoded_width(c.dir_freqs)) * dh);
    L.head1_w = L.head0_b + pad4(dh);
    L.head1_b = L.head1_w + pad4(dh * 3);
    L.total = L.head1_b + pad4(3);
    return L;
}

// sin and cos of a positional-encoding argument. torch evaluates sin(float32(x * float32(2^k pi))) accurately;
// nvcc's --use_fast_math turns sinf into __sinf, whose error grows with |a| (arguments reach ~2^9 pi), so on the
// GPU the argument is first reduced to [-pi, pi] in double precision.
RGS_HD void pe_sincos(float a, float& s, float& c) {
#if defined(__CUDA_ARCH__)
    const double k = rint(double(a) * (0.5 / kPi));
    const float r = float(fma(-k, 2.0 * kPi, double(a)));
    __sincosf(r, &s, &c);
#else
    s = std::sin(a);
    c = std::cos(a);
#endif
}

RGS_HD void pe_sincos(double a, double& s, double& c) {
#if defined(__CUDA_ARCH__)
    sincos(a, &s, &c);
#else
    s = std::sin(a);
    c = std::cos(a);
#endif
}

template <typename T>
RGS_HD T sigmoid_of(T z) { return T(1) / (T(1) + exp(-z)); }

template <typename T>
RGS_HD T relu(T v) { return v > T(0) ? v : T(0); }

#if defined(__CUDA_ARCH__)
// A 16-byte aligned float4 of weights. From shared memory through explicit PTX: nvcc otherwise splits the vector
// loads of the unrolled layers into 32-bit ones, one load per FMA, which bounds the kernel.
__device__ __forceinline__ float4 load_float4(const float* p) {
    float4 r;
    if (__isShared(p)) {
        const unsigned addr = static_cast<unsigned>(__cvta_generic_to_shared(p));
        asm("ld.shared.v4.f32 {%0, %1, %2, %3}, [%4];" : "=f"(r.x), "=f"(r.y), "=f"(r.z), "=f"(r.w) : "r"(addr));
    } else {
        r = *reinterpret_cast<const float4*>(p);
    }
    return r;
}
#endif

// acc[o] += w[o] * v for o < n; w starts at a multiple of 4 elements (vector loads on the GPU).
template <typename T, int N>
RGS_HD void axpy_row(int n, const T* __restrict__ w, T v, T* acc) {
    if constexpr (N > 0 && N % 4 == 0) {
#if defined(__CUDA_ARCH__)
        // Rows of a width divisible by 4 start 16-byte aligned (IllumLayout): 128-bit loads, so the broadcast
        // shared-memory reads keep up with the FMAs (one 32-bit load per FMA would bound the kernel).
        if constexpr (sizeof(T) == 4) {
            RGS_UNROLL
            for (int q = 0; q < N / 4; ++q) {
                const float4 x = load_float4(w + 4 * q);
                acc[4 * q] += x.x * v;
                acc[4 * q + 1] += x.y * v;
                acc[4 * q + 2] += x.z * v;
                acc[4 * q + 3] += x.w * v;
            }
        } else {
            const double2* w2 = reinterpret_cast<const double2*>(w);
            RGS_UNROLL
            for (int q = 0; q < N / 2; ++q) {
                const double2 x = w2[q];
                acc[2 * q] += x.x * v;
                acc[2 * q + 1] += x.y * v;
            }
        }
#else
        RGS_SIMD
        for (int o = 0; o < N; ++o) acc[o] += w[o] * v;
#endif
    } else if constexpr (N > 0) {
        RGS_SIMD
        for (int o = 0; o < N; ++o) acc[o] += w[o] * v;
    } else {
        RGS_SIMD
        for (int o = 0; o < n; ++o) acc[o] += w[o] * v;
    }
}

template <typename T, int N>
RGS_HD void load_bias(int n, const T* __restrict__ b, T* acc) {
    if constexpr (N > 0) {
        RGS_SIMD
        for (int o = 0; o < N; ++o) acc[o] = b[o];
    } else {
        for (int o = 0; o < n; ++o) acc[o] = b[o];
    }
}

template <typename T, int N>
RGS_HD void relu_into(int n, const T* acc, T* out) {
    if constexpr (N > 0) {
        RGS_SIMD
        for (int o = 0; o < N; ++o) out[o] = relu(acc[o]);
    } else {
        for (int o = 0; o < n; ++o) out[o] = relu(acc[o]);
    }
}

// dst[k · stride] = src[k] for k < n (N > 0: unrolled, src stays in registers).
template <typename T, int N>
RGS_HD void store_column(int n, const T* src, T* __restrict__ dst, int64_t stride) {
    if constexpr (N > 0) {
        RGS_UNROLL
        for (int k = 0; k < N; ++k) dst[k * stride] = src[k];
    } else {
        for (int k = 0; k < n; ++k) dst[k * stride] = src[k];
    }
}

// Positional encoding fed straight into a Linear: rows of w for (v, sin(2^k pi v_j), cos(2^k pi v_j)) in
// IlluminationField's order (raw input, all sines, then all cosines; frequency-major, coordinate-minor). kKeep: the
// encoding is also written to pe[k · stride] (training keeps it for the backward).
template <typename T, int N, bool kKeep = false>
RGS_HD void encode_into(int n_freqs, int n, const T v[3], const T* __restrict__ w, T* acc, T* __restrict__ pe = nullptr,
                        int64_t stride = 0) {
    const int64_t ld = n;  // row stride: the layer's output width
    for (int j = 0; j < 3; ++j) {
        if constexpr (kKeep) pe[j * stride] = v[j];
        axpy_row<T, N>(n, w + j * ld, v[j], acc);
    }
    T freq = T(kPi);  // float32(2^k) * float32(pi) = 2^k * float32(pi): exact scaling, as torch's freqs
    for (int k = 0; k < n_freqs; ++k, freq *= T(2)) {
        for (int j = 0; j < 3; ++j) {
            T s, c;
            pe_sincos(v[j] * freq, s, c);
            if constexpr (kKeep) {
                pe[(3 + 3 * k + j) * stride] = s;
                pe[(3 + 3 * n_freqs + 3 * k + j) * stride] = c;
            }
            axpy_row<T, N>(n, w + (3 + 3 * k + j) * ld, s, acc);
            axpy_row<T, N>(n, w + (3 + 3 * n_freqs + 3 * k + j) * ld, c, acc);
        }
    }
}

// Where a training forward keeps each Linear's input followed by a 1 (the bias's column): rows of A, this
// Gaussian's column (A[row · stride]); row[l] is Linear l's first (illumination_train.h). Inference keeps nothing.
template <typename T>
struct KeptInputs {
    T* A;
    int64_t stride;
    const int* row;
};

// The illumination of one Gaussian at x (already divided by bound) seen along the unit direction d -> rgb.
// H, DH: compile-time hidden / dir_hidden widths (0 = use cfg's at run time). Two activation arrays serve all
// layers (the head's accumulators reuse the trunk's), which keeps the runtime path's local memory small. kKeep:
// every Linear's input is also written to `keep` (the training forward).
template <typename T, int H, int DH, bool kKeep = false>
RGS_HD void illumination_mlp(const IllumConfig& cfg, const IllumLayout& L, const T* __restrict__ W, const T x[3],
                             const T d[3], T rgb[3], const KeptInputs<T>& keep = KeptInputs<T>{nullptr, 0, nullptr}) {
    constexpr int A = H > 0 ? (H > DH ? H : DH) : kMaxIllumWidth;
    const int h = H > 0 ? H : cfg.hidden, dh = DH > 0 ? DH : cfg.dir_hidden;
    const int64_t st = keep.stride;
    // Linear l's kept input: its first row, and the 1 after its `width` values
    auto kept = [&](int l) { return keep.A + keep.row[l] * st; };
    T act[A], acc[A];
    load_bias<T, H>(h, W + L.trunk0_b, acc);
    if constexpr (kKeep) {
        encode_into<T, H, true>(cfg.pos_freqs, h, x, W + L.trunk0_w, acc, kept(0), st);
        kept(0)[encoded_width(cfg.pos_freqs) * st] = T(1);
    } else {
        encode_into<T, H>(cfg.pos_freqs, h, x, W + L.trunk0_w, acc);
    }
    relu_into<T, H>(h, acc, act);
    for (int l = 0; l + 1 < cfg.depth; ++l) {
        if constexpr (kKeep) {
            store_column<T, H>(h, act, kept(l + 1), st);
            kept(l + 1)[h * st] = T(1);
        }
        const T* w = W + L.trunk_w + l * L.trunk_stride;
        load_bias<T, H>(h, W + L.trunk_b + l * L.trunk_stride, acc);
        if constexpr (H > 0) {
            RGS_UNROLL
            for (int i = 0; i < H; ++i) axpy_row<T, H>(h, w + i * H, act[i], acc);
        } else {
            for (int i = 0; i < h; ++i) axpy_row<T, H>(h, w + int64_t(i) * h, act[i], acc);
        }
        relu_into<T, H>(h, acc, act);
    }
    // Head: cat(feature, PE(d)) -> dir_hidden -> 3.
    if constexpr (kKeep) store_column<T, H>(h, act, kept(cfg.depth), st);
    load_bias<T, DH>(dh, W + L.head0_b, acc);
    const T* w0 = W + L.head0_w;
    if constexpr (H > 0) {
        RGS_UNROLL
        for (int i = 0; i < H; ++i) axpy_row<T, DH>(dh, w0 + i * dh, act[i], acc);
    } else {
        for (int i = 0; i < h; ++i) axpy_row<T, DH>(dh, w0 + int64_t(i) * dh, act[i], acc);
    }
    if constexpr (kKeep) {
        encode_into<T, DH, true>(cfg.dir_freqs, dh, d, w0 + int64_t(h) * dh, acc, kept(cfg.depth) + h * st, st);
        kept(cfg.depth)[(h + encoded_width(cfg.dir_freqs)) * st] = T(1);
    } else {
        encode_into<T, DH>(cfg.dir_freqs, dh, d, w0 + int64_t(h) * dh, acc);
    }
    relu_into<T, DH>(dh, acc, act);
    if constexpr (kKeep) {
        store_column<T, DH>(dh, act, kept(cfg.depth + 1), st);
        kept(cfg.depth + 1)[dh * st] = T(1);
    }
    T out[3] = {W[L.head1_b], W[L.head1_b + 1], W[L.head1_b + 2]};
    const T* w1 = W + L.head1_w;
    if constexpr (DH > 0) {
        RGS_UNROLL
        for (int i = 0; i < DH; ++i) axpy_row<T, 3>(3, w1 + 3 * i, act[i], out);
    } else {
        for (int i = 0; i < dh; ++i) axpy_row<T, 3>(3, w1 + 3 * i, act[i], out);
    }
    for (int c = 0; c < 3; ++c) rgb[c] = sigmoid_of(out[c]);
}

// The view direction of IlluminationField at a Gaussian: F.normalize twice (view_dirs, then the field's forward),
// each x / max(|x|, 1e-12) of v = mean − centre; u the first, d the second, n1 and n2 their norms (the backward's).
template <typename T>
RGS_HD void view_direction(const T v[3], T u[3], T d[3], T& n1, T& n2) {
    n1 = sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2]);
    const T m1 = n1 > T(1e-12) ? n1 : T(1e-12);
    for (int c = 0; c < 3; ++c) u[c] = v[c] / m1;
    n2 = sqrt(u[0] * u[0] + u[1] * u[1] + u[2] * u[2]);
    const T m2 = n2 > T(1e-12) ? n2 : T(1e-12);
    for (int c = 0; c < 3; ++c) d[c] = u[c] / m2;
}

// Everything one Gaussian needs besides the weights.
template <typename T>
struct ColorArgs {
    int degree;        // active SH degree 0..3
    int rest;          // bases in sh_rest (K - 1)
    T center[3];       // camera centre, already rounded to T (torch casts it to the means' dtype)
    T inv_bound;       // 1 / bound rounded to T (the GPU path multiplies, as torch's CUDA division by a scalar)
    T bound;           // the CPU path divides, as torch's CPU division
};

// Colours of Gaussian i into out[0 .. 3 or 6). H, DH as in illumination_mlp; H < 0: reflectance only.
template <typename T, int H, int DH>
RGS_HD void gaussian_colors(int64_t i, const ColorArgs<T>& a, const IllumConfig& cfg, const IllumLayout& L,
                            const T* __restrict__ means,    // [N, 3]
                            const T* __restrict__ sh_dc,    // [N, 3]
                            const T* __restrict__ sh_rest,  // [N, rest, 3]
                            const T* __restrict__ W,        // [L.total]
                            T* __restrict__ out) {          // [3 or 6]
    const T v[3] = {means[3 * i] - a.center[0], means[3 * i + 1] - a.center[1], means[3 * i + 2] - a.center[2]};
    // Reflectance: the SH kernel's normalisation and summation order (basis 0 first), + 0.5, clamp at 0.
    T x, y, z, B[kMaxShCoeffs];
    normalize3(v, x, y, z);
    sh_basis(a.degree, x, y, z, B);
    const int nb = sh_num_bases(a.degree);
    const T* dc = sh_dc + 3 * i;
    const T* rest = sh_rest + i * a.rest * 3;
    for (int c = 0; c < 3; ++c) {
        T acc = T(0) + B[0] * dc[c];
        for (int k = 1; k < nb; ++k) acc += B[k] * rest[(k - 1) * 3 + c];
        acc = acc + T(0.5);
        out[c] = acc < T(0) ? T(0) : acc;
    }
    if constexpr (H >= 0) {
        T u[3], d[3], p[3], n1, n2;
        view_direction(v, u, d, n1, n2);
        for (int c = 0; c < 3; ++c) {
#if defined(__CUDA_ARCH__)
            p[c] = means[3 * i + c] * a.inv_bound;
#else
            p[c] = means[3 * i + c] / a.bound;
#endif
        }
        illumination_mlp<T, H, DH>(cfg, L, W, p, d, out + 3);
    }
}

// ---- host helpers shared by the two launchers ------------------------------------------------

template <typename T>
inline ColorArgs<T> make_color_args(int degree, int rest, const T* center, double bound) {
    ColorArgs<T> a;
    a.degree = degree;
    a.rest = rest;
    for (int c = 0; c < 3; ++c) a.center[c] = center[c];
    a.bound = T(bound);
    a.inv_bound = T(1) / T(bound);
    return a;
}

// Widths with a register-resident specialisation; any other widths (<= kMaxIllumWidth) take the runtime path.
inline bool illum_widths_specialized(int hidden, int dir_hidden) {
    return (hidden == 64 && dir_hidden == 32) || (hidden == 32 && dir_hidden == 16);
}

// f(std::integral_constant<int, H>, std::integral_constant<int, DH>) with the specialisation for cfg's widths
// (H = -1: no MLP, reflectance only).
template <typename F>
inline void dispatch_illum_widths(const IllumConfig* cfg, F&& f) {
    using std::integral_constant;
    if (cfg == nullptr)
        f(integral_constant<int, -1>{}, integral_constant<int, -1>{});
    else if (cfg->hidden == 64 && cfg->dir_hidden == 32)
        f(integral_constant<int, 64>{}, integral_constant<int, 32>{});
    else if (cfg->hidden == 32 && cfg->dir_hidden == 16)
        f(integral_constant<int, 32>{}, integral_constant<int, 16>{});
    else
        f(integral_constant<int, 0>{}, integral_constant<int, 0>{});
}

}  // namespace rgs
