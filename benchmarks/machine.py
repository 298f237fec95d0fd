"""Describe the machine a benchmark ran on (recorded next to every number)."""

import os
import platform
from importlib.metadata import PackageNotFoundError, version

from rvt2cli.runtime import usable_cores


def cpu_model() -> str:
    try:
        for line in open("/proc/cpuinfo"):
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown CPU"


def describe() -> dict:
    info = {"cpu": cpu_model(), "cores": os.cpu_count(), "python": platform.python_version(), "platform": platform.platform()}
    usable = usable_cores()
    if usable != info["cores"]:  # pinned (taskset, a container's CPU set): the cores the benchmark could use
        info["usable_cores"] = usable
    for package in ("torch", "warp-lang", "mani-skill", "sapien", "rvt2"):
        try:
            info[package] = version(package)
        except PackageNotFoundError:
            pass
    try:
        import torch

        if torch.cuda.is_available():
            info["gpu"] = torch.cuda.get_device_name(0)
    except ImportError:
        pass
    return info
