"""Build torch_rbpt and its C++ extension torch_rbpt._C.

Install with `pip install --no-build-isolation -e .` after torch (see the Makefile).
Set DEBUG=1 for an unoptimised build with debug symbols. The optimised build targets the
machine it is built on (-march=native; floating-point contraction stays off, so results do
not change with the instruction set); PORTABLE=1 builds for baseline x86-64 instead.
"""
import glob
import os

from setuptools import setup
from torch.utils.cpp_extension import BuildExtension, CppExtension

debug = os.environ.get("DEBUG", "0") == "1"
cxx_flags = ["-std=c++17", "-fopenmp", "-Wall", "-Wno-sign-compare"]
portable = os.environ.get("PORTABLE", "0") == "1"
cxx_flags += ["-O0", "-g"] if debug else ["-O3", "-DNDEBUG", "-ffp-contract=off"]
if not debug and not portable:
    cxx_flags.append("-march=native")

setup(
    name="torch_rbpt",
    version="0.1.0",
    description="A physically based differentiable path tracer for PyTorch (radiative backpropagation)",
    packages=["torch_rbpt"],
    package_data={"torch_rbpt": ["scenes/*.xml"]},
    python_requires=">=3.10",
    ext_modules=[
        CppExtension(
            "torch_rbpt._C",
            sorted(glob.glob("csrc/*.cpp")),
            extra_compile_args={"cxx": cxx_flags},
            extra_link_args=["-fopenmp"],
        )
    ],
    cmdclass={"build_ext": BuildExtension},
)
