"""Where a result was measured: the machine (CPU, its vector / int8 instruction sets, cores, load,
library versions) and the commit, stored with every benchmark and evaluation result."""

from __future__ import annotations

import importlib.metadata
import os
import platform
import subprocess
from pathlib import Path
from typing import Any

from shared.paths import REPO_ROOT

# The CPU flags that decide which onnxruntime kernels run (fp32 SIMD width, int8 dot products).
VECTOR_FLAGS = (
    "sse4_2",
    "avx",
    "avx2",
    "fma",
    "f16c",
    "avx512f",
    "avx512bw",
    "avx512vl",
    "avx512_vnni",
    "avx_vnni",
    "avx512_bf16",
    "amx_tile",
    "amx_int8",
    "amx_bf16",
)


def machine_info() -> dict[str, Any]:
    cpu_model = platform.processor()
    try:
        lines = Path("/proc/cpuinfo").read_text().splitlines()
    except OSError:
        lines = []
    model = next((line for line in lines if line.startswith("model name")), None)
    if model is not None:
        cpu_model = model.split(":", 1)[1].strip()
    present = next((set(line.split(":", 1)[1].split()) for line in lines if line.startswith("flags")), set())
    flags = [f for f in VECTOR_FLAGS if f in present]
    info: dict[str, Any] = {
        "platform": platform.platform(),
        "machine": platform.machine(),
        "cpu_model": cpu_model,
        "cpu_vector_flags": flags,
        "cpu_count": os.cpu_count(),
        "cpu_affinity_count": len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else None,
        "python": platform.python_version(),
        "zenoh": importlib.metadata.version("eclipse-zenoh"),
        "protobuf": importlib.metadata.version("protobuf"),
        "onnxruntime": importlib.metadata.version("onnxruntime"),
    }
    if hasattr(os, "getloadavg"):
        info["loadavg_at_start"] = os.getloadavg()
    return info


def git_commit(repo: Path = REPO_ROOT, ignore: tuple[str, ...] = ()) -> str:
    """Short commit of `repo`, "+dirty" with uncommitted changes (outside the paths `ignore`); "unknown"
    outside a git checkout."""
    try:
        head = subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, cwd=repo
        )
        excluded = [f":!{path}" for path in ignore]
        dirty = subprocess.run(
            ["git", "status", "--porcelain", "--", ".", *excluded], capture_output=True, text=True, cwd=repo
        )
    except OSError:
        return "unknown"
    if head.returncode != 0:
        return "unknown"
    return head.stdout.strip() + ("+dirty" if dirty.stdout.strip() else "")
