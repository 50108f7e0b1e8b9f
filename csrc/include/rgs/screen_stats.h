// The screen-space statistics 3DGS's adaptive density control reads (Kerbl et al. 2023, §5.2), added per view
// after the backward: for every Gaussian seen in the view (both pixel radii > 0), the norm of its projected
// centre's gradient in NDC units (the pixel gradient times (W/2, H/2), the unit the densification threshold is
// defined in) and one more view that saw it; and, seen or not, the running maximum of its pixel radius. One fused
// pass instead of ~9 elementwise kernels (issue 65: they were 0.26 ms of a 4.5 ms fox-dark step, launch-bound).
// The accumulators are float32 whatever the gradient's precision (they are sums over views, read by a threshold).
#pragma once
#include <cmath>
#include <cstdint>

#include "rgs/types.h"

namespace rgs {

template <typename T>
RGS_HD void screen_stats_one(int64_t i,
                             const T* grad2d,        // [N, 2] dL/d(means2d), pixels
                             const int32_t* radii,   // [N, 2] pixel half extents; 0 = culled
                             T sx, T sy,             // W / 2, H / 2: pixels -> NDC
                             float* grad_accum,      // [N] += |NDC gradient| where seen
                             float* count,           // [N] += 1 where seen
                             float* max_radius) {    // [N] = max(., max(radii))
    const int32_t rx = radii[2 * i], ry = radii[2 * i + 1];
    if (rx > 0 && ry > 0) {
        const T gx = grad2d[2 * i] * sx, gy = grad2d[2 * i + 1] * sy;
        grad_accum[i] += float(sqrt(gx * gx + gy * gy));
        count[i] += 1.0f;
    }
    // A culled Gaussian's radii are (0, 0): the maximum stays (it starts at 0). NaN stays NaN, as torch.maximum.
    const float r = float(rx > ry ? rx : ry);
    if (r > max_radius[i]) max_radius[i] = r;
}

}  // namespace rgs
