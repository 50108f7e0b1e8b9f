"""Differentiable Gaussian rasterization (our own kernels; CPU/OpenMP and CUDA).

Public API: :func:`rasterize_gaussians`, :func:`spherical_harmonics`, :class:`Camera`, :class:`RenderOutput`.
The pure-torch twin lives in :mod:`retinexgs.render.reference`.
"""
from retinexgs.render._backend import get_num_threads, has_cuda, set_num_threads
from retinexgs.render.camera import Camera
from retinexgs.render.rasterize import RenderOutput, rasterize_gaussians, spherical_harmonics

__all__ = ["Camera", "RenderOutput", "rasterize_gaussians", "spherical_harmonics", "set_num_threads",
           "get_num_threads", "has_cuda"]
