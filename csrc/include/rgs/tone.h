// The enhancement's tone `exposure` per pixel (retinexgs/model/tone.py): S_enh = srgb(s(k · lin(R̂ ∘ L̂))), a
// longer exposure, i.e. a gain k on the light before the camera's sRGB curve, with the highlights above the knee
// rolled off by s (highlight_shoulder there; knee >= 1: none, the curve's clip). Mirrors tone.py operation by
// operation (IEC 61966-2-1 constants), so float64 agrees with torch to rounding.
#pragma once
#include <cmath>
#include <cstdint>

#include "rgs/tone_curve.h"
#include "rgs/types.h"

namespace rgs {

// One channel of one pixel: reflectance r, light l, gain k, shoulder knee: the training curve's clipped form
// (rgs/tone_curve.h), so inference and training share one definition.
template <typename T>
RGS_HD T exposure_tone(T r, T l, T k, T knee) {
    return tone_curve(r * l, k, knee, kClip, kClip);
}

// Pixel p of an [P, C] image whose channels 0-2 are R̂ and 3-5 L̂; gain [G] (G = 1: one gain, 3: per channel,
// 9: a 3x3 matrix, row-major, rows the output channels: a white balance times the exposure, W·diag(k), applied to
// the linear light before the shoulder, as render --white-balance does; issue 53).
template <typename T>
RGS_HD void exposure_tone_pixel(int64_t p, int C, int G, const T* image, const T* gain, T knee, T* out) {
    const T* px = image + p * C;
    if (G == 9) {
        T lin[3];
        for (int c = 0; c < 3; ++c) lin[c] = curve_to_linear(px[c] * px[3 + c], kClip, (T*)nullptr);
        for (int c = 0; c < 3; ++c) {
            const T* row = gain + 3 * c;
            const T v = row[0] * lin[0] + row[1] * lin[1] + row[2] * lin[2];
            out[p * 3 + c] = curve_to_srgb(curve_shoulder(v, knee, (T*)nullptr), kClip, (T*)nullptr);
        }
        return;
    }
    for (int c = 0; c < 3; ++c) out[p * 3 + c] = exposure_tone(px[c], px[3 + c], gain[G == 1 ? 0 : c], knee);
}

}  // namespace rgs
