// Adam's step on the CPU (rgs/adam.h): every tensor of every parameter group in one call, OpenMP over elements.
#include <omp.h>

#include "rgs/adam.h"
#include "rgs/kernels.h"

namespace rgs {

template <typename T>
void adam_step_cpu(const AdamTensor<T>* tensors, int count, int num_threads) {
    for (int k = 0; k < count; ++k) {
        const AdamTensor<T> t = tensors[k];
#pragma omp parallel for schedule(static) num_threads(num_threads)
        for (int64_t i = 0; i < t.n; ++i) adam_update(t, i);
    }
}

template void adam_step_cpu<float>(const AdamTensor<float>*, int, int);
template void adam_step_cpu<double>(const AdamTensor<double>*, int, int);

}  // namespace rgs
