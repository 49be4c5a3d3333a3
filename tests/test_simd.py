"""simd.h's helpers for the loops in lanes: simd::select_indices, which lists the lanes a stage
treats apart (the rays near a sphere, the rough vertices), built for this machine (its
AVX-512 path where the CPU has it) and for any AVX2 machine (its scalar path), against a
plain loop; simd::pad_indices, which pads such a list to whole vectors; simd::compact_columns,
which moves the wavefront's live lanes to the front of its columns, built for this machine,
for AVX2 and for the x86-64 baseline (three different codes)."""

import os
import shutil
import subprocess
from pathlib import Path

import pytest

from conftest import uninstrumented_env

ROOT = Path(__file__).resolve().parents[1]

PROGRAM = r"""
#include <cstdint>
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
                // Nothing written beyond the list's n entries (AVX2's whole stores fill it up
                // to the last vector of indices tested).
                const int allowed = n;
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
    // compact_columns: three 32-bit columns and two 64-bit ones of 256 lanes (and a
    // sentinel vector beyond), the live lanes of random patterns (none, all, runs, sparse).
    int compact_failures = 0, compact_checks = 0;
    alignas(64) static uint32_t w0[256 + 16], w1[256 + 16], w2[256 + 16];
    alignas(64) static uint64_t d0[256 + 16], d1[256 + 16];
    alignas(64) static int alive[256 + 16];
    for (int n : sizes) {
        for (int density : {0, 1, 2, 4, 7, 8}) {  // eighths alive
            for (int rep = 0; rep < 8; ++rep) {
                uint32_t *const words[] = {w0, w1, w2};
                uint64_t *const doubles[] = {d0, d1};
                for (int k = 0; k < 256 + 16; ++k) {
                    w0[k] = 1000u + k, w1[k] = 2000u + k, w2[k] = 3000u + k;
                    d0[k] = (uint64_t(k) << 32) | 7u, d1[k] = ~uint64_t(k);
                    alive[k] = k < n && int(next() % 8u) < density ? int(next() % 3u) + 1 : 0;  // (any nonzero)
                }
                if (rep == 1) for (int k = 0; k < n; ++k) alive[k] = (k / 9) % 2;  // runs
                const int live = rbpt::simd::compact_columns(words, doubles, alive, n);
                int expected = 0;
                for (int k = 0; k < n; ++k) {
                    if (!alive[k]) continue;
                    compact_failures += w0[expected] != 1000u + k || w1[expected] != 2000u + k || w2[expected] != 3000u + k;
                    compact_failures += d0[expected] != ((uint64_t(k) << 32) | 7u) || d1[expected] != ~uint64_t(k);
                    ++expected;
                }
                compact_failures += live != expected;
                // Nothing written beyond the whole vectors of 16 lanes that hold [0, n).
                for (int k = (n + 15) / 16 * 16; k < 256 + 16; ++k) {
                    compact_failures += w0[k] != 1000u + k || w2[k] != 3000u + k || d1[k] != ~uint64_t(k);
                }
                ++compact_checks;
            }
        }
    }
    std::printf("select_indices: %d checks, %d failures\n", checks, failures);
    std::printf("pad_indices: %d checks, %d failures\n", pad_checks, pad_failures);
    std::printf("compact_columns: %d checks, %d failures\n", compact_checks, compact_failures);
    return failures + pad_failures + compact_failures == 0 ? 0 : 1;
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
    env = uninstrumented_env()
    build = subprocess.run([cxx, "-std=c++17", "-O2", f"-march={march}", "-Wall", "-I", str(ROOT / "csrc"),
                            str(source), "-o", str(exe)], capture_output=True, text=True, env=env)
    assert build.returncode == 0, build.stderr
    run = subprocess.run([str(exe)], capture_output=True, text=True, timeout=60)
    return dict(line.split(": ", 1) for line in run.stdout.splitlines())


@pytest.mark.parametrize("march", ["native", "x86-64-v3", "x86-64"])
def test01_select_indices_lists_matching_lanes(tmp_path, march):
    # Every index whose value matches, in order, and no write past the list's contract
    # (a vector's store past the n entries, or an index off by one, fails it).
    result = _run_program(tmp_path, march)["select_indices"]
    assert result.endswith(" 0 failures") and not result.startswith("0 checks"), result


def test02_pad_indices_pads_lists_to_whole_vectors(tmp_path):
    # The rough stages, the spheres' interactions and near rays run their loops over the
    # padded length: a length not a multiple of 16, a changed entry or a write beyond the
    # padding fails it (the padding's lanes are computed and ignored, so they must be lanes
    # of the list).
    result = _run_program(tmp_path, "native")["pad_indices"]
    assert result.endswith(" 0 failures") and not result.startswith("0 checks"), result


@pytest.mark.parametrize("march", ["native", "x86-64-v3", "x86-64"])
def test03_compact_columns_moves_live_lanes_to_the_front(tmp_path, march):
    # The wavefront's compaction (AVX-512's compression, AVX2's permutes from a table, one
    # lane at a time without either): every live lane's words and doubles at its rank, in
    # order, their count, and nothing written beyond the whole vectors that hold the lanes (a
    # mask's bits doubled wrongly for the 64-bit columns, or a table entry off by one, fails it).
    result = _run_program(tmp_path, march)["compact_columns"]
    assert result.endswith(" 0 failures") and not result.startswith("0 checks"), result
