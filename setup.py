"""Build torch_rbpt and its C++ extension torch_rbpt._C.

Install with `pip install --no-build-isolation -e .` after torch (see the Makefile).
Set DEBUG=1 for an unoptimised build with debug symbols, SANITIZE=1 for one instrumented with
AddressSanitizer and UndefinedBehaviorSanitizer (`SANITIZE=1 make test` preloads their runtime).
The optimised build targets the machine it is built on (-march=native, with a tuning of its
own on some CPUs; floating-point contraction stays off, so results keep their rounding);
MARCH=<cpu> targets another CPU (e.g. MARCH=x86-64-v3 for any AVX2 machine), MTUNE=<cpu>
forces a tuning, PORTABLE=1 builds for baseline x86-64. The flags are in
torch_rbpt/build_flags.py, with which the tests and the ray benchmark compile csrc/ too.
"""
import glob
import importlib.util
import os

from setuptools import setup
from torch.utils.cpp_extension import BuildExtension, CppExtension

# (Loaded by its path: the package is not importable before its extension exists.)
_spec = importlib.util.spec_from_file_location(
    "build_flags", os.path.join(os.path.dirname(os.path.abspath(__file__)), "torch_rbpt", "build_flags.py"))
build_flags = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(build_flags)

debug = os.environ.get("DEBUG", "0") == "1"
sanitize = os.environ.get("SANITIZE", "0") == "1"
# Hidden visibility: only the module's entry point is exported, so that calls between our
# translation units are direct rather than through the PLT.
cxx_flags = ["-std=c++17", "-fopenmp", "-Wall", "-Wno-sign-compare", "-fvisibility=hidden"]
portable = os.environ.get("PORTABLE", "0") == "1"
target = [] if portable else build_flags.target_flags()
# The tuning, for the benchmarks' headers (_C.build_tune).
cxx_flags.append(f'-DRBPT_TUNE="{build_flags.tuned_for(target)}"')
link_flags = ["-fopenmp"]
if sanitize:
    # Assertions stay on: the sanitized build is the one that looks for bugs. It targets the
    # machine like the release build (below), so that it runs the same code paths (the
    # wavefront needs AVX2), and contracts no multiply-adds, so that its images are those of
    # the release build's arithmetic.
    sanitizers = ["-fsanitize=address,undefined", "-fno-sanitize-recover=undefined"]
    cxx_flags += sanitizers + ["-fno-omit-frame-pointer", "-g", "-O1", "-ffp-contract=off"] + target
    link_flags += sanitizers
elif debug:
    cxx_flags += ["-O0", "-g"]
else:
    cxx_flags += build_flags.OPTIMISED + target

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
            extra_link_args=link_flags,
        )
    ],
    cmdclass={"build_ext": BuildExtension},
)
