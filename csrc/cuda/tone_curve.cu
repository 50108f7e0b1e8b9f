// Training's tone curve on the GPU (rgs/tone_curve.h): one thread per element, one read and one write each way
// where torch's chain makes ~12 passes (issue 65: at 12 MP the step is bound by those bytes).
#include "common.cuh"
#include "rgs/kernels_cuda.h"
#include "rgs/tone_curve.h"

namespace rgs {

constexpr int kCurveThreads = 256;

template <typename T>
__global__ void __launch_bounds__(kCurveThreads)
tone_curve_forward_kernel(int64_t n, const T* __restrict__ x, const T* __restrict__ gain, int64_t C, int64_t inner,
                          T knee, int form_in, int form_out, T* __restrict__ y) {
    const int64_t i = int64_t(blockIdx.x) * blockDim.x + threadIdx.x;
    if (i < n) y[i] = tone_curve(x[i], gain[tone_curve_channel(i, C, inner)], knee, form_in, form_out);
}

template <typename T>
__global__ void __launch_bounds__(kCurveThreads)
tone_curve_backward_kernel(int64_t n, const T* __restrict__ x, const T* __restrict__ gain, int64_t C, int64_t inner,
                           T knee, int form_in, int form_out, const T* __restrict__ grad_out, T* __restrict__ grad_x,
                           T* __restrict__ grad_k) {
    const int64_t i = int64_t(blockIdx.x) * blockDim.x + threadIdx.x;
    if (i < n) tone_curve_backward_one(i, x, gain, C, inner, knee, form_in, form_out, grad_out, grad_x, grad_k);
}

template <typename T>
void tone_curve_forward_cuda(int64_t n, const T* x, const T* gain, int64_t C, int64_t inner, double knee, int form_in,
                             int form_out, T* y, void* stream) {
    if (n == 0) return;
    tone_curve_forward_kernel<T><<<num_blocks(n, kCurveThreads), kCurveThreads, 0, static_cast<cudaStream_t>(stream)>>>(
        n, x, gain, C, inner, T(knee), form_in, form_out, y);
    RGS_CHECK_LAUNCH("tone_curve_forward");
}

template <typename T>
void tone_curve_backward_cuda(int64_t n, const T* x, const T* gain, int64_t C, int64_t inner, double knee,
                              int form_in, int form_out, const T* grad_out, T* grad_x, T* grad_k, void* stream) {
    if (n == 0) return;
    tone_curve_backward_kernel<T><<<num_blocks(n, kCurveThreads), kCurveThreads, 0,
                                    static_cast<cudaStream_t>(stream)>>>(n, x, gain, C, inner, T(knee), form_in,
                                                                         form_out, grad_out, grad_x, grad_k);
    RGS_CHECK_LAUNCH("tone_curve_backward");
}

#define RGS_INSTANTIATE(T)                                                                                        \
    template void tone_curve_forward_cuda<T>(int64_t, const T*, const T*, int64_t, int64_t, double, int, int, T*, \
                                             void*);                                                              \
    template void tone_curve_backward_cuda<T>(int64_t, const T*, const T*, int64_t, int64_t, double, int, int,    \
                                              const T*, T*, T*, void*);
RGS_INSTANTIATE(float)
RGS_INSTANTIATE(double)
#undef RGS_INSTANTIATE

}  // namespace rgs
