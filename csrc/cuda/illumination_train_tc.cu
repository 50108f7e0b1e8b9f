// The illumination field's MLP in training on the tensor cores (TF32), float32 only (issue 65).
//
// illumination_train.cu runs the MLP one Gaussian per thread with fp32 FMAs fed from shared memory: ≈ 6 TFMA/s,
// 350 µs of a fox-dark step (58k Gaussians) forward and backward. Here a warp takes 16 Gaussians at a time and every
// Linear is a [16, in] × [in, out] product of wmma m16n16k8 TF32 tiles (products rounded to a 10-bit mantissa,
// accumulated in fp32; cuBLAS's TF32 mode does the same), the activations of the 16 staying in the warp's shared
// tile between the layers. Same interface and buffers as illumination_train.h: A (every Linear's input then a 1),
// D (every Linear's output gradient), rgb and the centres' gradient; the encodings, the view direction and their
// derivatives are that header's, so only the products' rounding differs (tests/test_cuda_illumination_kernel.py).
//
// Shared memory: each layer's transposed weight with its bias as one more row, [in_pad, out_pad] (both padded to
// whole 16s with zeros, already rounded to TF32), then one [16, ldx] activation tile per warp. The forward takes a
// layer's output as X · Wᵀ (Wᵀ row-major); the backward its input gradient as D · W, the same buffer read as the
// column-major W.
#include <mma.h>

#include <algorithm>
#include <type_traits>

#include "common.cuh"
#include "rgs/illumination_train.h"
#include "rgs/kernels_cuda.h"

namespace rgs {

constexpr int kTcMaxWarps = 16;  // a block: one per SM (the weights' copy is shared by all its warps)
constexpr int kTcMaxTiles = 8;   // output widths up to 128

struct IllumTcLayout {
    int in_pad[kMaxTrainLayers], out_pad[kMaxTrainLayers];
    int ldw[kMaxTrainLayers];    // layer l's row stride: out_pad + 4, so that a tile's 8 or 16 rows (or columns, read
                                 // column-major) fall in different banks (out_pad alone: 8- and 16-way conflicts)
    int w_off[kMaxTrainLayers];  // layer l's [in_pad, ldw] block in shared memory (floats)
    int weights;                 // floats of all blocks (a multiple of 8: the tiles stay 32-byte aligned)
    int ldx;                     // the activation tile's row stride
};

RGS_HD int pad16(int n) { return (n + 15) / 16 * 16; }

inline IllumTcLayout illum_tc_layout(const IllumTrainLayout& S, int depth, int ex, int ed) {
    IllumTcLayout T{};
    int off = 0, widest = 0;
    for (int l = 0; l < S.layers; ++l) {
        T.in_pad[l] = pad16(S.in[l] + 1);
        T.out_pad[l] = pad16(S.out[l]);
        T.ldw[l] = T.out_pad[l] + 4;
        T.w_off[l] = off;
        off += T.in_pad[l] * T.ldw[l];  // a multiple of 16 · 4: the next block stays 32-byte aligned
        widest = std::max(widest, std::max(T.in_pad[l], T.out_pad[l]));
    }
    (void)depth, (void)ex, (void)ed;
    T.weights = off;
    T.ldx = widest + 4;  // 4 banks between rows
    return T;
}

inline size_t illum_tc_shared_bytes(const IllumTcLayout& T, int warps) {
    return size_t(T.weights + warps * 16 * T.ldx) * sizeof(float);
}

#if !defined(__CUDA_ARCH__) || __CUDA_ARCH__ >= 800
#define RGS_TC_BODY 1
#endif

namespace {

using namespace nvcuda;

// Every layer's [in_pad, out_pad] block from the packed buffer (illum_layout: transposed weights [in, out], bias [out]).
__device__ void stage_tc_weights(const float* __restrict__ packed, const IllumLayout& L, const IllumTrainLayout& S,
                                 const IllumTcLayout& T, int depth, float* W) {
#ifdef RGS_TC_BODY
    for (int l = 0; l < S.layers; ++l) {
        const float* w = packed + layer_weight(L, depth, l);
        const float* b = packed + layer_bias(L, depth, l);
        const int in = S.in[l], out = S.out[l], op = T.ldw[l], n = T.in_pad[l] * op;
        float* dst = W + T.w_off[l];
        for (int k = threadIdx.x; k < n; k += blockDim.x) {
            const int r = k / op, c = k - r * op;
            const float v = c >= out ? 0.f : r < in ? w[r * out + c] : r == in ? b[c] : 0.f;
            dst[k] = wmma::__float_to_tf32(v);
        }
    }
    __syncthreads();
#endif
}

// X[:, 0 : 16·NT) = X[:, 0 : K) · B for the warp's 16 rows, in place (every tile of X is read before any is written).
// B [K, 16·NT]: kColMajor false reads it row-major with row stride ldb (the forward's Wᵀ), true column-major
// (the backward's W from the same buffer: element (k, n) at B[n · ldb + k]).
template <int NT, bool kColMajor>
__device__ void tc_product(float* X, int ldx, int K, const float* B, int ldb) {
#ifdef RGS_TC_BODY
    using Layout = typename std::conditional<kColMajor, wmma::col_major, wmma::row_major>::type;
    wmma::fragment<wmma::accumulator, 16, 16, 8, float> acc[NT];
#pragma unroll
    for (int j = 0; j < NT; ++j) wmma::fill_fragment(acc[j], 0.f);
    for (int k = 0; k < K; k += 8) {
        wmma::fragment<wmma::matrix_a, 16, 16, 8, wmma::precision::tf32, wmma::row_major> a;
        wmma::load_matrix_sync(a, X + k, ldx);
#pragma unroll
        for (int t = 0; t < a.num_elements; ++t) a.x[t] = wmma::__float_to_tf32(a.x[t]);
#pragma unroll
        for (int j = 0; j < NT; ++j) {
            wmma::fragment<wmma::matrix_b, 16, 16, 8, wmma::precision::tf32, Layout> b;
            wmma::load_matrix_sync(b, kColMajor ? B + j * 16 * ldb + k : B + k * ldb + j * 16, ldb);
            wmma::mma_sync(acc[j], a, b, acc[j]);
        }
    }
    __syncwarp();
#pragma unroll
    for (int j = 0; j < NT; ++j) wmma::store_matrix_sync(X + j * 16, acc[j], ldx, wmma::mem_row_major);
    __syncwarp();
#endif
}

template <bool kColMajor>
__device__ void tc_product_any(int n, float* X, int ldx, int K, const float* B, int ldb) {
    switch (n / 16) {
        case 1: tc_product<1, kColMajor>(X, ldx, K, B, ldb); break;
        case 2: tc_product<2, kColMajor>(X, ldx, K, B, ldb); break;
        case 3: tc_product<3, kColMajor>(X, ldx, K, B, ldb); break;
        case 4: tc_product<4, kColMajor>(X, ldx, K, B, ldb); break;
        case 5: tc_product<5, kColMajor>(X, ldx, K, B, ldb); break;
        case 6: tc_product<6, kColMajor>(X, ldx, K, B, ldb); break;
        case 7: tc_product<7, kColMajor>(X, ldx, K, B, ldb); break;
        default: tc_product<8, kColMajor>(X, ldx, K, B, ldb); break;
    }
}

// rows[c · ld + g] = X[g, c] for c < n and the tile's valid Gaussians g < nv (16 consecutive floats a row).
__device__ void tile_to_rows(const float* X, int ldx, int n, float* __restrict__ rows, int64_t ld, int nv, int lane) {
    for (int k = lane; k < 16 * n; k += 32) {
        const int g = k & 15, c = k >> 4;
        if (g < nv) rows[c * ld + g] = X[g * ldx + c];
    }
}

// The positional encoding of v into row[0 .. 3(2F + 1)), encode_into's order (v, the sines, the cosines); the
// half-warp `half` (0, 1) writes v and the octaves [0, F/2), the other half the rest.
__device__ void encode_row(int n_freqs, const float v[3], float* row, int half) {
    if (half == 0)
        for (int j = 0; j < 3; ++j) row[j] = v[j];
    const int k0 = half == 0 ? 0 : n_freqs / 2, k1 = half == 0 ? n_freqs / 2 : n_freqs;
    float freq = float(kPi) * float(1 << k0);  // 2^k · float32(pi): exact, as encode_into's doubling
    for (int k = k0; k < k1; ++k, freq *= 2.f) {
        for (int j = 0; j < 3; ++j) {
            float s, c;
            pe_sincos(v[j] * freq, s, c);
            row[3 + 3 * k + j] = s;
            row[3 + 3 * n_freqs + 3 * k + j] = c;
        }
    }
}

// encoding_backward (illumination_train.h) split over the two half-warps as encode_row: each adds its share to
// g_v, then the halves' shares are summed (every lane of a pair ends with the whole). Every lane of the warp calls
// it (the shuffle); half 2: a lane without a Gaussian, which adds nothing.
template <typename G>
__device__ void encoding_backward_halves(int n_freqs, const float* __restrict__ pe, int64_t stride, G&& g_pe,
                                         float g_v[3], int half) {
    float part[3] = {0.f, 0.f, 0.f};
    if (half == 0)
        for (int j = 0; j < 3; ++j) part[j] = g_pe(j);
    const int k0 = half == 0 ? 0 : n_freqs / 2, k1 = half == 0 ? n_freqs / 2 : half == 1 ? n_freqs : 0;
    float freq = float(kPi) * float(1 << k0);
    for (int k = k0; k < k1; ++k, freq *= 2.f) {
        for (int j = 0; j < 3; ++j) {
            const int ks = 3 + 3 * k + j, kc = 3 + 3 * n_freqs + 3 * k + j;
            part[j] += freq * (g_pe(ks) * pe[kc * stride] - g_pe(kc) * pe[ks * stride]);
        }
    }
    for (int j = 0; j < 3; ++j) g_v[j] += part[j] + __shfl_xor_sync(0xffffffffu, part[j], 16);
}

__global__ void __launch_bounds__(kTcMaxWarps * 32, 1)
illumination_forward_tc_kernel(int64_t N, IllumTrainArgs<float> a, IllumConfig cfg, IllumLayout L,
                               IllumTrainLayout S, IllumTcLayout T, const float* __restrict__ means,
                               const float* __restrict__ weights, float* __restrict__ rgb, float* __restrict__ A,
                               int64_t ld) {
#ifdef RGS_TC_BODY
    extern __shared__ __align__(32) float smem_tc[];
    stage_tc_weights(weights, L, S, T, cfg.depth, smem_tc);
    const int warps = blockDim.x >> 5, warp = threadIdx.x >> 5, lane = threadIdx.x & 31;
    const int g = lane & 15, half = lane >> 4;  // the tile row a lane works on, and which half of its octaves
    float* X = smem_tc + T.weights + warp * 16 * T.ldx;
    float* row = X + g * T.ldx;
    const int ex = encoded_width(cfg.pos_freqs), h = cfg.hidden;
    const int64_t tiles = (N + 15) / 16;
    for (int64_t t = int64_t(blockIdx.x) * warps + warp; t < tiles; t += int64_t(gridDim.x) * warps) {
        const int64_t i0 = t * 16;
        const int nv = int(N - i0 < 16 ? N - i0 : 16);
        // Row g: PE(x), 1, zeros to the padded width (rows past N: zeros; they are never written out)
        float d[3] = {0.f, 0.f, 0.f};
        if (g < nv) {
            float x[3], v[3], u[3], n1, n2;
            illum_inputs(i0 + g, a, means, x, v);
            view_direction(v, u, d, n1, n2);
            encode_row(cfg.pos_freqs, x, row, half);
            if (half == 1)
                for (int c = ex; c < T.in_pad[0]; ++c) row[c] = c == ex ? 1.f : 0.f;
        } else if (half == 0) {
            for (int c = 0; c < T.in_pad[0]; ++c) row[c] = 0.f;
        }
        __syncwarp();
        for (int l = 0; l < S.layers; ++l) {
            tile_to_rows(X, T.ldx, S.in[l] + 1, A + S.a_in[l] * ld + i0, ld, nv, lane);
            __syncwarp();
            tc_product_any<false>(T.out_pad[l], X, T.ldx, T.in_pad[l], smem_tc + T.w_off[l], T.ldw[l]);
            const int out = S.out[l];
            if (l + 1 == S.layers) {  // the head's last Linear: sigmoid -> rgb
                if (g < nv && half == 0)
                    for (int c = 0; c < 3; ++c) rgb[3 * (i0 + g) + c] = sigmoid_of(row[c]);
                break;
            }
            // ReLU, the next Linear's bias column, zeros to its padded width (PE(d) after the trunk: below)
            const int in_next = S.in[l + 1], pad_next = T.in_pad[l + 1];
            for (int k = lane; k < 16 * pad_next; k += 32) {
                const int r = k / pad_next, c = k - r * pad_next;
                float& x = X[r * T.ldx + c];
                x = c < out ? relu(x) : c == in_next ? 1.f : 0.f;
            }
            __syncwarp();
            if (l + 1 == cfg.depth && g < nv) encode_row(cfg.dir_freqs, d, row + h, half);
            __syncwarp();
        }
    }
#endif
}

__global__ void __launch_bounds__(kTcMaxWarps * 32, 1)
illumination_backward_tc_kernel(int64_t N, IllumTrainArgs<float> a, IllumConfig cfg, IllumLayout L,
                                IllumTrainLayout S, IllumTcLayout T, const float* __restrict__ means,
                                const float* __restrict__ weights, const float* __restrict__ A,
                                const float* __restrict__ rgb, const float* __restrict__ g_rgb, float* __restrict__ D,
                                float* __restrict__ g_means, int64_t ld) {
#ifdef RGS_TC_BODY
    extern __shared__ __align__(32) float smem_tc[];
    stage_tc_weights(weights, L, S, T, cfg.depth, smem_tc);
    const int warps = blockDim.x >> 5, warp = threadIdx.x >> 5, lane = threadIdx.x & 31;
    const int g = lane & 15, half = lane >> 4;
    float* X = smem_tc + T.weights + warp * 16 * T.ldx;
    float* row = X + g * T.ldx;
    const int ex = encoded_width(cfg.pos_freqs), h = cfg.hidden;
    const int last = S.layers - 1, k_last = T.out_pad[last];
    const int64_t tiles = (N + 15) / 16;
    for (int64_t t = int64_t(blockIdx.x) * warps + warp; t < tiles; t += int64_t(gridDim.x) * warps) {
        const int64_t i0 = t * 16;
        const int nv = int(N - i0 < 16 ? N - i0 : 16);
        const bool valid = g < nv;
        // Row g: the sigmoid's gradient g · (1 − y) · y, zeros to the last Linear's padded width
        for (int c = half; c < k_last; c += 2) {
            float v = 0.f;
            if (valid && c < 3) {
                const float y = rgb[3 * (i0 + g) + c];
                v = g_rgb[3 * (i0 + g) + c] * (1.f - y) * y;
            }
            row[c] = v;
        }
        __syncwarp();
        float g_x[3] = {0.f, 0.f, 0.f}, g_d[3] = {0.f, 0.f, 0.f};
        for (int l = last; l >= 0; --l) {
            // X holds Linear l's output gradient (zeros past its width)
            tile_to_rows(X, T.ldx, S.out[l], D + S.d_out[l] * ld + i0, ld, nv, lane);
            __syncwarp();
            const int n = l == 0 ? pad16(ex) : pad16(S.in[l]);  // the input gradient's columns wanted
            tc_product_any<true>(n, X, T.ldx, T.out_pad[l], smem_tc + T.w_off[l], T.ldw[l]);
            const float* in = A + S.a_in[l] * ld + i0;  // Linear l's saved input
            if (l == 0) {
                encoding_backward_halves(cfg.pos_freqs, in + (valid ? g : 0), ld,
                                         [&](int k) { return valid ? row[k] : 0.f; }, g_x, valid ? half : 2);
                break;
            }
            if (l == cfg.depth)  // the head's first Linear: PE(d)'s gradient after the feature's
                encoding_backward_halves(cfg.dir_freqs, in + int64_t(h) * ld + (valid ? g : 0), ld,
                                         [&](int k) { return valid ? row[h + k] : 0.f; }, g_d, valid ? half : 2);
            // the ReLU before Linear l passes the gradient where its output (Linear l's input) is positive
            const int width = l == cfg.depth ? h : S.in[l];
            for (int k = lane; k < 16 * width; k += 32) {
                const int r = k & 15, c = k >> 4;
                float& x = X[r * T.ldx + c];
                x = r < nv && in[c * ld + r] > 0.f ? x : 0.f;
            }
            __syncwarp();
        }
        if (valid && half == 0) {
            const int64_t i = i0 + g;
            float x[3], v[3], u[3], d[3], n1, n2, g_v[3];
            illum_inputs(i, a, means, x, v);
            view_direction(v, u, d, n1, n2);
            view_direction_backward(u, d, n1, n2, g_d, g_v);
            for (int c = 0; c < 3; ++c) g_means[3 * i + c] = g_x[c] * a.inv_bound + g_v[c];
        }
        __syncwarp();
    }
#endif
}

struct TcLaunch {
    IllumLayout L;
    IllumTrainLayout S;
    IllumTcLayout T;
    size_t bytes;
    int blocks, warps;
};

// The launch of N Gaussians, or false where the tensor-core path does not apply (an older GPU, widths that are not
// whole 16s, weights past shared memory). One block an SM, as many warps (≤ 16) as its shared memory holds tiles.
bool tc_launch(int64_t N, const IllumConfig& cfg, TcLaunch* out) {
    int device = 0, major = 0, sms = 0, max_shared = 0;
    check_cuda(cudaGetDevice(&device), "illumination tc (device)");
    check_cuda(cudaDeviceGetAttribute(&major, cudaDevAttrComputeCapabilityMajor, device), "illumination tc (arch)");
    check_cuda(cudaDeviceGetAttribute(&sms, cudaDevAttrMultiProcessorCount, device), "illumination tc (SMs)");
    check_cuda(cudaDeviceGetAttribute(&max_shared, cudaDevAttrMaxSharedMemoryPerBlockOptin, device),
               "illumination tc (shared memory size)");
    if (major < 8 || cfg.hidden % 16 != 0 || cfg.dir_hidden % 16 != 0 || cfg.hidden > 16 * kTcMaxTiles) return false;
    out->L = illum_layout(cfg);
    out->S = illum_train_layout(cfg);
    out->T = illum_tc_layout(out->S, cfg.depth, encoded_width(cfg.pos_freqs), encoded_width(cfg.dir_freqs));
    for (int l = 0; l < out->S.layers; ++l)
        if (out->T.in_pad[l] > 16 * kTcMaxTiles) return false;
    out->warps = kTcMaxWarps;
    while (out->warps > 1 && illum_tc_shared_bytes(out->T, out->warps) > size_t(max_shared)) --out->warps;
    out->bytes = illum_tc_shared_bytes(out->T, out->warps);
    if (out->bytes > size_t(max_shared)) return false;
    const int64_t tiles = (N + 15) / 16;
    out->blocks = int(std::max<int64_t>(1, std::min<int64_t>((tiles + out->warps - 1) / out->warps, sms)));
    return true;
}

template <typename Kernel>
void allow_tc_shared(Kernel kernel, size_t bytes) {
    check_cuda(cudaFuncSetAttribute(kernel, cudaFuncAttributeMaxDynamicSharedMemorySize, int(bytes)),
               "illumination tc (shared memory limit)");
}

}  // namespace

bool illumination_forward_tc_cuda(int64_t N, const float* means, const float* center, const IllumConfig& cfg,
                                  double bound, const float* weights, float* rgb, float* A, int64_t ld, void* stream) {
    TcLaunch c;
    if (!tc_launch(N, cfg, &c)) return false;
    if (N == 0) return true;
    const IllumTrainArgs<float> a{center, 1.f / float(bound), float(bound)};
    allow_tc_shared(illumination_forward_tc_kernel, c.bytes);
    illumination_forward_tc_kernel<<<c.blocks, c.warps * 32, c.bytes, static_cast<cudaStream_t>(stream)>>>(
        N, a, cfg, c.L, c.S, c.T, means, weights, rgb, A, ld);
    RGS_CHECK_LAUNCH("illumination_forward (tensor cores)");
    return true;
}

bool illumination_backward_tc_cuda(int64_t N, const float* means, const float* center, const IllumConfig& cfg,
                                   double bound, const float* weights, const float* A, const float* rgb,
                                   const float* g_rgb, float* D, float* g_means, int64_t ld, void* stream) {
    TcLaunch c;
    if (!tc_launch(N, cfg, &c)) return false;
    if (N == 0) return true;
    const IllumTrainArgs<float> a{center, 1.f / float(bound), float(bound)};
    allow_tc_shared(illumination_backward_tc_kernel, c.bytes);
    illumination_backward_tc_kernel<<<c.blocks, c.warps * 32, c.bytes, static_cast<cudaStream_t>(stream)>>>(
        N, a, cfg, c.L, c.S, c.T, means, weights, A, rgb, g_rgb, D, g_means, ld);
    RGS_CHECK_LAUNCH("illumination_backward (tensor cores)");
    return true;
}

}  // namespace rgs
