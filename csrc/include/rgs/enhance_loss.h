// L_enhance of the default configuration in two passes, its gradient carried forward (issue 65).
//
// With L_enhance off the scene (loss.enhance_trains_scene false: R̂, L̂ detached) the whole term is a function of the
// tone's per-channel gain k (3 numbers) over a fixed image x = R̂∘L̂ and the view S:
//   y_c(p)  = srgb(s(k_c · lin(x_c(p))))                     the enhanced image (rgs/tone_curve.h)
//   Y(p)    = (y_0 + y_1 + y_2) / 3, m_c = mean_p y_c          brightness, channel means
//   L_spa   = dᵀA d / n,  d_j = P_j / σ − O_j / σ_o            P, O: pool×pool means of Y and of S's brightness over
//             the n whole regions; σ, σ_o: their means (the images' where a border region is partial), floored at
//             1e-6 (or 1 without scale invariance); (A d)_j = (8 − border sides)·d_j − 2·(its 4 neighbours' sum)
//   L_exp   = (mean_c m_c − E)²  (or |·|)                     the whole image's meter, E fixed
//   L_col   = Σ_{a<b} (m̃_a − m̃_b)²,  m̃ = m / max(mean m, 1e-6)  (or m)
// (retinexgs/train/losses.py spatial_consistency_loss, exposure_loss, color_constancy_loss, term for term). Each y_c
// depends on k_c alone, so dL/dk_c needs only the per-region sums of t_c = ∂y_c/∂k_c besides the values: pass 1 (one
// thread a pool×pool cell) sums y_c, t_c and S's brightness per cell; pass 2 reduces the cells, forms d, A d and the
// three terms with their 3×3 Jacobian. In torch the same is ~60 operators each way (the tone curve, pooling, means,
// the normalisations, the pair energy). A cell sums its rows in order (enhance_cell_row: one GPU thread a row), and a
// cell's d is recomputed from its own sums wherever a neighbour needs it (no array of d: the GPU's pair pass is one
// thread a cell over many blocks, each block's sums in a fixed order).
#pragma once
#include <cmath>
#include <cstdint>

#include "rgs/tone_curve.h"
#include "rgs/types.h"

namespace rgs {

constexpr int kEnhanceCellValues = 7;  // per cell: Σ y_c (3), Σ t_c (3), Σ S's brightness (1)
constexpr int kEnhanceSums = 9;        // the first reduction: Σ y_c, Σ t_c, Σ O, over whole cells Σ P and Σ O
constexpr int kEnhancePairSums = 5;    // the second reduction (enhance_add_pair)
constexpr int kEnhanceScalarValues = 9;  // EnhanceScalars stored: m (3), M (3), σ, σ_o, σ free (0 or 1)
constexpr int kEnhanceOut = 12;        // (spa, exp, col) then d(term)/dk_c, term-major

// Row r of cell (cy, cx) of pool×pool pixels (a partial cell at the right or bottom border has fewer; a row past the
// bottom is zero): x and s are [H, W, 3] contiguous, gain [3]. Writes kEnhanceCellValues sums over the row.
template <typename T>
RGS_HD void enhance_cell_row(const T* x, const T* s, int64_t H, int64_t W, int pool, int64_t cy, int64_t cx, int r,
                             const T* gain, T knee, int form_in, int form_out, T* out) {
    T v[3] = {T(0), T(0), T(0)}, t[3] = {T(0), T(0), T(0)}, o = T(0);
    const int64_t py = cy * pool + r;
    if (r < pool && py < H) {
        const int64_t x1 = (cx + 1) * pool < W ? (cx + 1) * pool : W;
        for (int64_t px = cx * pool; px < x1; ++px) {
            const int64_t i = (py * W + px) * 3;
            for (int c = 0; c < 3; ++c) {
                T dk;
                v[c] += tone_curve_value_dk(x[i + c], gain[c], knee, form_in, form_out, &dk);
                t[c] += dk;
            }
            o += (s[i] + s[i + 1] + s[i + 2]) / T(3);
        }
    }
    for (int c = 0; c < 3; ++c) out[c] = v[c], out[3 + c] = t[c];
    out[6] = o;
}

// Pass 1 for cell (cy, cx): its rows' sums added in order (as the GPU's threads of one cell are).
template <typename T>
RGS_HD void enhance_cell(const T* x, const T* s, int64_t H, int64_t W, int pool, int64_t cy, int64_t cx,
                         const T* gain, T knee, int form_in, int form_out, T* out) {
    for (int j = 0; j < kEnhanceCellValues; ++j) out[j] = T(0);
    for (int r = 0; r < pool; ++r) {
        T row[kEnhanceCellValues];
        enhance_cell_row(x, s, H, W, pool, cy, cx, r, gain, knee, form_in, form_out, row);
        for (int j = 0; j < kEnhanceCellValues; ++j) out[j] += row[j];
    }
}

// The first reduction's share of one cell: sums[0..2] Σ y_c, [3..5] Σ t_c, [6] Σ O over every cell; [7] Σ P (the
// cell's brightness mean) and [8] Σ O / pool² over the whole cells.
template <typename T, typename A>
RGS_HD void enhance_add_cell(const T* cell, bool whole, int pool, A* sums) {
    for (int j = 0; j < kEnhanceCellValues; ++j) sums[j] += A(cell[j]);
    if (whole) {
        const A area = A(pool) * A(pool);
        sums[7] += (A(cell[0]) + A(cell[1]) + A(cell[2])) / A(3) / area;
        sums[8] += A(cell[6]) / area;
    }
}

// The scalars pass 2 needs after its first reduction: m_c, M_c (the mean of t_c), σ, σ_o and whether each floor let
// the gradient through.
template <typename A>
struct EnhanceScalars {
    A m[3], M[3], sigma, sigma_o;
    bool sigma_free;  // σ is the image's own (not floored, scale invariant): its derivative counts
};

template <typename A>
RGS_HD EnhanceScalars<A> enhance_scalars(const A* sums, int64_t H, int64_t W, int64_t n_whole, bool whole_image,
                                         bool scale_invariant) {
    EnhanceScalars<A> s;
    const A N = A(H) * A(W);
    for (int c = 0; c < 3; ++c) s.m[c] = sums[c] / N, s.M[c] = sums[3 + c] / N;
    s.sigma = A(1), s.sigma_o = A(1), s.sigma_free = false;
    if (scale_invariant) {
        // the regions' mean where no region is partial, else the image's (losses.py _pooled_brightness)
        const A mean = whole_image ? sums[7] / A(n_whole) : (s.m[0] + s.m[1] + s.m[2]) / A(3);
        const A mean_o = whole_image ? sums[8] / A(n_whole) : sums[6] / N;
        s.sigma_free = mean >= A(1e-6);
        s.sigma = s.sigma_free ? mean : A(1e-6);
        s.sigma_o = mean_o >= A(1e-6) ? mean_o : A(1e-6);
    }
    return s;
}

template <typename A>
RGS_HD void enhance_scalars_store(const EnhanceScalars<A>& s, A* out) {
    for (int c = 0; c < 3; ++c) out[c] = s.m[c], out[3 + c] = s.M[c];
    out[6] = s.sigma, out[7] = s.sigma_o, out[8] = s.sigma_free ? A(1) : A(0);
}

template <typename A>
RGS_HD EnhanceScalars<A> enhance_scalars_load(const A* in) {
    EnhanceScalars<A> s;
    for (int c = 0; c < 3; ++c) s.m[c] = in[c], s.M[c] = in[3 + c];
    s.sigma = in[6], s.sigma_o = in[7], s.sigma_free = in[8] != A(0);
    return s;
}

// d_j of whole cell j (its pool×pool sums in `cell`).
template <typename T, typename A>
RGS_HD A enhance_d(const T* cell, int pool, const EnhanceScalars<A>& s) {
    const A area = A(pool) * A(pool);
    const A P = (A(cell[0]) + A(cell[1]) + A(cell[2])) / A(3) / area, O = A(cell[6]) / area;
    return P / s.sigma - O / s.sigma_o;
}

// The second reduction's share of whole cell j: acc[0] Σ d·Ad, [1] Σ G·P (G = 2 Ad / n, dL_spa/dd), [2..4]
// Σ G · t_c's cell mean / 3 (dP_j/dk_c = that mean / 3).
template <typename T, typename A>
RGS_HD void enhance_add_pair(const T* cell, int pool, A dj, A Adj, int64_t n_whole, A* acc) {
    const A area = A(pool) * A(pool);
    const A G = A(2) * Adj / A(n_whole);
    acc[0] += dj * Adj;
    acc[1] += G * (A(cell[0]) + A(cell[1]) + A(cell[2])) / A(3) / area;
    for (int c = 0; c < 3; ++c) acc[2 + c] += G * A(cell[3 + c]) / area / A(3);
}

// enhance_add_pair for whole cell (jy, jx) of nh × nw (cells: [ch, cw] rows of kEnhanceCellValues), its d and
// (A d)_j = (8 − border sides)·d_j − 2·(its 4 neighbours' sum) from its own and its neighbours' cell sums.
template <typename T, typename A>
RGS_HD void enhance_add_pair_at(const T* cells, int64_t cw, int pool, int64_t nh, int64_t nw, int64_t jy, int64_t jx,
                                const EnhanceScalars<A>& s, A* acc) {
    const T* cell = cells + (jy * cw + jx) * kEnhanceCellValues;
    const A dj = enhance_d(cell, pool, s);
    A nbr = A(0);
    int border = 0;
    if (jy > 0) nbr += enhance_d(cell - cw * kEnhanceCellValues, pool, s); else ++border;
    if (jy + 1 < nh) nbr += enhance_d(cell + cw * kEnhanceCellValues, pool, s); else ++border;
    if (jx > 0) nbr += enhance_d(cell - kEnhanceCellValues, pool, s); else ++border;
    if (jx + 1 < nw) nbr += enhance_d(cell + kEnhanceCellValues, pool, s); else ++border;
    enhance_add_pair(cell, pool, dj, A(8 - border) * dj - A(2) * nbr, nh * nw, acc);
}

// The three terms and their gradients in the gain from the reductions (out: kEnhanceOut values).
template <typename T, typename A>
RGS_HD void enhance_terms(const EnhanceScalars<A>& s, const A* acc, int64_t n_whole, A E, bool exp_l1,
                          bool scale_invariant, T* out) {
    // L_spa: d depends on k through P directly (1/σ) and through σ (−Σ G·P / σ², dσ/dk_c = M_c / 3)
    const A spa = acc[0] / A(n_whole);
    const A dsigma = s.sigma_free ? -acc[1] / (s.sigma * s.sigma) : A(0);
    // L_exp on the mean brightness ȳ = mean_c m_c, dȳ/dk_c = M_c / 3
    const A ybar = (s.m[0] + s.m[1] + s.m[2]) / A(3), r = ybar - E;
    const A exp = exp_l1 ? (r < A(0) ? -r : r) : r * r;
    const A dexp = exp_l1 ? (r > A(0) ? A(1) : (r < A(0) ? A(-1) : A(0))) : A(2) * r;
    // L_col on m̃ = m / μ (μ = mean m, floored): dL/dm̃_a = 2 (3 m̃_a − Σ m̃), then through μ
    A mu = A(1);
    bool mu_free = false;
    if (scale_invariant) {
        const A mean = (s.m[0] + s.m[1] + s.m[2]) / A(3);
        mu_free = mean >= A(1e-6);
        mu = mu_free ? mean : A(1e-6);
    }
    A mt[3], G[3];
    for (int c = 0; c < 3; ++c) mt[c] = s.m[c] / mu;
    A col = A(0);
    for (int a = 0; a < 3; ++a)
        for (int b = a + 1; b < 3; ++b) col += (mt[a] - mt[b]) * (mt[a] - mt[b]);
    const A sum_mt = mt[0] + mt[1] + mt[2];
    A Gm = A(0);
    for (int c = 0; c < 3; ++c) G[c] = A(2) * (A(3) * mt[c] - sum_mt), Gm += G[c] * s.m[c];
    out[0] = T(spa), out[1] = T(exp), out[2] = T(col);
    for (int c = 0; c < 3; ++c) {
        out[3 + c] = T(acc[2 + c] / s.sigma + dsigma * s.M[c] / A(3));
        out[6 + c] = T(dexp * s.M[c] / A(3));
        const A dm = scale_invariant && mu_free ? G[c] / mu - Gm / (A(3) * mu * mu) : G[c] / mu;
        out[9 + c] = T(dm * s.M[c]);
    }
}

}  // namespace rgs
