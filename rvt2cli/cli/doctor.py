"""`rvt2 doctor`: what this machine gives rvt2: versions, the GPU, and the Vulkan driver the simulator
renders with (NVIDIA's where it works, else Mesa's lavapipe on the CPU)."""


def register(subparsers) -> None:
    p = subparsers.add_parser("doctor", help="check this machine: versions, GPU, the simulator's Vulkan driver",
                              description="Print what rvt2 finds on this machine, one line each, and which Vulkan driver the "
                                          "simulator uses (override with RVT2_VULKAN=nvidia|lavapipe).")
    p.add_argument("--no-render-check", action="store_true", help="skip choosing (and probing) the Vulkan driver")
    p.set_defaults(run=run)


def _version(module: str) -> str:
    from importlib import import_module

    try:
        return getattr(import_module(module), "__version__", "installed")
    except Exception as e:  # noqa: BLE001 - a broken install is what doctor is for
        return f"MISSING ({type(e).__name__}: {str(e)[:80]})"


def run(args) -> int:
    import platform

    import torch

    from rvt2cli import __version__

    lines = [("rvt2", __version__), ("python", platform.python_version()), ("torch", torch.__version__)]
    if torch.cuda.is_available():
        names = [torch.cuda.get_device_name(i) for i in range(torch.cuda.device_count())]
        lines.append(("CUDA", f"{len(names)} GPU(s): {', '.join(names)}"))
    else:
        lines.append(("CUDA", "no GPU (training and inference on the CPU)"))
    for label, module in (("numpy", "numpy"), ("warp", "warp"), ("sapien", "sapien"), ("mani-skill", "mani_skill"),
                          ("mplib", "mplib"), ("mcap", "mcap"), ("ROS bags", "rosbags"), ("onnxruntime", "onnxruntime"),
                          ("websockets", "websockets"), ("msgpack", "msgpack")):  # rvt2 serve, --shared-policy
        lines.append((label, _version(module)))
    if not args.no_render_check:
        from rvt2cli.runtime import use_vulkan_driver

        driver = use_vulkan_driver()
        lines.append(("Vulkan", f"{driver.name} ({driver.icd}): {driver.why}"))
    width = max(len(label) for label, _ in lines)
    for label, value in lines:
        print(f"{label:<{width}}  {value}")
    return 0
