"""The machine a benchmark ran on, for the header of every table and plot."""
from __future__ import annotations

import csv
import datetime
import os
import platform
from pathlib import Path


def _cpuinfo() -> tuple:
    """The CPU's model name and flags from /proc/cpuinfo (flags empty if unreadable)."""
    name, flags = platform.processor() or "unknown CPU", []
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name") and name == (platform.processor() or "unknown CPU"):
                    name = line.split(":", 1)[1].strip()
                elif line.startswith("flags"):
                    flags = line.split(":", 1)[1].split()
                    break
    except OSError:
        pass
    return name, flags


def simd(levels=("avx512f", "avx2", "avx"), flags=None) -> str:
    """The widest of the x86 vector extensions `levels` (widest first) among the CPU's flags
    (read from /proc/cpuinfo unless given), or ''."""
    flags = _cpuinfo()[1] if flags is None else flags
    return next((f for f in levels if f in flags), "")


def built_for() -> str:
    """What torch_rbpt's extension was compiled for: its widest vector extension and the
    tuning setup.py chose, e.g. 'avx512, tuned for sapphirerapids'."""
    from torch_rbpt import _C
    tune = getattr(_C, "build_tune", "")
    return f"{_C.build_isa}, tuned for {tune}" if tune else _C.build_isa


def cpu_model() -> str:
    """The CPU's model name from /proc/cpuinfo, with its widest vector extension."""
    name, flags = _cpuinfo()
    widest = simd(flags=flags)
    return f"{name} ({widest})" if widest else name


def status_mb(field: str) -> float:
    """A memory figure of this process in MB from /proc/self/status: 'VmRSS' (resident set)
    or 'VmHWM' (its high-water mark). Raises where the field is missing: a memory benchmark
    without its figure has nothing to report."""
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith(field + ":"):
                return int(line.split()[1]) / 1024.0
    raise RuntimeError(f"no {field} line in /proc/self/status")


def machine() -> str:
    """CPU, cores, torch and its thread count, date: one line."""
    import torch
    return (f"{cpu_model()}, {os.cpu_count()} cores, torch {torch.__version__} "
            f"({torch.get_num_threads()} threads), {platform.system()}, "
            f"{datetime.datetime.now().strftime('%Y-%m-%d %H:%M')}")


def write_csv(path: Path, rows: list) -> None:
    """Write `rows` (dicts) to the CSV file `path`, its columns the rows' keys in order of first
    appearance, and say so."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fields = list(dict.fromkeys(k for r in rows for k in r))
    with open(path, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=fields)
        w.writeheader()
        w.writerows(rows)
    print(f"wrote {shown(path)}")


def shown(path: Path, root: Path = Path(__file__).resolve().parent.parent) -> Path:
    """`path` as printed: relative to the checkout (`root`) when inside it, else absolute.
    (A relative `path`, e.g. --out benchmarks/results/avx2 from the Makefile, is resolved
    first: relative_to() of a relative path against an absolute root raises.)"""
    where = Path(path).resolve()
    return where.relative_to(root) if where.is_relative_to(root) else where
