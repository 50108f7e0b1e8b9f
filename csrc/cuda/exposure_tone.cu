// The exposure tone on the GPU (rgs/tone.h): one thread per pixel. One kernel instead of the ~20 elementwise ones
// torch launches for the two sRGB curves; the frame graph replays it every frame.
#include "common.cuh"
#include "rgs/kernels_cuda.h"
#include "rgs/tone.h"

namespace rgs {

constexpr int kToneThreads = 256;

template <typename T>
__global__ void __launch_bounds__(kToneThreads)
exposure_tone_kernel(int64_t P, int C, int G,
                     const T* __restrict__ image,  // [P, C], channels 0-2 R̂, 3-5 L̂
                     const T* __restrict__ gain,   // [G] device memory
                     T knee,                       // the highlight shoulder's knee (>= 1: none)
                     T* __restrict__ out) {        // [P, 3]
    const int64_t p = int64_t(blockIdx.x) * blockDim.x + threadIdx.x;
    if (p < P) exposure_tone_pixel(p, C, G, image, gain, knee, out);
}

template <typename T>
void exposure_tone_cuda(int64_t P, int C, int G, const T* image, const T* gain, double knee, T* out, void* stream) {
    if (P == 0) return;
    exposure_tone_kernel<T><<<num_blocks(P, kToneThreads), kToneThreads, 0, static_cast<cudaStream_t>(stream)>>>(
        P, C, G, image, gain, T(knee), out);
    RGS_CHECK_LAUNCH("exposure_tone");
}

template void exposure_tone_cuda<float>(int64_t, int, int, const float*, const float*, double, float*, void*);
template void exposure_tone_cuda<double>(int64_t, int, int, const double*, const double*, double, double*, void*);

}  // namespace rgs
