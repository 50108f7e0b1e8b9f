"""CUDA graphs of the training step (the step is launch-bound: a few ms of GPU work behind ~500 small kernel
launches). Two parts are captured; the rasterizer (its binning needs a data-dependent size), L_SH, density
statistics and the optimiser stay eager.

:class:`LossGraphs`: the image losses, forward and backward of every loss term that depends only on the
rendered image (all but L_SH), replayed as one graph launch instead of a few hundred kernel launches.

A captured graph takes the rendered image [H,W,C] and the view's packed targets (S, and the 2D priors R, L;
or the baselines' target) in static buffers (with the depth prior on, the image carries the render's depth and
alpha as two more channels, and the targets the prior's edge weights: its term is graphed too), and leaves in
static buffers: the gradient of the image losses' sum with respect to the image, the gradients of the networks
that live entirely inside the loss (the EnhancementNet, while L_enhance is on), and every term's value. The
trainer copies the image in (one copy), feeds the image gradient to the rasterizer's backward, and hands the
network gradients to the optimiser.

One graph per (image shape, dtype, targets' shape, enhancement on/off): the EnhancementNet and its losses
switch on at a step of the schedule, views may differ in size. The loss function is the trainer's eager one,
traced by capture, so the graphed values and gradients are the eager ones (tests/test_cuda_step.py compares
them for every shipped config). Only CUDA tensors are captured; anything else, a capture that fails, or more
than ``max_graphs`` shapes, runs eagerly (the caller's fallback): the config switch ``train.cuda_graphs``
turns graphs off altogether.

:class:`ChannelGraphs`: the per-Gaussian channels (SH colour + the illumination MLP), forward and backward
as two graph launches, rebuilt when the Gaussians change (densification) or the SH degree grows.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Dict, List, Optional, Tuple

import torch
from torch import Tensor
from torch.profiler import record_function

from retinexgs.model.retinex_model import GaussianChannels
from retinexgs.render import cuda_graphs

# (image [H,W,C], packed targets [H,W,K], enhancement on) -> (the image losses' sum, {name: term}).
LossFn = Callable[[Tensor, Tensor, bool], Tuple[Tensor, Dict[str, Tensor]]]


@dataclass
class GraphResult:
    """What one replay leaves (static buffers: valid until the next replay of the same graph)."""

    grad_image: Tensor              # [H,W,C] d(image losses)/d(image)
    names: Tuple[str, ...]          # the image loss terms, in the loss function's order
    values: Tensor                  # [1 + len(names)]: the image losses' sum, then each term (detached)
    param_grads: List[Tensor]       # gradients of ``params`` (empty while the enhancement is off)


@dataclass
class _Captured:
    graph: "torch.cuda.CUDAGraph"
    image: Tensor
    packed: Tensor
    result: GraphResult


class LossGraphs:
    """Captures and replays :data:`LossFn` per input shape.

    Args:
        loss_fn: the image part of the loss; must not sync with the host (no ``.item()``, no data-dependent
            shapes) and must read only ``image``, ``packed`` and long-lived tensors (parameters, buffers).
        params: the parameters that get gradients inside the graph while the enhancement is on (their
            tensors must stay the same objects: the optimiser updates them in place).
        max_graphs: shapes captured at most; further shapes run eagerly.
        warmup: eager iterations on a side stream before capture (library handles, workspaces, caches).
        emulate: on non-CUDA tensors run the same forward + backward eagerly each call (no capture) and hand
            back the same kind of result: the trainer's graphed path on the CPU, for tests and op counts.
    """

    def __init__(self, loss_fn: LossFn, params: List[Tensor], max_graphs: int = 8, warmup: int = 2,
                 emulate: bool = False) -> None:
        self.loss_fn, self.params = loss_fn, list(params)
        self.max_graphs, self.warmup = int(max_graphs), int(warmup)
        self.emulate = bool(emulate)
        self._graphs: Dict[tuple, _Captured] = {}
        self._failed: Dict[tuple, str] = {}

    def supports(self, image: Tensor, packed: Tensor) -> bool:
        return image.is_cuda and packed.is_cuda and image.device == packed.device

    def _key(self, image: Tensor, packed: Tensor, enhance: bool) -> tuple:
        return (tuple(image.shape), image.dtype, tuple(packed.shape), packed.dtype, image.device, bool(enhance))

    def _step(self, image: Tensor, packed: Tensor, enhance: bool) -> GraphResult:
        """One forward + backward of the image losses on the static inputs (what is captured)."""
        total, terms = self.loss_fn(image, packed, enhance)
        params = self.params if enhance else []
        grads = torch.autograd.grad(total, [image] + params, allow_unused=True)
        if any(g is None for g in grads):  # a graph cannot give None some steps and a tensor on others
            raise RuntimeError("a parameter of the graphed loss gets no gradient")
        values = torch.stack([total.detach()] + [t.detach() for t in terms.values()])
        return GraphResult(grads[0], tuple(terms), values, list(grads[1:]))

    def _capture(self, image: Tensor, packed: Tensor, enhance: bool) -> _Captured:
        static_image = image.detach().clone().requires_grad_(True)
        static_packed = packed.detach().clone()
        side = torch.cuda.Stream(device=image.device)
        side.wait_stream(torch.cuda.current_stream(image.device))
        with torch.cuda.stream(side):
            for _ in range(self.warmup):
                self._step(static_image, static_packed, enhance)
        torch.cuda.current_stream(image.device).wait_stream(side)
        graph = torch.cuda.CUDAGraph()
        # Forward and backward in one capture (autograd's device thread launches onto the capturing stream, as
        # in torch.cuda.make_graphed_callables); a private memory pool per graph. The live viewer renders from
        # another thread only between steps (its gate).
        with cuda_graphs.capture(graph):
            result = self._step(static_image, static_packed, enhance)
        return _Captured(graph, static_image, static_packed, result)

    def run(self, image: Tensor, packed: Tensor, enhance: bool) -> Optional[GraphResult]:
        """Replay (capturing first when the shape is new); None when this input must run eagerly."""
        if not self.supports(image, packed):
            if not self.emulate or image.is_cuda:
                return None
            with torch.enable_grad():
                return self._step(image.detach().requires_grad_(True), packed, enhance)
        key = self._key(image, packed, enhance)
        cap = self._graphs.get(key)
        if cap is None:
            if key in self._failed or len(self._graphs) >= self.max_graphs:
                return None
            try:
                with torch.cuda.device(image.device):  # captures run on the current device's streams
                    cap = self._capture(image, packed, enhance)
            except Exception as err:  # an op that cannot be captured: this shape runs eagerly from now on
                self._failed[key] = f"{type(err).__name__}: {err}"
                return None
            if enhance:  # the enhancement never switches off again: free the graphs without it
                for old in [k for k in self._graphs if not k[-1]]:
                    del self._graphs[old]
            self._graphs[key] = cap
        with torch.no_grad():
            cap.image.copy_(image.detach())
            if cap.packed.data_ptr() != packed.data_ptr():
                cap.packed.copy_(packed)
        with torch.cuda.device(image.device):
            cap.graph.replay()
        return cap.result

    @property
    def failures(self) -> Dict[tuple, str]:
        """Shapes whose capture failed, with the error (they run eagerly)."""
        return dict(self._failed)

    def __len__(self) -> int:
        return len(self._graphs)


class _Emulated(torch.autograd.Function):
    """What ``make_graphed_callables`` builds, run eagerly: the module's forward as one autograd node whose
    backward differentiates the module (inputs and parameters) in one go. Its operators show under
    ``record_function("step/channel_graph")``, the phase that is two graph launches on the GPU."""

    @staticmethod
    def forward(ctx, module, n_inputs: int, *tensors):
        with torch.enable_grad(), record_function("step/channel_graph"):
            # The inputs as fresh leaves; the parameters (the module's own) as they are.
            leaves = [t.detach().requires_grad_(t.requires_grad) for t in tensors[:n_inputs]] + \
                list(tensors[n_inputs:])
            out = module(*leaves[:n_inputs])
        ctx.leaves, ctx.out = leaves, out
        return out.detach()

    @staticmethod
    def backward(ctx, grad):
        need = [t for t in ctx.leaves if t.requires_grad]
        with record_function("step/channel_graph"):
            grads = iter(torch.autograd.grad(ctx.out, need, grad))
        return (None, None) + tuple(next(grads) if t.requires_grad else None for t in ctx.leaves)


class _ChannelCapture:
    """Forward and backward CUDA graphs of a :class:`GaussianChannels` module for one set of Gaussian tensors
    (the graphs' static inputs themselves: Adam updates them in place) and a private copy of the centre.
    What ``torch.cuda.make_graphed_callables`` builds, without its reference cycles: dropping this object
    frees the graphs and their memory at once (a run rebuilds them at every densification)."""

    def __init__(self, module, gaussians: Tuple[Tensor, ...], center: Tensor, warmup: int,
                 side: "torch.cuda.Stream") -> None:
        self.center = center.detach().clone()
        self.inputs = tuple(gaussians) + (self.center,)
        self.params = tuple(module.parameters())
        self.diff = [t for t in self.inputs + self.params if t.requires_grad]
        device = center.device
        side.wait_stream(torch.cuda.current_stream(device))
        with torch.cuda.stream(side):
            for _ in range(warmup):
                warm = module(*self.inputs)
                torch.autograd.grad(warm, self.diff, torch.ones_like(warm))
                del warm
        torch.cuda.current_stream(device).wait_stream(side)
        self.fwd, self.bwd = torch.cuda.CUDAGraph(), torch.cuda.CUDAGraph()
        pool = torch.cuda.graph_pool_handle()  # shared by the two: the backward reads the forward's saved tensors
        # The lean capture: a re-capture at every densification must not drain the GPU's queue nor empty the
        # allocator's caches, as torch.cuda.graph does (experiments/notes/2026-11-26-scale-events.md).
        with cuda_graphs.capture_lean(self.fwd, side, pool):
            out = module(*self.inputs)
        self.grad_out = torch.empty_like(out)
        with cuda_graphs.capture_lean(self.bwd, side, pool):
            self.grads = torch.autograd.grad(out, self.diff, self.grad_out)
        torch.cuda.current_stream(device).wait_stream(side)
        self.out = out.detach()


class _GraphedChannels(torch.autograd.Function):
    """Replays a :class:`_ChannelCapture`: forward = the forward graph, backward = the backward graph."""

    @staticmethod
    def forward(ctx, cap: _ChannelCapture, *tensors: Tensor) -> Tensor:
        # tensors: the Gaussians' tensors (the capture's own storage), the centre, the module's parameters.
        ctx.cap = cap
        cap.center.copy_(tensors[len(cap.inputs) - 1])
        with torch.cuda.device(cap.center.device):
            cap.fwd.replay()
        return cap.out.detach()  # a new tensor object on the static storage (autograd sets its grad_fn)

    @staticmethod
    def backward(ctx, grad: Tensor):
        cap = ctx.cap
        cap.grad_out.copy_(grad)
        with torch.cuda.device(cap.center.device):
            cap.bwd.replay()
        grads = iter(g.detach() for g in cap.grads)
        return (None,) + tuple(next(grads) if t.requires_grad else None for t in cap.inputs + cap.params)


class ChannelGraphs:
    """The per-Gaussian channels of a render (SH colour + illumination MLP,
    :func:`retinexgs.model.retinex_model.gaussian_channels`), forward and backward, as two CUDA graphs
    instead of a few dozen small kernels each way on [N, ...] tensors.

    The Gaussians' tensors are the graphs' static inputs themselves (Adam updates them in place), so a call
    copies only the camera centre. The graphs are rebuilt when the Gaussians change (densification,
    pruning, an opacity reset: new tensors) or the active SH degree grows: a few dozen captures in a run.
    ``emulate``: on the CPU run the same structure eagerly (tests, op counts).
    """

    # A capture is made only where it will be replayed at least this many times before the Gaussians change
    # again. A capture costs the host one eager evaluation (recorded, not run) plus the graphs' instantiation
    # (0.7 ms an event, H100, 2026-11-26); a replay saves a few dozen launches: a span of a few steps cannot pay
    # it back, and a short run densifies every few steps (500 steps: every 5). 8 is a round number, not tuned.
    MIN_REPLAYS = 8

    def __init__(self, model, warmup: int = 2, emulate: bool = False) -> None:
        self.model, self.warmup, self.emulate = model, int(warmup), bool(emulate)
        self._key: Optional[tuple] = None
        self._cap: Optional[_ChannelCapture] = None
        self._failed: Dict[tuple, str] = {}
        self._side: Dict[torch.device, "torch.cuda.Stream"] = {}  # one capture stream per device
        self._warmed: set = set()  # (device, SH degree, MLP or not): captured before, no eager warm-up again
        self.captures = 0
        self.deferred = 0  # steps evaluated eagerly because the Gaussians were about to change

    def run(self, active_degree: int, center: Tensor, replays: Optional[int] = None) -> Optional[Tensor]:
        """The channels [N,C] (differentiable in the Gaussians and the illumination field); None: evaluate
        them eagerly (not CUDA, the capture failed, or ``replays``, the steps these Gaussians and this SH degree
        are known to last, is below :attr:`MIN_REPLAYS`: then no graph is captured for them)."""

        g = self.model.gaussians
        degree = self.model.channel_degree(active_degree)
        illumination = self.model.illumination if self.model.decomposed else None
        gaussians = (g.means, g.sh_dc, g.sh_rest)
        if not g.means.is_cuda:
            if not self.emulate:
                return None
            module = GaussianChannels(degree, illumination)
            return _Emulated.apply(module, 4, *gaussians, center, *module.parameters())
        key = (degree, center.device, center.dtype) + tuple((t.data_ptr(), tuple(t.shape), t.dtype) for t in gaussians)
        if key != self._key:
            self._cap = None  # the old graphs (and their memory) go with the old Gaussians
            if key in self._failed:
                self._key = key
                return None
            if replays is not None and replays < self.MIN_REPLAYS:
                self._key = None  # decided again next step
                self.deferred += 1
                return None
            self._key = key
            device = center.device
            side = self._side.get(device)
            try:
                with torch.cuda.device(device):
                    if side is None:
                        side = torch.cuda.Stream(device=device)
                    warm = (device, degree, illumination is not None)
                    self._cap = _ChannelCapture(GaussianChannels(degree, illumination), gaussians, center,
                                                0 if warm in self._warmed else self.warmup, side)
                self._side[device] = side
                self._warmed.add(warm)
                self.captures += 1
            except Exception as err:  # runs eagerly until the Gaussians change
                self._failed[key] = f"{type(err).__name__}: {err}"
                return None
        if self._cap is None:
            return None
        return _GraphedChannels.apply(self._cap, *gaussians, center, *self._cap.params)

    @property
    def failures(self) -> Dict[tuple, str]:
        return dict(self._failed)
