// SSIM with a Gaussian window and zero ("same") padding, fused: the training loss's SSIM (3DGS's) in one forward and
// one backward pass instead of two depthwise convolutions each way and ~20 elementwise kernels (issue 65: at 360x640
// the filters alone were 0.74 ms of a 4.75 ms step).
//
// Per pixel q, with G the normalised window and zero outside the image (Wang et al. 2004, Eq. 13):
//   mx = G*x, my = G*y, exx = G*x², eyy = G*y², exy = G*xy,  sxx = exx - mx², syy = eyy - my², sxy = exy - mx·my,
//   S = A1·A2 / (B1·B2),  A1 = 2·mx·my + c1, A2 = 2·sxy + c2, B1 = mx² + my² + c1, B2 = sxx + syy + c2.
// The gradient with respect to x (y is the fixed target): S depends on x through mx, exx and exy only, so with
// g = dLoss/dS and the three partials of S at q,
//   dLoss/dx(p) = (G*(g·dS/dmx))(p) + 2·x(p)·(G*(g·dS/dexx))(p) + y(p)·(G*(g·dS/dexy))(p)
// (the window is symmetric and zero-padded, so the adjoint of the filter is the filter itself).
// The filtering loops differ by device (shared-memory tiles on the GPU, row strips on the CPU); the per-pixel
// math, the window and the padding rule live here.
#pragma once
#include <cstdint>

#include "rgs/types.h"

namespace rgs {

constexpr int kSsimMaxRadius = 7;  // windows of up to 15 taps (the loss uses 11)

// The separable window (taps w[0..2·radius], normalised, symmetric) and SSIM's two constants; passed by value,
// so on the GPU it sits in the kernel's parameter space.
template <typename T>
struct SsimWindow {
    int radius;
    T w[2 * kSsimMaxRadius + 1];
    T c1, c2;
};

// S at one pixel from its five moments, and (when d is not null) d[0..2] = dS/dmx, dS/dexx, dS/dexy there.
template <typename T>
RGS_HD T ssim_from_moments(T mx, T my, T exx, T eyy, T exy, T c1, T c2, T* d) {
    const T sxx = exx - mx * mx, syy = eyy - my * my, sxy = exy - mx * my;
    const T a1 = T(2) * mx * my + c1, a2 = T(2) * sxy + c2;
    const T b1 = mx * mx + my * my + c1, b2 = sxx + syy + c2;
    const T inv = T(1) / (b1 * b2);
    const T s = a1 * a2 * inv;
    if (d) {
        const T ds_dsxy = T(2) * a1 * inv;  // dS/dsxy; dexy moves sxy one for one
        const T ds_dsxx = -s / b2;          // dS/dsxx; dexx moves sxx one for one
        // mx moves A1 (2·my), B1 (2·mx), sxx (-2·mx) and sxy (-my)
        d[0] = T(2) * my * a2 * inv - T(2) * mx * s / b1 - T(2) * mx * ds_dsxx - my * ds_dsxy;
        d[1] = ds_dsxx;
        d[2] = ds_dsxy;
    }
    return s;
}

// dLoss/dx at a pixel from the three filtered maps G*(g·dS/dmx), G*(g·dS/dexx), G*(g·dS/dexy) there.
template <typename T>
RGS_HD T ssim_grad_x(T x, T y, T f_mx, T f_exx, T f_exy) {
    return f_mx + T(2) * x * f_exx + y * f_exy;
}

// The five per-pixel products the forward filters: x, y, x², y², xy.
template <typename T>
RGS_HD void ssim_products(T x, T y, T* v) {
    v[0] = x, v[1] = y, v[2] = x * x, v[3] = y * y, v[4] = x * y;
}

}  // namespace rgs
