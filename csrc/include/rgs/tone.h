// The enhancement's tone `exposure` per pixel (retinexgs/model/tone.py): S_enh = srgb(k · lin(R̂ ∘ L̂)), a longer
// exposure, i.e. a gain k on the light before the camera's sRGB curve. Mirrors srgb_to_linear / linear_to_srgb
// there operation by operation (IEC 61966-2-1 constants), so float64 agrees with torch to rounding.
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

// One channel of one pixel: reflectance r, light l, gain k.
template <typename T>
RGS_HD T exposure_tone(T r, T l, T k) { return linear_to_srgb(k * srgb_to_linear(r * l)); }

// Pixel p of an [P, C] image whose channels 0-2 are R̂ and 3-5 L̂; gain [G] (G = 1: one gain, 3: per channel).
template <typename T>
RGS_HD void exposure_tone_pixel(int64_t p, int C, int G, const T* image, const T* gain, T* out) {
    const T* px = image + p * C;
    for (int c = 0; c < 3; ++c) out[p * 3 + c] = exposure_tone(px[c], px[3 + c], gain[G == 1 ? 0 : c]);
}

}  // namespace rgs
