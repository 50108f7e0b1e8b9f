"""Build RetinexGS and its kernel library ``retinexgs._C``.

The CPU (OpenMP) kernels always build. The CUDA kernels build too when torch is a CUDA build and a CUDA
toolkit is found (``TORCH_CUDA_ARCH_LIST`` is respected). Set ``RETINEXGS_CPU_ONLY=1`` to skip CUDA.
"""
import glob
import os
import re
import shutil
import sys

from setuptools import find_packages, setup
from setuptools.command.build_py import build_py
from torch.utils.cpp_extension import CUDA_HOME, BuildExtension, CppExtension, CUDAExtension
import torch

HERE = os.path.dirname(os.path.abspath(__file__))


def _version() -> str:
    """retinexgs.__version__, read from the source (importing the package here would need it built): the one
    place the version is written; `retinexgs --version` and the package metadata both show it."""
    with open(os.path.join(HERE, "retinexgs", "__init__.py"), encoding="utf-8") as f:
        return re.search(r'^__version__ = "([^"]+)"', f.read(), re.M).group(1)


def _sources(pattern: str) -> list:
    # Relative paths keep object names distinct per folder (csrc/cpu/x.o vs csrc/cuda/x.o).
    return sorted(os.path.relpath(p, HERE) for p in glob.glob(os.path.join(HERE, pattern)))


def _extension():
    cpu_sources = ["csrc/bindings.cpp"] + _sources("csrc/cpu/*.cpp")
    include_dirs = [os.path.join(HERE, "csrc", "include")]
    # No -std flag: torch picks the standard its headers (and its c10::Error layout) were built with.
    # -ffp-contract=off: no fused multiply-adds on the host, so the tile culling of the binning (rgs/math.h,
    # TileReach, written with unfused device operations) decides every tile exactly as the GPU does.
    cxx_flags = ["-O3", "-fopenmp", "-ffp-contract=off"]
    link_flags = ["-fopenmp"]
    want_cuda = os.environ.get("RETINEXGS_CPU_ONLY", "0") != "1"
    has_cuda = want_cuda and torch.version.cuda is not None and CUDA_HOME is not None
    if has_cuda:
        print(f"[retinexgs] building CPU+CUDA kernels (CUDA {torch.version.cuda}, toolkit {CUDA_HOME})")
        return CUDAExtension(
            "retinexgs._C",
            cpu_sources + _sources("csrc/cuda/*.cu"),
            include_dirs=include_dirs,
            define_macros=[("RGS_WITH_CUDA", "1")],
            extra_compile_args={"cxx": cxx_flags, "nvcc": ["-O3", "--use_fast_math"]},
            extra_link_args=link_flags,
        )
    why = "disabled by RETINEXGS_CPU_ONLY" if not want_cuda else (
        "torch is a CPU build" if torch.version.cuda is None else "no CUDA toolkit found")
    print(f"[retinexgs] building CPU-only kernels ({why})")
    return CppExtension("retinexgs._C", cpu_sources, include_dirs=include_dirs,
                        extra_compile_args={"cxx": cxx_flags}, extra_link_args=link_flags)


class BuildPyWithConfigs(build_py):
    """Also ship the top-level configs/ inside the package (retinexgs/configs), so that an installed copy finds
    default.yaml, demo.yaml and the ablations without the source tree."""

    def run(self):
        super().run()
        if not self.dry_run:
            shutil.copytree(os.path.join(HERE, "configs"), os.path.join(self.build_lib, "retinexgs", "configs"),
                            dirs_exist_ok=True)


setup(
    name="retinexgs",
    version=_version(),
    description="3D Retinex Gaussian splatting: normally-lit, 3D-consistent novel views from dark photos",
    packages=find_packages(include=["retinexgs", "retinexgs.*"]),
    # LPIPS-AlexNet's weights (retinexgs/evaluate/lpips.py: eval reports LPIPS offline) and their licences.
    package_data={"retinexgs.evaluate": ["weights/lpips_alex.npz", "weights/THIRD_PARTY.md"]},
    python_requires=">=3.9",
    license="Apache-2.0",  # LICENSE; third-party parts (weights) in their own notice
    license_files=["LICENSE"],
    # pycolmap reads COLMAP models and runs SfM; plyfile reads and writes the exported PLY;
    # pydantic checks the config (retinexgs/config/schema.py); pillow-heif reads phone photos (HEIC/HEIF); rawpy (LibRaw)
    # and exifread read camera raw files and their exposure (retinexgs/data/camera_raw.py); imageio-ffmpeg decodes
    # a phone's night video for `retinexgs frames` (retinexgs/data/video.py) with the static ffmpeg its wheel
    # ships (68 MB), so that no system ffmpeg is needed.
    install_requires=["torch>=2.1", "numpy", "pyyaml", "tqdm", "pillow", "opencv-contrib-python-headless>=4.8",
                      "pycolmap>=4.0", "plyfile", "pydantic>=2", "pillow-heif>=0.10", "rawpy>=0.28", "exifread>=3.0",
                      "imageio-ffmpeg>=0.4.5"],
    extras_require={
        # import-linter: the layer contracts (.importlinter). viser and selenium: the viewer's server and browser
        # tests (the browser test also needs Debian's chromium and chromium-driver, installed by .ci/run; without
        # them it is skipped).
        "test": ["pytest", "hypothesis", "scipy", "imageio[ffmpeg]", "viser>=1.1", "selenium", "import-linter>=2.1",
                 "openexr>=3.3"],
        # Video paths (render --path) and TensorBoard logging (log.tensorboard, off by default).
        "io": ["imageio[ffmpeg]", "tensorboard"],
        # The web viewer (retinexgs view).
        "view": ["viser>=1.1"],
        # Scene-linear OpenEXR renders (render --format exr); 3.3 brought the OpenEXR.File API used there.
        "hdr": ["openexr>=3.3"],
    },
    entry_points={"console_scripts": ["retinexgs=retinexgs.cli:main"]},
    ext_modules=[_extension()],
    cmdclass={"build_ext": BuildExtension.with_options(use_ninja=True), "build_py": BuildPyWithConfigs},
    zip_safe=False,
)
