"""Write files so that a complete-looking file is always a complete file.

Every output is written under a hidden temporary name in the destination folder and renamed over
the final name only once it is complete (rename is atomic on POSIX file systems). A crash, a
Ctrl-C or a full disk leaves at most a hidden `.STEM.tmp-PID.SUFFIX` file behind, never a truncated NAME.
"""

import contextlib
import errno
import os
from pathlib import Path

from rvt2cli.errors import UserError


def temp_path_for(path: Path) -> Path:
    """Hidden, unique per process, and with the same suffix (writers that go by it still work)."""
    return path.with_name(f".{path.stem}.tmp-{os.getpid()}{path.suffix}")


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike):
    """Yield a temporary path to write; on success it is renamed to `path`."""
    path = Path(path)
    tmp = temp_path_for(path)
    try:
        yield tmp
        with open(tmp, "rb+") as f:
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except OSError as e:
        tmp.unlink(missing_ok=True)
        if e.errno == errno.ENOSPC:
            raise UserError(f"{path}: disk full while writing; nothing was written. Free some space and run again.") from None
        raise
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


@contextlib.contextmanager
def atomic_open(path: str | os.PathLike, mode: str = "wb"):
    """Open a temporary file for writing; on success it replaces `path`."""
    with atomic_path(path) as tmp:
        with open(tmp, mode) as f:
            yield f
