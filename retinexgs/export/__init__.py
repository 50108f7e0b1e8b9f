"""Rendering a trained run to images and videos, and exporting it as a standard 3DGS PLY.

- :func:`retinexgs.export.renders.render_run`: maps of the test/train views (PNG) or a camera path (MP4/PNG).
- :func:`retinexgs.export.export.export_run`: the enhanced scene as an INRIA 3DGS PLY (colours baked).
- :func:`retinexgs.export.ply.write_ply` / :func:`retinexgs.export.ply.read_ply`: the PLY format.
"""

# Here rather than in the modules that use them, so the CLI can build its --help without importing torch.
PATH_KINDS = ("orbit", "orbit-360", "interpolate")
DEFAULT_DIRECTIONS = 64  # Fibonacci directions of the SH fit: 4x the 16 coefficients of degree 3
