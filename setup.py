"""The build of dyq: setuptools drives the CMake project beside this file (CMakeLists.txt, the one
description of what is compiled), as the torch ecosystem's CMake-built extensions do.

    pip install .                                  # isolated build against torch==2.13.0 (pyproject.toml)
    pip install --no-build-isolation --no-deps .   # against the torch already installed (a GPU machine's)
    pip install -e .                               # editable: python/dyq in place, dyq/_C built beside it
    pip wheel .

CMAKE_ARGS passes options to CMake (CMAKE_ARGS="-DDYQ_CUDA=ON"); CMAKE_BUILD_PARALLEL_LEVEL sets the jobs.
The extension is built against one torch release and its torch dependency is pinned to that release
(torch's C++ ABI holds only within a release), so the metadata always names the torch it was built for.
"""
from __future__ import annotations

import os
import shlex
import subprocess
import sys
from pathlib import Path

from setuptools import Extension, find_namespace_packages, setup
from setuptools.command.build_ext import build_ext

ROOT = Path(__file__).resolve().parent


def torch_requirement() -> str:
    """``torch==X.Y.*`` for the torch this build compiles against."""
    import torch

    major, minor = torch.__version__.split("+")[0].split(".")[:2]
    return f"torch=={major}.{minor}.*"


class CMakeExtension(Extension):
    def __init__(self, name: str) -> None:
        super().__init__(name, sources=[])


class CMakeBuild(build_ext):
    """Configures and builds CMakeLists.txt with DYQ_BUILD_PYTHON, the module landing where setuptools
    puts the extension (the wheel's dyq/, or python/dyq/ for an editable install)."""

    def build_extension(self, ext: Extension) -> None:
        output_dir = Path(self.get_ext_fullpath(ext.name)).resolve().parent
        build_dir = Path(self.build_temp).resolve() / "cmake"
        cache = build_dir / "CMakeCache.txt"
        # A cache of another interpreter (an earlier isolated build's temporary environment) would point
        # CMake at a torch that no longer exists.
        if cache.is_file() and f"Python_EXECUTABLE:FILEPATH={sys.executable}\n" not in cache.read_text():
            cache.unlink()
        build_dir.mkdir(parents=True, exist_ok=True)
        configure = [
            "cmake", "-S", str(ROOT), "-B", str(build_dir), "-G", "Ninja",
            f"-DPython_EXECUTABLE={sys.executable}",
            "-DCMAKE_BUILD_TYPE=Release",
            "-DDYQ_BUILD_PYTHON=ON",
            "-DDYQ_BUILD_TESTS=OFF",
            f"-DCMAKE_LIBRARY_OUTPUT_DIRECTORY={output_dir}",
            *shlex.split(os.environ.get("CMAKE_ARGS", "")),
        ]
        jobs = os.environ.get("CMAKE_BUILD_PARALLEL_LEVEL") or str(os.cpu_count() or 1)
        subprocess.run(configure, check=True)
        subprocess.run(["cmake", "--build", str(build_dir), "--target", "_C", "-j", jobs], check=True)


setup(
    # Namespace discovery: the policy folders (data only, no __init__.py) are packages too, as Python
    # sees them, so setuptools neither warns about them nor drops them.
    packages=find_namespace_packages("python", include=["dyq*"], exclude=["*__pycache__*"]),
    package_dir={"": "python"},
    # Everything under python/dyq ships, data too (the trained policies under dyq/sim/policies/<task>/).
    package_data={"dyq": ["**/*"]},
    exclude_package_data={"": ["__pycache__/*", "*.pyc", "_C*.so"]},
    ext_modules=[CMakeExtension("dyq._C")],
    cmdclass={"build_ext": CMakeBuild},
    install_requires=[torch_requirement(), "numpy>=1.24"],
)
