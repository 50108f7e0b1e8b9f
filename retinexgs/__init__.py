"""RetinexGS: multi-view dark photos -> a 3D Gaussian scene that renders normally-lit novel views.

The public rendering API is :func:`retinexgs.render.rasterize_gaussians`.
"""
__version__ = "0.1.0"
