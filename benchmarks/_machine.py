"""What every benchmark prints first: the CPU, its vector instructions and the thread count.

A ratio measured on one machine is not a property of the design; these lines
let a reader compare figures from AMD and Intel, AVX2 and AVX-512 machines.
"""

from __future__ import annotations

import os
import platform
import subprocess


def cpu_model() -> str:
    """The CPU model name (lscpu's "Model name", else /proc/cpuinfo's, else platform's)."""
    try:
        out = subprocess.run(["lscpu"], capture_output=True, text=True, timeout=10).stdout
        for line in out.splitlines():
            if line.startswith("Model name:"):
                return line.split(":", 1)[1].strip()
    except (OSError, subprocess.SubprocessError):
        pass
    try:
        with open("/proc/cpuinfo") as handle:
            for line in handle:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def cpu_flags() -> set[str]:
    try:
        with open("/proc/cpuinfo") as handle:
            for line in handle:
                if line.startswith("flags"):
                    return set(line.split(":", 1)[1].split())
    except OSError:
        pass
    return set()


def vector_isa(flags: set[str] | None = None) -> str:
    """The widest x86 vector instruction set: AVX-512, AVX2, AVX or SSE (or the machine)."""
    flags = cpu_flags() if flags is None else flags
    fma = "+FMA" if "fma" in flags else ""
    if "avx512f" in flags:
        return "AVX-512" + fma
    if "avx2" in flags:
        return "AVX2" + fma
    if "avx" in flags:
        return "AVX"
    if "sse2" in flags:
        return "SSE2"
    return platform.machine()


def machine_line() -> str:
    """One header line: CPU model, vector ISA, cores, Python."""
    return (
        f"machine: {cpu_model()} ({platform.machine()}, {vector_isa()}), "
        f"{os.cpu_count()} cores; Python {platform.python_version()}"
    )
