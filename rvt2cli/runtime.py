"""Process-wide settings: the Vulkan driver the simulator renders with, the random generators an
episode draws from, and worker processes that end with the process that started them."""

import contextlib
import ctypes
import itertools
import json
import multiprocessing
import os
import random
import signal
import sys
from dataclasses import dataclass
from pathlib import Path

LAVAPIPE_ICD = Path("/usr/share/vulkan/icd.d/lvp_icd.json")
# Where NVIDIA's driver installs its Vulkan ICD manifest (distribution packages, the .run installer,
# and NVIDIA's container runtime, which mounts the driver under /usr/local/nvidia).
NVIDIA_ICDS = (Path("/usr/share/vulkan/icd.d/nvidia_icd.json"), Path("/etc/vulkan/icd.d/nvidia_icd.json"),
               Path("/usr/local/share/vulkan/icd.d/nvidia_icd.json"),
               Path("/usr/local/nvidia/share/vulkan/icd.d/nvidia_icd.json"))
CHOICE_VARIABLE = "RVT2_VULKAN"   # auto (default) | nvidia | lavapipe
_CHOSEN = "RVT2_VULKAN_CHOSEN"    # set by rvt2 once chosen, so worker processes inherit the choice


@dataclass(frozen=True)
class VulkanDriver:
    name: str             # "nvidia", "lavapipe", or "yours" (VK_ICD_FILENAMES / VK_DRIVER_FILES set by you)
    icd: str | None       # the ICD manifest used
    why: str              # one line for `rvt2 doctor`


def _nvidia_renders(icd: Path) -> str | None:
    """None if SAPIEN finds an NVIDIA rendering device through this ICD, else why not. Runs in a
    separate process: a driver that fails can abort the process that loads it."""
    import subprocess
    import sys

    if not Path("/dev/nvidiactl").exists():
        return "no /dev/nvidiactl (no NVIDIA kernel driver)"
    env = {**os.environ, "VK_ICD_FILENAMES": str(icd), "VK_DRIVER_FILES": str(icd)}
    code = "import sapien; print(sapien.render.get_device_summary())"
    try:
        probe = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=120)
    except (subprocess.TimeoutExpired, OSError) as e:
        return f"probe failed ({type(e).__name__})"
    if probe.returncode != 0:
        lines = [line for line in probe.stderr.strip().splitlines() if line.strip()]
        return lines[-1][:120] if lines else f"probe exited with {probe.returncode}"
    if "Supported: 1" not in probe.stdout or "llvmpipe" in probe.stdout:
        return "SAPIEN found no NVIDIA device through it"
    return None


def _is_lavapipe(manifest: str) -> bool:
    """Whether a Vulkan ICD manifest loads Mesa's lavapipe (libvulkan_lvp.so), wherever it is installed."""
    try:
        library = json.loads(Path(manifest).read_text())["ICD"]["library_path"]
    except (OSError, ValueError, KeyError, TypeError):
        return False
    return isinstance(library, str) and Path(library).name.startswith("libvulkan_lvp")


def choose_vulkan_driver() -> VulkanDriver:
    """The Vulkan driver SAPIEN should render with: NVIDIA's where it works, else Mesa's lavapipe (CPU).

    RVT2_VULKAN=nvidia or lavapipe forces one; VK_ICD_FILENAMES or VK_DRIVER_FILES set by you are used
    as they are, and count as lavapipe where they name it (a lavapipe installed outside the system's
    folders: SAPIEN must then be asked for its CPU device). The choice is probed once per run and
    inherited by worker processes."""
    from rvt2cli.errors import UserError

    wanted = os.environ.get(CHOICE_VARIABLE, "auto").strip().lower()
    if wanted not in ("auto", "nvidia", "lavapipe"):
        raise UserError(f"{CHOICE_VARIABLE}={wanted!r}: choose auto, nvidia or lavapipe")
    if os.environ.get(_CHOSEN):
        name, _, icd = os.environ[_CHOSEN].partition(":")
        return VulkanDriver(name, icd or None, "chosen earlier in this run")
    user = os.environ.get("VK_DRIVER_FILES") or os.environ.get("VK_ICD_FILENAMES")
    if user and wanted in ("auto", "lavapipe") and all(_is_lavapipe(m) for m in user.split(os.pathsep)):
        return VulkanDriver("lavapipe", user, "VK_ICD_FILENAMES/VK_DRIVER_FILES name Mesa's lavapipe")
    if user and wanted == "auto":
        return VulkanDriver("yours", user, "VK_ICD_FILENAMES/VK_DRIVER_FILES set in the environment")
    problems = []
    if wanted in ("auto", "nvidia"):
        for icd in NVIDIA_ICDS:
            if icd.is_file():
                problem = _nvidia_renders(icd)
                if problem is None:
                    return VulkanDriver("nvidia", str(icd), "NVIDIA GPU renders")
                problems.append(f"{icd}: {problem}")
        if wanted == "nvidia":
            raise UserError(f"{CHOICE_VARIABLE}=nvidia but no NVIDIA Vulkan driver works here "
                            f"({'; '.join(problems) or 'no NVIDIA ICD manifest found'}); unset it to render on the CPU")
    if LAVAPIPE_ICD.is_file():
        why = "no NVIDIA Vulkan driver works here" if wanted == "auto" else f"{CHOICE_VARIABLE}=lavapipe"
        return VulkanDriver("lavapipe", str(LAVAPIPE_ICD), why + (f" ({problems[0]})" if problems else ""))
    raise UserError("no Vulkan driver for the simulator: install Mesa's lavapipe (`make setup` does) or an NVIDIA driver")


def use_vulkan_driver() -> VulkanDriver:
    """Choose the driver (see `choose_vulkan_driver`) and point SAPIEN and the Vulkan loader at it."""
    driver = choose_vulkan_driver()
    if driver.name in ("nvidia", "lavapipe"):
        os.environ["VK_ICD_FILENAMES"] = os.environ["VK_DRIVER_FILES"] = driver.icd
    os.environ[_CHOSEN] = f"{driver.name}:{driver.icd or ''}"
    return driver


def seed_everything(seed: int) -> None:
    """Every random generator a simulated episode draws from: Python's, numpy's, torch's, the C
    library's (mplib's inverse-kinematics restarts draw from it, through pinocchio's random
    configurations) and OMPL's (mplib's RRTConnect), so that an episode is the same in any process."""
    import numpy as np
    import torch

    random.seed(seed)
    np.random.seed(seed % 2**32)
    torch.manual_seed(seed)
    ctypes.CDLL(None).srand(seed % 2**32)
    _reset_ompl_generator()


OMPL_SEED = 1


def _reset_ompl_generator() -> None:
    """OMPL seeds each new generator from one process-wide seed generator. mplib does not expose it,
    but its bundled libompl exports `ompl::RNG::setSeed`: the first call (before any planning) fixes
    the seed, later calls rewind the seed generator to it, so every episode draws the same sequence.
    OMPL's own log is silenced (it calls a rewind an error)."""
    import glob
    import importlib.util

    spec = importlib.util.find_spec("mplib")
    if spec is None or not spec.origin:
        return
    import mplib  # noqa: F401 - loads libompl's dependencies first

    found = glob.glob(os.path.join(os.path.dirname(spec.origin), "..", "mplib.libs", "libompl-*.so*"))
    if not found:
        return
    lib = ctypes.CDLL(found[0])
    lib._ZN4ompl3msg11setLogLevelENS0_8LogLevelE(ctypes.c_int(4))  # ompl::msg::LOG_NONE
    lib._ZN4ompl3RNG7setSeedEm(ctypes.c_ulong(OMPL_SEED))


PR_SET_PDEATHSIG = 1  # linux/prctl.h


def end_with_parent() -> None:
    """Call first in a worker process (record, eval): when the process that started it ends, even killed
    with SIGTERM, which runs none of its clean-up, the worker gets SIGTERM too, instead of finishing its
    episode and moving a file into a folder whose command has ended. Linux only; elsewhere a no-op.
    (Linux signals the worker when the *thread* that started it ends: rvt2's pools start their workers
    from the main thread, in `submit`.)"""
    if not sys.platform.startswith("linux"):
        return
    starter = multiprocessing.parent_process()
    ctypes.CDLL(None, use_errno=True).prctl(PR_SET_PDEATHSIG, int(signal.SIGTERM), 0, 0, 0)
    if starter is not None and os.getppid() != starter.pid:  # it ended before the call above
        os.kill(os.getpid(), signal.SIGTERM)


# Thread pools a simulator worker would otherwise size to the whole machine: OpenMP, the BLAS libraries
# numpy and torch link, and Mesa's software rasteriser (lavapipe renders with LP_NUM_THREADS threads).
_THREAD_VARIABLES = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")
RENDER_THREADS = "LP_NUM_THREADS"


# Reading episodes in parallel (extract-keyframes, train): at least this many files per worker process,
# whose start (its imports) takes about as long as reading 20 of them.
FILES_PER_WORKER = 32


def usable_cores() -> int:
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1


def render_threads(workers: int) -> dict[str, str]:
    """The render-thread limit for `workers` simulators sharing this machine: lavapipe's threads, cores //
    workers each. Commands that run side by side give their children the limit of all their workers
    together (`benchmarks/experiment.py`), since each pool alone would count only its own."""
    return {RENDER_THREADS: str(max(1, usable_cores() // workers))}


@contextlib.contextmanager
def worker_pool(workers: int, initializer=None, initargs=(), gpus: str = "one"):
    """A pool of `workers` processes (the simulators of record and eval, the readers of extract-keyframes
    and train) that share the machine instead of each sizing its thread pools to all of it: numerical
    libraries run one thread per process, and lavapipe renders with cores // workers. On a 32-core machine
    30 workers otherwise start about 70 threads each, and spend their time switching between them. The
    limits are read when a library starts, which in a spawned process is before any initializer runs, so
    they travel in the environment the processes are started with; variables you set yourself are kept.
    `gpus`: "one", each worker sees one of the machine's GPUs in turn (see `_start_worker`); "all", where a
    worker must find a GPU by its number (`--device cuda:1`); "none", where workers need no GPU (readers,
    simulators rendering with lavapipe), so that they open no CUDA context at all."""
    from concurrent.futures import ProcessPoolExecutor

    limits = {name: "1" for name in _THREAD_VARIABLES} | render_threads(workers)
    saved = {name: os.environ.get(name) for name in limits}
    for name, value in limits.items():
        os.environ.setdefault(name, value)
    context = multiprocessing.get_context("spawn")  # SAPIEN does not survive fork
    started = context.Value("i", 0)  # numbers the workers as they start: their places in the pool
    try:
        with ProcessPoolExecutor(workers, mp_context=context, initializer=_start_worker,
                                 initargs=(started, _worker_gpus(gpus), initializer, initargs)) as pool:
            yield pool
    finally:
        for name, value in saved.items():
            if value is None:
                os.environ.pop(name, None)


def file_workers(workers: int, files: int) -> int:
    """How many processes `map_over_files` reads `files` files with, given up to `workers`."""
    return max(1, min(workers, files // FILES_PER_WORKER))


def map_over_files(function, paths, *args, workers: int = 1):
    """`function(path, *args)` for each path, yielded in the order of `paths`: in worker processes
    (`file_workers` of them) where the files are many enough, else in this process. Files are
    independent, so the results are the same either way."""
    processes = file_workers(workers, len(paths))
    if processes == 1:
        for path in paths:
            yield function(path, *args)
        return
    with worker_pool(processes, gpus="none") as pool:
        yield from pool.map(function, paths, *(itertools.repeat(a) for a in args))


def torch_device(name: str):
    """The torch device `--device NAME` asks for ("auto": CUDA where torch sees a GPU, else the CPU), refused in one
    line where it names CUDA on a machine without one (instead of a traceback from a worker much later)."""
    import torch

    from rvt2cli.errors import UserError

    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        device = torch.device(name)
    except RuntimeError:
        raise UserError(f"--device {name}: not a torch device; give cpu, cuda or cuda:N") from None
    if device.type == "cuda" and not torch.cuda.is_available():
        raise UserError(f"--device {name}: no CUDA GPU is available here (torch {torch.__version__}); use --device cpu")
    return device


_worker_index: int | None = None  # this process's place in its pool (0, 1, ...); None outside a pool


def visible_gpus() -> list[str]:
    """The CUDA devices this process may use, named as CUDA_VISIBLE_DEVICES names them."""
    if (listed := os.environ.get("CUDA_VISIBLE_DEVICES")) is not None:
        return [name.strip() for name in listed.split(",") if name.strip()]
    import torch

    return [str(index) for index in range(torch.cuda.device_count())]


def _worker_gpus(gpus: str) -> list[str] | None:
    """What `_start_worker` makes visible: one of these per worker, none ([]), or what this process sees
    (None: "all", or "one" on a machine of at most one GPU)."""
    if gpus not in ("one", "all", "none"):
        raise ValueError(f"gpus={gpus!r}: one, all or none")
    if gpus == "none":
        return []
    if gpus == "all":
        return None
    listed = visible_gpus()
    return listed if len(listed) > 1 else None


def _start_worker(started, gpus, initializer, initargs) -> None:
    global _worker_index
    end_with_parent()
    with started.get_lock():
        _worker_index = started.value
        started.value += 1
    # On a machine of several GPUs each worker sees one of them, in turn: an evaluation's workers (each with
    # its copy of the policy) share every GPU instead of crowding the first, and a worker opens one CUDA
    # context, not one per GPU (ManiSkill's torch.random.fork_rng opens them all). Set before the worker
    # first touches CUDA: unpickling the initializer and its arguments imports neither torch nor SAPIEN.
    if gpus == []:
        os.environ["CUDA_VISIBLE_DEVICES"] = ""
    elif gpus is not None:
        os.environ["CUDA_VISIBLE_DEVICES"] = gpus[_worker_index % len(gpus)]
    import torch

    torch.set_num_threads(1)  # the same arithmetic in every process, whatever the number of workers
    if initializer is not None:
        initializer(*initargs)

