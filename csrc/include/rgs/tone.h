// The enhancement's tone `exposure` per pixel (retinexgs/model/tone.py): S_enh = srgb(s(k · lin(R̂ ∘ L̂))), a
// longer exposure, i.e. a gain k on the light before the camera's sRGB curve, with the highlights above the knee
// rolled off by s (highlight_shoulder there; knee >= 1: none, the curve's clip). Mirrors tone.py operation by
// operation (IEC 61966-2-1 constants), so float64 agrees with torch to rounding.
#pragma once
#include <cmath>
#include <cstdint>

#include "rgs/types.h"

namespace rgs {

// clamp to [0, 1]; a NaN stays NaN (as torch.clamp), so a broken render is not painted black.
template <typename T>
RGS_HD T clamp01(T x) { return x < T(0) ? T(0) : (x > T(1) ? T(1) : x); }

template <typename T>
RGS_HD T srgb_to_linear(T x) {
    x = clamp01(x);
    return x <= T(0.04045) ? x / T(12.92) : pow((x + T(0.055)) / T(1.055), T(2.4));
}

template <typename T>
RGS_HD T linear_to_srgb(T x) {
    x = clamp01(x);
    return x <= T(0.0031308) ? T(12.92) * x : T(1.055) * pow(x, T(1.0 / 2.4)) - T(0.055);
}

// Linear light v above the knee rolled off towards white: knee + (1 - knee)(1 - e^(-(v - knee) / (1 - knee))),
// slope 1 at the knee (a camera's shoulder); below it, or with knee >= 1, v unchanged.
template <typename T>
RGS_HD T highlight_shoulder(T v, T knee) {
    if (knee >= T(1) || !(v > knee)) return v;
    const T span = T(1) - knee;
    return knee + span * (T(1) - exp(-(v - knee) / span));
}

// One channel of one pixel: reflectance r, light l, gain k, shoulder knee.
template <typename T>
RGS_HD T exposure_tone(T r, T l, T k, T knee) {
    return linear_to_srgb(highlight_shoulder(k * srgb_to_linear(r * l), knee));
}

// Pixel p of an [P, C] image whose channels 0-2 are R̂ and 3-5 L̂; gain [G] (G = 1: one gain, 3: per channel,
// 9: a 3x3 matrix, row-major, rows the output channels: a white balance times the exposure, W·diag(k), applied to
// the linear light before the shoulder, as render --white-balance does; issue 53).
template <typename T>
RGS_HD void exposure_tone_pixel(int64_t p, int C, int G, const T* image, const T* gain, T knee, T* out) {
    const T* px = image + p * C;
    if (G == 9) {
        T lin[3];
        for (int c = 0; c < 3; ++c) lin[c] = srgb_to_linear(px[c] * px[3 + c]);
        for (int c = 0; c < 3; ++c) {
            const T* row = gain + 3 * c;
            out[p * 3 + c] = linear_to_srgb(highlight_shoulder(row[0] * lin[0] + row[1] * lin[1] + row[2] * lin[2], knee));
        }
        return;
    }
    for (int c = 0; c < 3; ++c) out[p * 3 + c] = exposure_tone(px[c], px[3 + c], gain[G == 1 ? 0 : c], knee);
}

}  // namespace rgs
