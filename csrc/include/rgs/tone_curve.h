// Training's tone curve per element, forward and backward: y = srgb_o(s(k · lin_i(x))), the exposure tone of
// retinexgs/model/tones/exposure.py (lin, a gain k in linear light, the highlight shoulder s, the sRGB curve) and the
// reconstruction's exposed photo of retinexgs/train/losses.py (s the identity there). In torch that chain is ~12
// elementwise operators each way, each a full pass over the image: at 12 MP the step is bound by those bytes
// (issue 65; notes 2026-11-29-redenoise-gpu-step-launches §5). Here it is one read and one write each way.
//
// The curves' three forms, as retinexgs/data/srgb.py has them (IEC 61966-2-1 constants, operation by operation, so
// float64 agrees with torch to rounding, gradients included):
//   kClip:     the value clamped to [0, 1] first (a camera's clip at white);
//   kOpen:     clamped at 0 only (clip=False: light past white keeps rising along the curve);
//   kExtended: no clamp (a raw view's encoding: negative values along the curve's linear segment);
//   kLinear:   (the output only) no sRGB curve: y = s(k · lin_i(x)), the light itself.
// A clamp passes the gradient where lo <= x <= hi, as torch.clamp's backward does.
#pragma once
#include <cmath>
#include <cstdint>

#include "rgs/types.h"

namespace rgs {

enum CurveForm : int { kClip = 0, kOpen = 1, kExtended = 2, kLinear = 3 };

// Each curve below returns its value and, where `grad` is not null, writes its derivative there (null: the value
// alone, as the forward and the inference tone ask, with no derivative's pow computed).

// x limited as `form` says; d(limited)/dx is 0 or 1.
template <typename T>
RGS_HD T curve_limit(T x, int form, T* grad) {
    T g = T(1);
    if (form != kExtended) {
        if (x < T(0)) x = T(0), g = T(0);
        else if (form == kClip && x > T(1)) x = T(1), g = T(0);  // NaN stays NaN (both false), as torch.clamp
    }
    if (grad) *grad = g;
    return x;
}

// sRGB -> linear light (srgb.py srgb_to_linear; the knee's value takes the linear branch).
template <typename T>
RGS_HD T curve_to_linear(T x, int form, T* grad) {
    T dlim;
    x = curve_limit(x, form, &dlim);
    if (x <= T(0.04045)) {
        if (grad) *grad = dlim / T(12.92);
        return x / T(12.92);
    }
    const T base = (x + T(0.055)) / T(1.055);
    if (grad) *grad = dlim * T(2.4) / T(1.055) * pow(base, T(1.4));
    return pow(base, T(2.4));
}

// Linear light -> sRGB (srgb.py linear_to_srgb), or v itself for the output form kLinear.
template <typename T>
RGS_HD T curve_to_srgb(T v, int form, T* grad) {
    if (form == kLinear) {
        if (grad) *grad = T(1);
        return v;
    }
    T dlim;
    v = curve_limit(v, form, &dlim);
    if (v <= T(0.0031308)) {
        if (grad) *grad = dlim * T(12.92);
        return T(12.92) * v;
    }
    const T root = pow(v, T(1.0 / 2.4));
    if (grad) *grad = dlim * T(1.055 / 2.4) * root / v;  // d/dv 1.055·v^(1/2.4) = 1.055/2.4 · v^(1/2.4 − 1)
    return T(1.055) * root - T(0.055);
}

// The highlight shoulder (curves.py highlight_shoulder): above the knee v rolls off towards white,
// knee + (1 − knee)(1 − e^(−(v − knee)/(1 − knee))), slope 1 at the knee; knee >= 1: v unchanged.
template <typename T>
RGS_HD T curve_shoulder(T v, T knee, T* grad) {
    if (knee >= T(1) || !(v > knee)) {
        if (grad) *grad = T(1);
        return v;
    }
    const T span = T(1) - knee;
    const T e = exp(-(v - knee) / span);
    if (grad) *grad = e;
    return knee + span * (T(1) - e);
}

// y = srgb_o(s(k · lin_i(x))).
template <typename T>
RGS_HD T tone_curve(T x, T k, T knee, int form_in, int form_out) {
    return curve_to_srgb(curve_shoulder(k * curve_to_linear(x, form_in, (T*)nullptr), knee, (T*)nullptr), form_out,
                         (T*)nullptr);
}

// dy/dx and dy/dk of tone_curve at (x, k).
template <typename T>
RGS_HD void tone_curve_grad(T x, T k, T knee, int form_in, int form_out, T* dx, T* dk) {
    T dlin, dshoulder, dsrgb;
    const T lin = curve_to_linear(x, form_in, &dlin);
    curve_to_srgb(curve_shoulder(k * lin, knee, &dshoulder), form_out, &dsrgb);
    const T dv = dsrgb * dshoulder;  // dy/d(k · lin)
    *dx = dv * k * dlin;
    *dk = dv * lin;
}

// tone_curve's value, and dy/dk into *dk, from one evaluation of the chain (no dy/dx: the lin curve's derivative
// and its pow are skipped).
template <typename T>
RGS_HD T tone_curve_value_dk(T x, T k, T knee, int form_in, int form_out, T* dk) {
    T dshoulder, dsrgb;
    const T lin = curve_to_linear(x, form_in, (T*)nullptr);
    const T y = curve_to_srgb(curve_shoulder(k * lin, knee, &dshoulder), form_out, &dsrgb);
    *dk = dsrgb * dshoulder * lin;
    return y;
}

// Element i of a tensor whose gain is per channel: channel (i / inner) % C (C = 1: one gain).
RGS_HD int64_t tone_curve_channel(int64_t i, int64_t C, int64_t inner) {
    return C == 1 ? 0 : (i / inner) % C;
}

// The backward of element i: grad_x[i] = g·dy/dx (if grad_x), grad_k[i] = g·dy/dk (if grad_k; summed per channel
// by the caller, so the reduction's order is torch's and the result deterministic).
template <typename T>
RGS_HD void tone_curve_backward_one(int64_t i, const T* x, const T* gain, int64_t C, int64_t inner, T knee,
                                    int form_in, int form_out, const T* grad_out, T* grad_x, T* grad_k) {
    T dx, dk;
    tone_curve_grad(x[i], gain[tone_curve_channel(i, C, inner)], knee, form_in, form_out, &dx, &dk);
    const T g = grad_out[i];
    if (grad_x) grad_x[i] = g * dx;
    if (grad_k) grad_k[i] = g * dk;
}

}  // namespace rgs
