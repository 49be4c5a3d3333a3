"""The machine a benchmark ran on, for the header of every table and plot."""
from __future__ import annotations

import datetime
import os
import platform


def cpu_model() -> str:
    """The CPU's model name from /proc/cpuinfo, with its widest vector extension."""
    name, flags = platform.processor() or "unknown CPU", []
    try:
        for line in open("/proc/cpuinfo"):
            if line.startswith("model name") and name == (platform.processor() or "unknown CPU"):
                name = line.split(":", 1)[1].strip()
            elif line.startswith("flags"):
                flags = line.split(":", 1)[1].split()
                break
    except OSError:
        pass
    simd = next((f for f in ("avx512f", "avx2", "avx") if f in flags), "")
    return f"{name} ({simd})" if simd else name


def machine() -> str:
    """CPU, cores, torch and its thread count, date: one line."""
    import torch
    return (f"{cpu_model()}, {os.cpu_count()} cores, torch {torch.__version__} "
            f"({torch.get_num_threads()} threads), {platform.system()}, "
            f"{datetime.datetime.now().strftime('%Y-%m-%d %H:%M')}")
