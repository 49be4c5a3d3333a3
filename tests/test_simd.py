"""simd.h's helpers for the loops in lanes: simd::select_indices, which lists the lanes a stage
treats apart (the rays near a sphere, the rough vertices), built for this machine (its
AVX-512 path where the CPU has it) and for any AVX2 machine (its scalar path), against a
plain loop; simd::pad_indices, which pads such a list to whole vectors."""

import os
import shutil
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

PROGRAM = r"""
#include <cstdio>
#include <initializer_list>
#include "simd.h"

int main() {
    unsigned state = 12345u;
    auto next = [&] { state = state * 1664525u + 1013904223u; return state >> 8; };
    const int sizes[] = {0, 1, 7, 15, 16, 17, 31, 32, 100, 255, 256};
    const int Sentinel = -7;
    int failures = 0, checks = 0, pad_failures = 0, pad_checks = 0;
    for (int n : sizes) {
        for (int kinds : {1, 2, 3, 6}) {
            int values[256], list[256 + 32];
            for (int k = 0; k < n; ++k) values[k] = int(next() % unsigned(kinds));
            for (int value = 0; value < kinds; ++value) {
                for (int &l : list) l = Sentinel;
                const int count = rbpt::simd::select_indices(values, n, value, list);
                int expected = 0;
                for (int k = 0; k < n; ++k) {
                    if (values[k] != value) continue;
                    if (list[expected] != k) ++failures;
                    ++expected;
                }
                if (count != expected) ++failures;
                // Nothing written beyond what the contract allows: n entries, or the count + 1.
                const int allowed = count < n ? count + 1 : count;
                for (int i = allowed; i < 256 + 32; ++i) failures += list[i] != Sentinel;
                ++checks;
                // Padded: to the next multiple of 16 (at most n's), the list kept, the padding
                // its last entry, nothing written beyond.
                int before[256 + 32];
                for (int i = 0; i < 256 + 32; ++i) before[i] = list[i];
                const int padded = rbpt::simd::pad_indices(list, count);
                if (padded % 16 != 0 || padded < count || padded >= count + 16 || padded > (n + 15) / 16 * 16)
                    ++pad_failures;
                for (int i = 0; i < count; ++i) pad_failures += list[i] != before[i];
                for (int i = count; i < padded; ++i) pad_failures += list[i] != list[count - 1];
                for (int i = padded; i < 256 + 32; ++i) pad_failures += list[i] != before[i];
                ++pad_checks;
            }
        }
    }
    std::printf("select_indices: %d checks, %d failures\n", checks, failures);
    std::printf("pad_indices: %d checks, %d failures\n", pad_checks, pad_failures);
    return failures + pad_failures == 0 ? 0 : 1;
}
"""


def _compiler():
    for name in (os.environ.get("CXX"), "g++", "c++"):
        if name and shutil.which(name):
            return shutil.which(name)
    return None


def _run_program(tmp_path, march):
    cxx = _compiler()
    if cxx is None:
        pytest.skip("no C++ compiler found ($CXX, g++ or c++)")
    source = tmp_path / "select.cpp"
    source.write_text(PROGRAM)
    exe = tmp_path / "select"
    env = {k: v for k, v in os.environ.items() if k != "LD_PRELOAD"}
    build = subprocess.run([cxx, "-std=c++17", "-O2", f"-march={march}", "-Wall", "-I", str(ROOT / "csrc"),
                            str(source), "-o", str(exe)], capture_output=True, text=True, env=env)
    assert build.returncode == 0, build.stderr
    run = subprocess.run([str(exe)], capture_output=True, text=True, timeout=60)
    return dict(line.split(": ", 1) for line in run.stdout.splitlines())


@pytest.mark.parametrize("march", ["native", "x86-64-v3"])
def test01_select_indices_lists_matching_lanes(tmp_path, march):
    # Every index whose value matches, in order, and no write past the list's contract
    # (a compressed vector's store past the count, or an index off by one, fails it).
    result = _run_program(tmp_path, march)["select_indices"]
    assert result.endswith(" 0 failures") and not result.startswith("0 checks"), result


def test02_pad_indices_pads_lists_to_whole_vectors(tmp_path):
    # The rough stages, the spheres' interactions and near rays run their loops over the
    # padded length: a length not a multiple of 16, a changed entry or a write beyond the
    # padding fails it (the padding's lanes are computed and ignored, so they must be lanes
    # of the list).
    result = _run_program(tmp_path, "native")["pad_indices"]
    assert result.endswith(" 0 failures") and not result.startswith("0 checks"), result
