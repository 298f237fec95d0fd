"""Process-wide settings the simulator and the renderer need before they are imported."""

import os
from pathlib import Path

LAVAPIPE_ICD = Path("/usr/share/vulkan/icd.d/lvp_icd.json")


def use_software_vulkan_if_unset() -> None:
    """Point SAPIEN at Mesa's lavapipe (CPU Vulkan) unless the user chose an ICD.

    SAPIEN otherwise prefers its bundled NVIDIA ICD whenever `nvidia-smi` exists, which fails on
    machines without a usable GPU driver. Set VK_ICD_FILENAMES yourself to render on a GPU.
    """
    if "VK_ICD_FILENAMES" not in os.environ and LAVAPIPE_ICD.exists():
        os.environ["VK_ICD_FILENAMES"] = str(LAVAPIPE_ICD)
