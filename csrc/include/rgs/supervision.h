// RetinexGS's per-pixel training losses in one pass each way (retinexgs/train/fused_loss.py): the 2D priors'
// supervision and the reconstruction (paper Eq. 4), L_TV of the reflectance (Eq. 5) and the depth prior's edge-aware
// smoothness. In torch these are ~200 small kernels a step inside the loss graph (forward and backward) that move
// ~2.5 kB a pixel: launch-bound at 360x640, bytes-bound at 12 MP (issue 65). Here the forward reads a pixel's render
// and targets once, writes the SSIM's two 9-channel stacks and 12 block sums; the backward reads them once more and
// writes the render's gradient.
//
// Per pixel p (HWC inputs: image [H, W, Ci], Ci = 6: R̂, L̂; Ci = 8: + the depth prior's depth Σwz and alpha Σw;
// packed [H, W, K], K = 7: S, R, L (1 channel); K = 9: + the edge weights wx, wy, zero in the last column / row):
//   x9 = [R̂', L̂, e(R̂∘L̂)], y9 = [R', L, L, L, e(S)]  (CHW; the SSIM's pairs, e the exposure or the identity;
//   X' = X − (1−κ)·mean_c X, the R prior's pair with its luma scaled by κ = loss.raw.r_prior_luma, 1: X itself)
//   sums (kSum*): the L1 numerators Σ c·|R̂' − R'|, Σ c·|L̂ − L| (c the raw priors' confidence, else 1), the
//   reconstruction's numerator (Σ|R̂∘L̂ − S|, Σ|e(R̂∘L̂) − e(S)|, or a raw scene's Σ w·(g(lin(R̂∘L̂) − lin(S)))² with
//   its Σ w), L_TV's forward differences, and the depth prior's Σ disparity, Σ covered, Σ |Δ disparity|·w·m, Σ m.
// The means and ratios are formed from the sums by the caller. The gradient of every sum is defined, except of the
// counts and of Σ w (the weights are constants of the step, as torch's no_grad weights), which have none.
#pragma once
#include <cmath>
#include <cstdint>

#include "rgs/tone_curve.h"
#include "rgs/types.h"

namespace rgs {

// The reconstruction's L1 form.
enum RecForm : int { kRecPlain = 0, kRecExposed = 1, kRecNoise = 2, kRecRelative = 3 };

enum SupervisionSum : int {
    kSumR = 0, kSumL, kSumRec, kSumW, kSumTvX, kSumTvY, kSumDisp, kSumCov, kSumDx, kSumMx, kSumDy, kSumMy, kSums
};

template <typename T>
struct SupervisionArgs {
    int H, W;
    int ci, k;             // channels of image (6 or 8) and packed (7 or 9); 8 and 9 go together (depth prior)
    int rec_form;          // RecForm
    int s_form;            // the curve form of S's exposure and linear light: kOpen (photos) or kExtended (raw)
    const T* ssim_gain;    // [1] on the device: the SSIM's pair exposed at this gain; null: R̂∘L̂ and S as they are
    const T* lin_gain;     // [1]: kRecExposed's gain, or the linear term's g (kRecNoise / kRecRelative)
    const T* noise_a;      // [3]: a raw view's noise var = a·y + b per channel (kRecNoise)
    const T* noise_b;      // [3]
    const T* conf;         // [H, W]: the priors' L1 weight, or null (1)
    T relative_eps;        // RawNeRF's ε (kRecRelative)
    T min_alpha, depth_eps;
    T r_luma;              // κ: the share of R̂'s luma (channel mean) the R prior compares (1: all of it)
};

template <typename T>
RGS_HD T sup_sign(T v) { return T(v > T(0)) - T(v < T(0)); }  // torch.sgn: 0 at 0, the abs's backward

// The exposure e(v) = srgb(g · lin(v)) of form `form` in and out (train/losses.py exposed); dv: de/dv (or null).
template <typename T>
RGS_HD T sup_exposed(T v, T g, int form, T* dv) {
    if (dv) {
        T dk;
        tone_curve_grad(v, g, T(1), form, form, dv, &dk);
    }
    return tone_curve(v, g, T(1), form, form);
}

// The linear term's weight at the render's linear light x (train/losses.py linear_weights, unnormalised).
template <typename T>
RGS_HD T sup_lin_weight(const SupervisionArgs<T>& a, int c, T x, T g) {
    const T xs = x > T(0) ? x : T(0);
    if (a.rec_form == kRecNoise) return T(1) / ((a.noise_a[c] * xs + a.noise_b[c]) * (g * g));
    const T d = g * xs + a.relative_eps;
    return T(1) / (d * d);
}

// The depth prior's disparity at pixel p (losses.depth_smoothness_loss, before its normalisation): α / max(z, ε)
// where α >= min_alpha, else 0; *covered the mask.
template <typename T>
RGS_HD T sup_disparity(const SupervisionArgs<T>& a, const T* image, int64_t p, T* covered) {
    const T z = image[p * a.ci + 6], alpha = image[p * a.ci + 7];
    const bool cov = alpha >= a.min_alpha;
    *covered = T(cov);
    return cov ? alpha / (z > a.depth_eps ? z : a.depth_eps) : T(0);
}

// What both passes read of pixel p: its place, its render and targets, the priors' weight and the two gains.
template <typename T>
struct SupPixel {
    int64_t HW;
    int x, y;
    const T* im;  // image[p, :]
    const T* pk;  // packed[p, :]
    T c, Lp, gs, gl;
    T dRh, dR;  // (1−κ)·mean_c R̂ and (1−κ)·mean_c R: what the R prior's pair leaves out of each channel

    RGS_HD SupPixel(const SupervisionArgs<T>& a, int64_t p, const T* image, const T* packed)
        : HW(int64_t(a.H) * a.W), x(int(p % a.W)), y(int(p / a.W)), im(image + p * a.ci), pk(packed + p * a.k),
          c(a.conf ? a.conf[p] : T(1)), Lp(pk[6]), gs(a.ssim_gain ? a.ssim_gain[0] : T(1)),
          gl(a.lin_gain ? a.lin_gain[0] : T(1)),
          dRh((T(1) - a.r_luma) * ((im[0] + im[1] + im[2]) / T(3))),
          dR((T(1) - a.r_luma) * ((pk[3] + pk[4] + pk[5]) / T(3))) {}
};

// Pixel p's forward: its x9 / y9 entries and its share of the sums (added to s[kSums]).
template <typename T>
RGS_HD void supervision_forward_pixel(const SupervisionArgs<T>& a, int64_t p, const T* image, const T* packed,
                                      T* x9, T* y9, T* s) {
    const SupPixel<T> q(a, p, image, packed);
    const int64_t HW = q.HW;
    const int x = q.x, y = q.y;
    const T *im = q.im, *pk = q.pk;
    const T c = q.c, Lp = q.Lp, gs = q.gs, gl = q.gl;
    RGS_UNROLL
    for (int ch = 0; ch < 3; ++ch) {
        const T Rh = im[ch], Lh = im[3 + ch], S = pk[ch], R = pk[3 + ch];
        const T Rh_p = Rh - q.dRh, R_p = R - q.dR;  // the R prior's pair
        s[kSumR] += c * fabs(Rh_p - R_p);
        s[kSumL] += c * fabs(Lh - Lp);
        const T rec = Rh * Lh;
        const T xe = a.ssim_gain ? sup_exposed(rec, gs, int(kOpen), (T*)nullptr) : rec;
        const T ye = a.ssim_gain ? sup_exposed(S, gs, a.s_form, (T*)nullptr) : S;
        x9[ch * HW + p] = Rh_p, x9[(3 + ch) * HW + p] = Lh, x9[(6 + ch) * HW + p] = xe;
        y9[ch * HW + p] = R_p, y9[(3 + ch) * HW + p] = Lp, y9[(6 + ch) * HW + p] = ye;
        if (a.rec_form == kRecPlain) {
            s[kSumRec] += fabs(rec - S);
        } else if (a.rec_form == kRecExposed) {
            s[kSumRec] += fabs(sup_exposed(rec, gl, int(kOpen), (T*)nullptr) - sup_exposed(S, gl, a.s_form, (T*)nullptr));
        } else {
            const T lx = curve_to_linear(rec, int(kOpen), (T*)nullptr), ly = curve_to_linear(S, a.s_form, (T*)nullptr);
            const T w = sup_lin_weight(a, ch, lx, gl), e = gl * (lx - ly);
            s[kSumRec] += w * e * e;
            s[kSumW] += w;
        }
        if (x + 1 < a.W) s[kSumTvX] += fabs(image[(p + 1) * a.ci + ch] - Rh);
        if (y + 1 < a.H) s[kSumTvY] += fabs(image[(p + a.W) * a.ci + ch] - Rh);
    }
    if (a.ci == 8) {
        T cov;
        const T d = sup_disparity(a, image, p, &cov);
        s[kSumDisp] += d;
        s[kSumCov] += cov;
        if (x + 1 < a.W) {
            T cq;
            const T dq = sup_disparity(a, image, p + 1, &cq);
            const T m = cov * cq;
            s[kSumDx] += fabs(dq - d) * pk[a.k - 2] * m;
            s[kSumMx] += m;
        }
        if (y + 1 < a.H) {
            T cq;
            const T dq = sup_disparity(a, image, p + a.W, &cq);
            const T m = cov * cq;
            s[kSumDy] += fabs(dq - d) * pk[a.k - 1] * m;
            s[kSumMy] += m;
        }
    }
}

// Pixel p's backward: grad_image[p, :] from g_x9 (the SSIM's gradient on x9; null: none) and g_sums [kSums].
template <typename T>
RGS_HD void supervision_backward_pixel(const SupervisionArgs<T>& a, int64_t p, const T* image, const T* packed,
                                       const T* g_x9, const T* g, T* grad_image) {
    const SupPixel<T> q(a, p, image, packed);
    const int64_t HW = q.HW;
    const int x = q.x, y = q.y;
    const T *im = q.im, *pk = q.pk;
    const T c = q.c, Lp = q.Lp, gs = q.gs, gl = q.gl;
    T* gi = grad_image + p * a.ci;
    // The R prior's gradient on its pair R̂' = R̂ − (1−κ)·mean_c R̂, then through that map: d/dR̂ = g' − (1−κ)·mean_c g'.
    T gp[3];
    RGS_UNROLL
    for (int ch = 0; ch < 3; ++ch) {
        gp[ch] = g[kSumR] * c * sup_sign((im[ch] - q.dRh) - (pk[3 + ch] - q.dR));
        if (g_x9) gp[ch] += g_x9[ch * HW + p];
    }
    const T gp_shift = (T(1) - a.r_luma) * ((gp[0] + gp[1] + gp[2]) / T(3));
    RGS_UNROLL
    for (int ch = 0; ch < 3; ++ch) {
        const T Rh = im[ch], Lh = im[3 + ch], S = pk[ch];
        const T rec = Rh * Lh;
        T gR = gp[ch] - gp_shift;
        T gL = g[kSumL] * c * sup_sign(Lh - Lp);
        T grec = T(0);
        if (g_x9) {
            gL += g_x9[(3 + ch) * HW + p];
            T de = T(1);
            if (a.ssim_gain) sup_exposed(rec, gs, int(kOpen), &de);
            grec += g_x9[(6 + ch) * HW + p] * de;
        }
        if (a.rec_form == kRecPlain) {
            grec += g[kSumRec] * sup_sign(rec - S);
        } else if (a.rec_form == kRecExposed) {
            T de;
            const T xe = sup_exposed(rec, gl, int(kOpen), &de);
            grec += g[kSumRec] * sup_sign(xe - sup_exposed(S, gl, a.s_form, (T*)nullptr)) * de;
        } else {
            T dlin;
            const T lx = curve_to_linear(rec, int(kOpen), &dlin), ly = curve_to_linear(S, a.s_form, (T*)nullptr);
            const T w = sup_lin_weight(a, ch, lx, gl);
            grec += g[kSumRec] * w * T(2) * gl * gl * (lx - ly) * dlin;
        }
        gR += grec * Lh;
        gL += grec * Rh;
        // L_TV: |R̂(q) − R̂(p)| over the pairs (p, right), (left, p), (p, down), (up, p).
        if (x + 1 < a.W) gR -= g[kSumTvX] * sup_sign(image[(p + 1) * a.ci + ch] - Rh);
        if (x > 0) gR += g[kSumTvX] * sup_sign(Rh - image[(p - 1) * a.ci + ch]);
        if (y + 1 < a.H) gR -= g[kSumTvY] * sup_sign(image[(p + a.W) * a.ci + ch] - Rh);
        if (y > 0) gR += g[kSumTvY] * sup_sign(Rh - image[(p - a.W) * a.ci + ch]);
        gi[ch] = gR;
        gi[3 + ch] = gL;
    }
    if (a.ci == 8) {
        T cov, cq;
        const T d = sup_disparity(a, image, p, &cov);
        T gd = g[kSumDisp];
        // The pairs (p, right) and (p, down) carry p's edge weights; (left, p) and (up, p) their neighbour's.
        if (x + 1 < a.W) {
            const T dq = sup_disparity(a, image, p + 1, &cq);
            gd -= g[kSumDx] * sup_sign(dq - d) * pk[a.k - 2] * cov * cq;
        }
        if (x > 0) {
            const T dq = sup_disparity(a, image, p - 1, &cq);
            gd += g[kSumDx] * sup_sign(d - dq) * packed[(p - 1) * a.k + a.k - 2] * cov * cq;
        }
        if (y + 1 < a.H) {
            const T dq = sup_disparity(a, image, p + a.W, &cq);
            gd -= g[kSumDy] * sup_sign(dq - d) * pk[a.k - 1] * cov * cq;
        }
        if (y > 0) {
            const T dq = sup_disparity(a, image, p - a.W, &cq);
            gd += g[kSumDy] * sup_sign(d - dq) * packed[(p - a.W) * a.k + a.k - 1] * cov * cq;
        }
        // disparity = α / max(z, ε) · covered (the mask has no gradient; clamp_min passes it where z >= ε)
        const T z = im[6], alpha = im[7];
        const T zc = z > a.depth_eps ? z : a.depth_eps;
        gi[6] = (cov != T(0) && z >= a.depth_eps) ? -gd * alpha / (zc * zc) : T(0);
        gi[7] = cov != T(0) ? gd / zc : T(0);
    }
}

}  // namespace rgs
