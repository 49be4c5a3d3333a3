"""Autodiff number types (csrc/autodiff.h: reverse-mode Var, csrc/dual.h: forward-mode Dual).

The checks live in the standalone C++ program tests/cpp/test_autodiff.cpp (the headers need
neither torch nor the extension); this compiles it warning-free with -Wall and runs it. Under
SANITIZE=1 (`SANITIZE=1 make test`) it is built with AddressSanitizer and UBSan, with leak
detection on: unlike Python, this program should free everything it allocates.
"""
import os
import re
import shutil
import subprocess
from pathlib import Path

import pytest

from conftest import uninstrumented_env

ROOT = Path(__file__).resolve().parents[1]
SOURCE = ROOT / "tests" / "cpp" / "test_autodiff.cpp"


def _compiler():
    for name in (os.environ.get("CXX"), "g++", "c++", "clang++"):
        if name and shutil.which(name):
            return shutil.which(name)
    return None


def test01_cpp_autodiff_suite(tmp_path):
    cxx = _compiler()
    if cxx is None:
        pytest.skip("no C++ compiler found ($CXX, g++, c++ or clang++) to build test_autodiff.cpp")
    exe = tmp_path / "test_autodiff"
    sanitize = os.environ.get("SANITIZE", "0") == "1"
    flags = ["-fsanitize=address,undefined", "-fno-sanitize-recover=undefined",
             "-fno-omit-frame-pointer", "-g", "-O1"] if sanitize else ["-O2"]
    cmd = [cxx, "-std=c++17", *flags, "-Wall", "-I", str(ROOT / "csrc"), str(SOURCE), "-o", str(exe)]
    # The compiler is not instrumented: keep the preloaded sanitizer runtime away from it.
    env = uninstrumented_env()
    build = subprocess.run(cmd, capture_output=True, text=True, env=env)
    assert build.returncode == 0, f"compilation failed: {' '.join(cmd)}\n{build.stderr}"
    assert "warning:" not in build.stderr, f"compiler warnings:\n{build.stderr}"

    if sanitize:
        env["ASAN_OPTIONS"] = env.get("ASAN_OPTIONS", "") + ":detect_leaks=1"
    run = subprocess.run([str(exe)], capture_output=True, text=True, timeout=600, env=env)
    output = run.stdout + run.stderr
    assert run.returncode == 0, f"test_autodiff exited with status {run.returncode}:\n{output}"
    summary = re.search(r"^(\d+) passed, (\d+) failed$", run.stdout, re.MULTILINE)
    assert summary, f"no summary line in the output:\n{output}"
    assert summary.group(2) == "0" and int(summary.group(1)) > 0, output
