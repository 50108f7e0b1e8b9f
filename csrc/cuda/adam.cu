// Adam's step on the GPU (rgs/adam.h): one launch for up to kAdamBatch parameter tensors of any groups, one thread
// per element. torch's fused Adam launches once per group, and its 64k-element chunks give a 57k-Gaussian tensor
// only a few blocks: 8 launches of ~44 µs each on fox-dark (issue 65), where the bytes need ~30 µs in all.
#include "common.cuh"
#include "rgs/adam.h"
#include "rgs/kernels_cuda.h"

namespace rgs {

constexpr int kAdamThreads = 256;

// The batch by value (kernel parameters): no host-to-device copy, nothing to keep alive after the launch.
template <typename T>
struct AdamBatch {
    AdamTensor<T> t[kAdamBatch];
    int64_t block_end[kAdamBatch];  // exclusive prefix sum of each tensor's blocks
    int count;
};

template <typename T>
__global__ void __launch_bounds__(kAdamThreads) adam_kernel(const AdamBatch<T> batch) {
    const int64_t block = blockIdx.x;
    int k = 0;
    while (k + 1 < batch.count && block >= batch.block_end[k]) ++k;
    const int64_t first = k == 0 ? 0 : batch.block_end[k - 1];
    const int64_t i = (block - first) * kAdamThreads + threadIdx.x;
    if (i < batch.t[k].n) adam_update(batch.t[k], i);
}

template <typename T>
void adam_step_cuda(const AdamTensor<T>* tensors, int count, void* stream) {
    int k = 0;
    while (k < count) {
        AdamBatch<T> batch{};
        batch.count = 0;
        int64_t blocks = 0;
        for (; k < count && batch.count < kAdamBatch; ++k) {
            if (tensors[k].n == 0) continue;
            batch.t[batch.count] = tensors[k];
            blocks += num_blocks(tensors[k].n, kAdamThreads);
            batch.block_end[batch.count] = blocks;
            ++batch.count;
        }
        if (batch.count == 0) continue;
        adam_kernel<T><<<blocks, kAdamThreads, 0, static_cast<cudaStream_t>(stream)>>>(batch);
        RGS_CHECK_LAUNCH("adam_step");
    }
}

template void adam_step_cuda<float>(const AdamTensor<float>*, int, void*);
template void adam_step_cuda<double>(const AdamTensor<double>*, int, void*);

}  // namespace rgs
