// Adam's update of one element (Kingma & Ba 2015, Algorithm 1, in torch.optim.Adam's arrangement, no weight decay):
//   m ← β1 m + (1 − β1) g,  v ← β2 v + (1 − β2) g²,  p ← p − (lr / (1 − β1^t)) · m / (√v / √(1 − β2^t) + ε)
// The host passes step_size = lr / (1 − β1^t) and bc2_sqrt = √(1 − β2^t) per tensor (t: that tensor's step count),
// so the device does no powers. Shared by the CPU loop and the CUDA kernel (one kernel for every parameter group).
#pragma once

#include <cmath>
#include <cstdint>

#include "rgs/types.h"

namespace rgs {

// Tensors per CUDA launch (they travel as kernel parameters: 32 × 104 bytes in double, under the 4 KB limit).
constexpr int kAdamBatch = 32;

// One parameter tensor of an Adam step: its contiguous parameter, gradient and moments, and its group's constants.
template <typename T>
struct AdamTensor {
    T* param;
    const T* grad;
    T* exp_avg;
    T* exp_avg_sq;
    int64_t n;
    T beta1, beta2, one_minus_beta1, one_minus_beta2, eps, step_size, bc2_sqrt;  // 1 − β: rounded once, in double
};

template <typename T>
RGS_HD void adam_update(const AdamTensor<T>& t, int64_t i) {
    const T g = t.grad[i];
    const T m = t.beta1 * t.exp_avg[i] + t.one_minus_beta1 * g;
    const T v = t.beta2 * t.exp_avg_sq[i] + t.one_minus_beta2 * g * g;
    t.exp_avg[i] = m;
    t.exp_avg_sq[i] = v;
    const T denom = sqrt(v) / t.bc2_sqrt + t.eps;
    t.param[i] -= t.step_size * m / denom;
}

}  // namespace rgs
