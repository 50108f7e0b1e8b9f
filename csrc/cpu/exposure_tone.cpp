// The exposure tone on the CPU (rgs/tone.h): one OpenMP iteration per pixel.
#include <omp.h>

#include "rgs/kernels.h"
#include "rgs/tone.h"

namespace rgs {

template <typename T>
void exposure_tone_cpu(int64_t P, int C, int G, const T* image, const T* gain, double knee, T* out, int num_threads) {
    const T k = T(knee);
#pragma omp parallel for schedule(static) num_threads(num_threads)
    for (int64_t p = 0; p < P; ++p) exposure_tone_pixel(p, C, G, image, gain, k, out);
}

template void exposure_tone_cpu<float>(int64_t, int, int, const float*, const float*, double, float*, int);
template void exposure_tone_cpu<double>(int64_t, int, int, const double*, const double*, double, double*, int);

}  // namespace rgs
