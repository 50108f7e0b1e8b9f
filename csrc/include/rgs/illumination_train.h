// The illumination field's MLP in training (issue 65), one Gaussian per thread. In torch the field's forward +
// backward is ~60 kernels a step (5 Linear layers, the two positional encodings, their concatenations, ReLUs, bias
// sums), 0.57 ms of GPU time at 58k Gaussians.
//
// The forward is gaussian_colors.h's illumination_mlp keeping what the backward needs: every Linear's input followed
// by a 1 (the bias's column), in A [a_width, ld] (one row per activation, one column per Gaussian: the threads of a
// warp write consecutive addresses; ld >= N, the columns past N are the caller's). The backward writes each Linear's
// output gradient (before its activation) into D [d_width, ld] and the gradient of the Gaussians' centres; each
// layer's weight and bias gradients are then D_l · A_lᵀ = [out, in + 1] (the last column: the bias's), done by the
// caller (retinexgs/model/illumination_kernel.py). The weights are gaussian_colors.h's packed, transposed buffer
// (IllumLayout): the forward adds rows of it (axpy_row), the backward takes dot products with them. The encodings'
// and the view direction's derivatives follow IlluminationField.forward and view_dirs, so float64 agrees with
// torch's autograd to rounding.
#pragma once
#include "rgs/gaussian_colors.h"

namespace rgs {

constexpr int kMaxTrainLayers = 10;  // the trunk's depth + the head's 2 Linear layers: depth <= 8

// Where each Linear's input sits in A and its output gradient in D (rows), and its widths.
struct IllumTrainLayout {
    int layers;                     // depth + 2
    int in[kMaxTrainLayers];        // input width (the bias's column not counted)
    int out[kMaxTrainLayers];       // output width
    int a_in[kMaxTrainLayers];      // first row of the input in A (in + 1 rows: the input, then 1)
    int d_out[kMaxTrainLayers];     // first row of the output gradient in D (out rows)
    int a_width, d_width;
};

inline IllumTrainLayout illum_train_layout(const IllumConfig& c) {
    IllumTrainLayout S{};
    S.layers = c.depth + 2;
    const int ex = encoded_width(c.pos_freqs), ed = encoded_width(c.dir_freqs);
    int a = 0, d = 0;
    for (int l = 0; l < S.layers; ++l) {
        S.in[l] = l == 0 ? ex : l < c.depth ? c.hidden : l == c.depth ? c.hidden + ed : c.dir_hidden;
        S.out[l] = l < c.depth ? c.hidden : l == c.depth ? c.dir_hidden : 3;
        S.a_in[l] = a;
        S.d_out[l] = d;
        a += S.in[l] + 1;
        d += S.out[l];
    }
    S.a_width = a;
    S.d_width = d;
    return S;
}

// Offset of Linear l's transposed weight ([in, out]) and of its bias in the packed buffer.
RGS_HD int64_t layer_weight(const IllumLayout& L, int depth, int l) {
    return l == 0 ? L.trunk0_w : l < depth ? L.trunk_w + (l - 1) * L.trunk_stride : l == depth ? L.head0_w : L.head1_w;
}
RGS_HD int64_t layer_bias(const IllumLayout& L, int depth, int l) {
    return l == 0 ? L.trunk0_b : l < depth ? L.trunk_b + (l - 1) * L.trunk_stride : l == depth ? L.head0_b : L.head1_b;
}

// Σ_o w[o] · v[o] for o < n; w starts at a multiple of 4 elements (vector loads on the GPU, as axpy_row).
template <typename T, int N>
RGS_HD T dot_row(int n, const T* __restrict__ w, const T* v) {
    if constexpr (N > 0 && N % 4 == 0) {
        T s0 = T(0), s1 = T(0), s2 = T(0), s3 = T(0);  // four chains: the FMAs do not wait on each other
        RGS_UNROLL
        for (int q = 0; q < N / 4; ++q) {
#if defined(__CUDA_ARCH__)
            if constexpr (sizeof(T) == 4) {  // 128-bit loads of the shared weights, as axpy_row
                const float4 x = load_float4(w + 4 * q);
                s0 += x.x * v[4 * q];
                s1 += x.y * v[4 * q + 1];
                s2 += x.z * v[4 * q + 2];
                s3 += x.w * v[4 * q + 3];
                continue;
            }
#endif
            s0 += w[4 * q] * v[4 * q];
            s1 += w[4 * q + 1] * v[4 * q + 1];
            s2 += w[4 * q + 2] * v[4 * q + 2];
            s3 += w[4 * q + 3] * v[4 * q + 3];
        }
        return (s0 + s1) + (s2 + s3);
    } else {
        const int m = N > 0 ? N : n;
        T s = T(0);
        for (int o = 0; o < m; ++o) s += w[o] * v[o];
        return s;
    }
}

// prev[i] for i < n (N: its compile-time value) = Σ_o w[i·m + o] · delta[o], the input gradient of a Linear whose
// transposed rows are m wide, where the ReLU before it gave a positive output (the Linear's saved input in[i · stride]).
template <typename T, int N, int M>
RGS_HD void relu_input_grad(int n, int m, const T* __restrict__ w, const T* delta, const T* __restrict__ in,
                            int64_t stride, T* prev) {
    if constexpr (N > 0) {
        RGS_UNROLL
        for (int i = 0; i < N; ++i) {
            const T t = dot_row<T, M>(m, w + i * m, delta);
            prev[i] = in[i * stride] > T(0) ? t : T(0);
        }
    } else {
        for (int i = 0; i < n; ++i) {
            const T t = dot_row<T, M>(m, w + int64_t(i) * m, delta);
            prev[i] = in[i * stride] > T(0) ? t : T(0);
        }
    }
}

// g_v[j] += the gradient of the encoding pe (read at pe[k · stride]) of v, given its gradient g_pe(k):
// ∂/∂v_j of (v_j, sin(2^k π v_j), cos(2^k π v_j)) = (1, 2^k π cos, −2^k π sin).
template <typename T, typename G>
RGS_HD void encoding_backward(int n_freqs, const T* __restrict__ pe, int64_t stride, G&& g_pe, T g_v[3]) {
    for (int j = 0; j < 3; ++j) g_v[j] += g_pe(j);
    T freq = T(kPi);
    for (int k = 0; k < n_freqs; ++k, freq *= T(2)) {
        for (int j = 0; j < 3; ++j) {
            const int ks = 3 + 3 * k + j, kc = 3 + 3 * n_freqs + 3 * k + j;
            g_v[j] += freq * (g_pe(ks) * pe[kc * stride] - g_pe(kc) * pe[ks * stride]);
        }
    }
}

// The backward of illumination_mlp (gaussian_colors.h) with its inputs kept, for one Gaussian: from its output rgb and the gradient g_rgb, every
// Linear's output gradient into D (this Gaussian's column: D[row · d_stride]) and the gradients of x and d added to
// g_x and g_d. A ReLU passes the gradient where its output (the next layer's saved input) is positive, as torch's.
template <typename T, int H, int DH>
RGS_HD void illumination_mlp_backward(const IllumConfig& cfg, const IllumLayout& L, const IllumTrainLayout& S,
                                      const T* __restrict__ W, const T* __restrict__ A, int64_t stride,
                                      const T rgb[3], const T g_rgb[3], T* __restrict__ D, int64_t d_stride,
                                      T g_x[3], T g_d[3]) {
    constexpr int AW = H > 0 ? (H > DH ? H : DH) : kMaxIllumWidth;
    const int h = H > 0 ? H : cfg.hidden, dh = DH > 0 ? DH : cfg.dir_hidden;
    const int l0 = cfg.depth;
    T delta[AW], prev[AW];
    // sigmoid: g · (1 − y) · y (torch's order)
    T g_out[4] = {T(0), T(0), T(0), T(0)};
    for (int c = 0; c < 3; ++c) {
        g_out[c] = g_rgb[c] * (T(1) - rgb[c]) * rgb[c];
        D[(S.d_out[l0 + 1] + c) * d_stride] = g_out[c];
    }
    // Head's last Linear [dh, 3] (transposed rows of 3): its input g = relu(head's first Linear).
    relu_input_grad<T, DH, 3>(dh, 3, W + L.head1_w, g_out, A + S.a_in[l0 + 1] * stride, stride, delta);
    store_column<T, DH>(dh, delta, D + S.d_out[l0] * d_stride, d_stride);
    // Head's first Linear [h + enc_d, dh]: the trunk's feature (h rows), then PE(d).
    const T* w0 = W + L.head0_w;
    const T* f_in = A + S.a_in[l0] * stride;
    relu_input_grad<T, H, DH>(h, dh, w0, delta, f_in, stride, prev);
    encoding_backward(cfg.dir_freqs, f_in + int64_t(h) * stride, stride,
                      [&](int k) { return dot_row<T, DH>(dh, w0 + int64_t(h + k) * dh, delta); }, g_d);
    // The trunk, last to first: prev holds layer l's output gradient.
    for (int l = cfg.depth - 1; l >= 0; --l) {
        store_column<T, H>(h, prev, D + S.d_out[l] * d_stride, d_stride);
        if constexpr (H > 0) {
            RGS_UNROLL
            for (int i = 0; i < H; ++i) delta[i] = prev[i];
        } else {
            for (int i = 0; i < h; ++i) delta[i] = prev[i];
        }
        const T* w = W + layer_weight(L, cfg.depth, l);
        const T* in = A + S.a_in[l] * stride;
        if (l == 0) {
            encoding_backward(cfg.pos_freqs, in, stride, [&](int k) { return dot_row<T, H>(h, w + int64_t(k) * h, delta); },
                              g_x);
            break;
        }
        relu_input_grad<T, H, H>(h, h, w, delta, in, stride, prev);
    }
}

// The gradient of v from that of d = normalize(normalize(v)): y = x / |x| gives g_x = (g_y − y (y · g_y)) / |x|
// (and g_y / 1e-12 below the clamp).
template <typename T>
RGS_HD void view_direction_backward(const T u[3], const T d[3], T n1, T n2, const T g_d[3], T g_v[3]) {
    T g_u[3];
    const T dg = d[0] * g_d[0] + d[1] * g_d[1] + d[2] * g_d[2];
    for (int c = 0; c < 3; ++c) g_u[c] = n2 > T(1e-12) ? (g_d[c] - d[c] * dg) / n2 : g_d[c] / T(1e-12);
    const T ug = u[0] * g_u[0] + u[1] * g_u[1] + u[2] * g_u[2];
    for (int c = 0; c < 3; ++c) g_v[c] = n1 > T(1e-12) ? (g_u[c] - u[c] * ug) / n1 : g_u[c] / T(1e-12);
}

// Everything one Gaussian needs besides the weights: the camera centre (device or host memory: read per thread)
// and the position's scale (as ColorArgs: the GPU multiplies by 1 / bound, the CPU divides, as torch).
template <typename T>
struct IllumTrainArgs {
    const T* center;   // [3]
    T inv_bound, bound;
};

template <typename T>
RGS_HD void illum_inputs(int64_t i, const IllumTrainArgs<T>& a, const T* __restrict__ means, T x[3], T v[3]) {
    for (int c = 0; c < 3; ++c) {
        v[c] = means[3 * i + c] - a.center[c];
#if defined(__CUDA_ARCH__)
        x[c] = means[3 * i + c] * a.inv_bound;
#else
        x[c] = means[3 * i + c] / a.bound;
#endif
    }
}

// Forward of Gaussian i: rgb[3i .. 3i+3) and its column of A [a_width, ld].
template <typename T, int H, int DH>
RGS_HD void illumination_forward_one(int64_t i, int64_t ld, const IllumTrainArgs<T>& a, const IllumConfig& cfg,
                                     const IllumLayout& L, const IllumTrainLayout& S, const T* __restrict__ means,
                                     const T* __restrict__ W, T* __restrict__ rgb, T* __restrict__ A) {
    T x[3], v[3], u[3], d[3], n1, n2, out[3];
    illum_inputs(i, a, means, x, v);
    view_direction(v, u, d, n1, n2);
    illumination_mlp<T, H, DH, true>(cfg, L, W, x, d, out, KeptInputs<T>{A + i, ld, S.a_in});
    for (int c = 0; c < 3; ++c) rgb[3 * i + c] = out[c];
}

// Backward of Gaussian i: its column of D [d_width, ld] and g_means[3i .. 3i+3).
template <typename T, int H, int DH>
RGS_HD void illumination_backward_one(int64_t i, int64_t ld, const IllumTrainArgs<T>& a, const IllumConfig& cfg,
                                      const IllumLayout& L, const IllumTrainLayout& S, const T* __restrict__ means,
                                      const T* __restrict__ W, const T* __restrict__ A, const T* __restrict__ rgb,
                                      const T* __restrict__ g_rgb, T* __restrict__ D, T* __restrict__ g_means) {
    T x[3], v[3], u[3], d[3], n1, n2;
    illum_inputs(i, a, means, x, v);
    view_direction(v, u, d, n1, n2);
    const T y[3] = {rgb[3 * i], rgb[3 * i + 1], rgb[3 * i + 2]};
    const T g[3] = {g_rgb[3 * i], g_rgb[3 * i + 1], g_rgb[3 * i + 2]};
    T g_x[3] = {T(0), T(0), T(0)}, g_d[3] = {T(0), T(0), T(0)}, g_v[3];
    illumination_mlp_backward<T, H, DH>(cfg, L, S, W, A + i, ld, y, g, D + i, ld, g_x, g_d);
    view_direction_backward(u, d, n1, n2, g_d, g_v);
    for (int c = 0; c < 3; ++c) {
#if defined(__CUDA_ARCH__)
        g_means[3 * i + c] = g_x[c] * a.inv_bound + g_v[c];
#else
        g_means[3 * i + c] = g_x[c] / a.bound + g_v[c];
#endif
    }
}

}  // namespace rgs
