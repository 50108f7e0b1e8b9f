"""retinexgs.kth_value: the k-th smallest value by topk (the GPU's form) is kthvalue's, ties and both selection
directions included; bad k is refused with one line; on a GPU the CUDA form against the CPU's kthvalue."""
import pytest
import torch

from retinexgs.kth_value import by_topk, kth_smallest


def tensors():
    g = torch.Generator().manual_seed(4)
    yield torch.rand(1001, generator=g)                                      # distinct values
    yield torch.randint(0, 7, (500,), generator=g).float()                   # heavy ties
    yield torch.rand(3, 257, generator=g, dtype=torch.float64)               # rows
    yield torch.rand(400, 3, generator=g).pow(3)                             # columns (dim=0, as black_lift)
    yield torch.tensor([2.0])                                                # one value


@pytest.mark.parametrize("case", range(5))
def test_topk_form_is_kthvalue(case):
    x = list(tensors())[case]
    for dim in range(x.dim()):
        n = x.shape[dim]
        for k in sorted({1, min(2, n), n // 3 + 1, n // 2 + 1, max(1, n - 1), n}):
            want = x.kthvalue(k, dim=dim).values
            assert torch.equal(by_topk(x, k, dim), want), (case, dim, k)
            assert torch.equal(kth_smallest(x, k, dim), want), (case, dim, k)


def test_lower_median_is_torchs_median():
    # estimate_noise_sigma's median as a k-th value: torch.median is the lower middle value, odd and even n.
    g = torch.Generator().manual_seed(6)
    for n in (1, 2, 9, 10, 1000):
        x = torch.randint(0, 5, (2, n), generator=g).float() + torch.rand(2, n, generator=g).round()
        assert torch.equal(by_topk(x, (n + 1) // 2, 1), x.median(dim=1).values), n


def test_bad_k_is_refused():
    x = torch.rand(10)
    for k in (0, 11, -1):
        with pytest.raises(ValueError, match="k must lie in 1..10"):
            kth_smallest(x, k)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU")
def test_cuda_form_is_the_cpus_kthvalue():
    g = torch.Generator().manual_seed(5)
    for x in (torch.rand(300_000, generator=g), torch.randint(0, 50, (2, 70_000), generator=g).float()):
        for k in (1, 7, x.shape[-1] // 2, x.shape[-1] - 3, x.shape[-1]):
            got = kth_smallest(x.cuda(), k).cpu()
            assert torch.equal(got, x.kthvalue(k).values), k
