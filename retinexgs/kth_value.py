"""The k-th smallest value of a tensor along a dimension, fast on the GPU (issue 65).

torch's CUDA ``kthvalue`` selects within one thread block per slice: a 12 MP image's one slice took 70 ms on an H200,
and the exposure meter's white point (every training step), LR3M's illumination scale (twice a photo) and the view
statistics read such slices. ``topk``'s radix selection spreads over the GPU (0.3 ms at 12 MP):
experiments/notes/2026-11-30-meter-select-packed-render.md §2. The k-th smallest is then the largest of the k
smallest, or the least of the n - k + 1 largest: the same element as ``kthvalue``'s, ties included.
"""
from __future__ import annotations

from torch import Tensor

__all__ = ["kth_smallest"]


def kth_smallest(x: Tensor, k: int, dim: int = -1) -> Tensor:
    """The k-th smallest value (1-based, as ``torch.kthvalue``) of ``x`` along ``dim``, that dimension removed: the
    value ``x.kthvalue(k, dim).values`` gives. CUDA tensors select by ``topk`` (no host sync: graph-capturable), the
    CPU keeps ``kthvalue`` (its quickselect is the quicker there)."""
    n = x.shape[dim]
    if not 1 <= k <= n:
        raise ValueError(f"kth_smallest: k must lie in 1..{n} (the size along dim {dim}), got {k}")
    if not x.is_cuda:
        return x.kthvalue(k, dim=dim).values
    return by_topk(x, k, dim)


def by_topk(x: Tensor, k: int, dim: int = -1) -> Tensor:
    """:func:`kth_smallest` through ``topk`` on any device (the GPU's form; public for its CPU tests)."""
    n = x.shape[dim]
    if k <= n - k + 1:  # the fewer of the two selections
        return x.topk(k, dim=dim, largest=False, sorted=False).values.amax(dim=dim)
    return x.topk(n - k + 1, dim=dim, largest=True, sorted=False).values.amin(dim=dim)
