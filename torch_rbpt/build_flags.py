"""Compiler flags of the extension's optimised build, chosen for the machine that builds it.

setup.py loads this file by its path (torch_rbpt is not importable before its extension is
built), and the tests and the ray benchmark that compile csrc/ themselves take their flags
from it, so that all of them compile the core alike. Standard library only.

The target: ``-march=native`` unless MARCH names another CPU (e.g. ``x86-64-v3`` for any AVX2
machine). The tuning: GCC's own for that target, except on Intel CPUs with AVX-512 that are
not affected by Gather Data Sampling (Sapphire Rapids and later Xeons), which get
``-mtune=sapphirerapids -mprefer-vector-width=512`` (see ``host_tuning``). MTUNE=<cpu>
forces ``-mtune=<cpu>`` (MTUNE=generic: GCC's default).
"""
from __future__ import annotations

import os
from pathlib import Path

# Optimised, without changing any result's rounding: no floating-point contraction; no errno
# from libm (nothing reads it: sqrt inlines without a call on the error path); no trapping
# floating-point operations (nothing enables FP exceptions: a division or square root may be
# computed before the branch that uses it).
OPTIMISED = ["-O3", "-DNDEBUG", "-ffp-contract=off", "-fno-math-errno", "-fno-trapping-math"]

GDS = Path("/sys/devices/system/cpu/vulnerabilities/gather_data_sampling")


def host_tuning(cpuinfo: str | None = None, gds: str | None = None) -> list[str]:
    """Tuning flags for the build machine where GCC's own choice for ``-march=native`` is
    poor, else []. ``cpuinfo`` and ``gds`` default to /proc/cpuinfo and the kernel's Gather
    Data Sampling status (for tests).

    GCC 12 builds an Intel Xeon of Sapphire Rapids' generations or later for cooperlake with
    generic tuning, which loads the lanes of the vector loops' gathers one by one. Tuned for
    Sapphire Rapids it uses the hardware gathers (fast on CPUs that Gather Data Sampling does
    not affect; the microcode mitigating it makes them several times slower on the older
    ones) but prefers 256-bit vectors, so 512-bit ones are asked for: our vector loops are
    written for 16 lanes. Measured on an Intel Xeon (family 6, model 207), one thread, 256
    px, 16 spp: renders 4% (cornell-box) to 10% (cbox, the bunny) faster, images bitwise
    the same. AMD keeps GCC's choice: on a Zen 5 EPYC the hardware gathers made renders
    10-20% slower (-mtune=icelake-server, session 25).
    """
    try:
        cpuinfo = Path("/proc/cpuinfo").read_text() if cpuinfo is None else cpuinfo
        gds = GDS.read_text() if gds is None else gds
    except OSError:  # not Linux, or a kernel that does not report it: GCC's choice
        return []
    fields = {}
    for line in cpuinfo.splitlines():
        key, _, value = line.partition(":")
        fields.setdefault(key.strip(), value.strip())
    intel = fields.get("vendor_id") == "GenuineIntel"
    avx512 = "avx512f" in fields.get("flags", "").split()
    if intel and avx512 and gds.strip() == "Not affected":
        return ["-mtune=sapphirerapids", "-mprefer-vector-width=512"]
    return []


def target_flags(march: str | None = None, tune: str | None = None) -> list[str]:
    """``-march`` and the tuning: MARCH (default native) and MTUNE from the environment
    unless given; the host's tuning (host_tuning()) only for a native build without MTUNE."""
    march = march or os.environ.get("MARCH") or "native"
    tune = tune if tune is not None else os.environ.get("MTUNE", "")
    if tune:
        return [f"-march={march}", f"-mtune={tune}"]
    return [f"-march={march}"] + (host_tuning() if march == "native" else [])


def tuned_for(flags: list[str]) -> str:
    """The -mtune value among `flags`, or "" (GCC's own choice for the target)."""
    return next((f.split("=", 1)[1] for f in reversed(flags) if f.startswith("-mtune=")), "")
