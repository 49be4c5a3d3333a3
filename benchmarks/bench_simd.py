"""What SIMD lanes would gain on the shading side: three stages of a path vertex (camera ray,
triangle interaction, emitter sample + diffuse BSDF + MIS + BSDF sample), each run over 256
lanes as a plain loop (one path after another, as the renderer shades today) and as a loop
GCC vectorises, from the same inline code (benchmarks/simd/simd_stages.cpp, compiled here
with g++ and setup.py's release flags into benchmarks/cache/).

It is compiled for this machine (-march=native), for AVX2 (-march=x86-64-v3, if the CPU has
AVX2) and for the portable x86-64 baseline (SSE2), so the three vector widths are measured on
one CPU. Prints ns per lane, the speedup and whether both loops gave bitwise equal results
(they must: with -ffp-contract=off the vectorised loop performs the same IEEE operations), and
writes benchmarks/results/simd_stages.csv. Exits non-zero if a stage's results differ.

    python benchmarks/bench_simd.py [--quick]
"""
from __future__ import annotations

import argparse
import os
import re
import subprocess
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
from bench_rays import CSRC, CXX_FLAGS, RESULTS, build_flags, compile_cached, print_table  # noqa: E402
from machine import machine, simd, write_csv  # noqa: E402

SOURCE = HERE / "simd" / "simd_stages.cpp"
# setup.py's release flags without its target and tuning (chosen per build below: native
# with the extension's tuning).
BASE_FLAGS = [f for f in CXX_FLAGS if not f.startswith(("-march", "-mtune", "-mprefer-vector-width"))]
ISAS = {"native": " ".join(build_flags.target_flags("native")), "avx2": "-march=x86-64-v3", "portable": "-march=x86-64"}


def compile_stages(isa: str, cxx: str) -> Path:
    """Compile simd_stages.cpp for `isa`; cached by the sources' mtimes and the command."""
    cmd = [cxx, *BASE_FLAGS, *ISAS[isa].split(), f"-I{CSRC}", str(SOURCE)]
    return compile_cached(f"simd_stages_{isa}", cmd, [SOURCE] + sorted(CSRC.glob("*.h")),
                          "the SIMD stage benchmark")


def parse(text: str) -> list[dict]:
    rows = []
    for line in text.splitlines():
        if line.startswith("STAGE "):
            rows.append(dict(re.findall(r"(\w+)=(\S+)", line)))
    return rows


def main(argv=None) -> list[dict]:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="fewer repetitions (seconds), for the tests")
    ap.add_argument("--out", default=str(RESULTS), help="directory for simd_stages.csv")
    args = ap.parse_args(argv)
    cxx = os.environ.get("CXX", "g++")
    mach = machine()
    isas = ["native"] + (["avx2"] if simd(("avx2",)) else []) + ["portable"]
    rows, table, differing = [], [], []
    for isa in isas:
        exe = compile_stages(isa, cxx)
        r = subprocess.run([str(exe), "--reps", "500" if args.quick else "20000"], capture_output=True, text=True)
        stages = parse(r.stdout)
        if not stages:
            raise RuntimeError(f"{exe.name} printed no stages:\n{r.stdout}\n{r.stderr}")
        for st in stages:
            scalar, vector = float(st["scalar_ns"]), float(st["simd_ns"])
            equal = st["equal"] == "1"
            if not equal:
                differing.append(f"{st['name']} ({isa})")
            rows.append(dict(stage=st["name"], isa=isa, flag=ISAS[isa], scalar_ns=scalar, simd_ns=vector,
                             speedup=scalar / vector, bitwise_equal=int(equal), machine=mach))
            table.append([st["name"], f"{isa} ({ISAS[isa]})", f"{scalar:.2f}", f"{vector:.2f}",
                          f"{scalar / vector:.2f}", "equal" if equal else "DIFFERENT"])
    print(f"\nShading stages over 256 lanes, one path at a time against `omp simd` ({mach})")
    print_table(["stage", "build", "scalar ns/lane", "SIMD ns/lane", "speedup", "results"], table, "<<>>><")
    write_csv(Path(args.out) / "simd_stages.csv", rows)
    if differing:
        raise SystemExit(f"the vectorised loop changed the results of: {', '.join(differing)}")
    return rows


if __name__ == "__main__":
    main()
