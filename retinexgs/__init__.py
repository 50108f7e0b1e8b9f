"""RetinexGS: multi-view dark photos -> a 3D Gaussian scene that renders normally-lit novel views.

The public rendering API is :func:`retinexgs.render.rasterize_gaussians`.
"""
# The one place the version is written: setup.py reads it from here, `retinexgs --version` prints it.
__version__ = "0.1.0"
