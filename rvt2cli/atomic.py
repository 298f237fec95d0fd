"""Write outputs so that a complete-looking output is always a complete output.

Every file and every folder rvt2 writes is first written under a hidden temporary name next to its
destination and renamed into place only once it is complete (a rename is atomic on POSIX file
systems). A crash, a Ctrl-C or a full disk leaves at most a hidden `.NAME.tmp-PID...` behind, never a
truncated file or a half-filled folder under the real name.

    with atomic_open("eval.json", "w") as f: ...          # one file
    with atomic_path("video.mp4") as tmp: writer(tmp)     # one file, written by a library that wants a path
    with atomic_folder("policy/", replace=True) as tmp: ...  # a folder, swapped in as a whole

Errors of the file system (disk full, permission denied, a parent that is a file) become one-line
`UserError`s naming the output.

Every output ends with the permissions a plain `open()` would give a new file (0666 less the umask),
also where the writer made its temporary file private (safetensors writes 0600):
a policy folder copied to a robot must be readable by the robot's user.
"""

import contextlib
import ctypes
import errno
import os
import shutil
import stat
import threading
from pathlib import Path

from rvt2cli.errors import UserError


def temp_path_for(path: Path) -> Path:
    """Hidden, unique per process, and with the same suffix (writers that go by it still work)."""
    return path.with_name(f".{path.stem}.tmp-{os.getpid()}{path.suffix}")


def output_error(path: Path, error: OSError) -> UserError:
    """A file-system error while writing `path`, as the one line a user sees."""
    if error.errno == errno.ENOSPC:
        return UserError(f"{path}: disk full while writing; nothing was written. Free some space and run again.")
    reason = error.strerror or type(error).__name__
    return UserError(f"{path}: cannot write here ({reason}); nothing was written. Choose another output path.")


_WRITE_ERRNOS = {errno.ENOSPC, errno.EDQUOT, errno.EROFS, errno.EACCES, errno.EPERM, errno.ENOTDIR}


def _about_output(error: OSError, *paths: Path) -> bool:
    """Whether an error raised while writing concerns the output (not, say, an input read meanwhile)."""
    if error.filename is None:
        return error.errno in _WRITE_ERRNOS
    return any(os.fsdecode(error.filename) == str(p) for p in paths) or error.errno in {errno.ENOSPC, errno.EDQUOT}


def ensure_folder(path: str | os.PathLike, what: str = "output folder") -> Path:
    """Create `path` (and its parents) if needed; one line if it cannot be created or is not a folder."""
    path = Path(path)
    try:
        path.mkdir(parents=True, exist_ok=True)
    except FileExistsError:
        raise UserError(f"{path}: exists and is not a folder; choose another {what}") from None
    except OSError as e:
        raise UserError(f"{path}: cannot create the {what} ({e.strerror or type(e).__name__}); choose another path") from None
    if not os.access(path, os.W_OK | os.X_OK):
        raise UserError(f"{path}: the {what} is not writable; choose another path")
    return path


def check_folder_can_be_made(path: str | os.PathLike, what: str = "output folder") -> Path:
    """One line now if `path` could not be created (or used) later, without creating anything yet: its
    nearest existing ancestor must be a writable folder (for work that checks its inputs first)."""
    path = Path(path)
    ancestor = path
    while not ancestor.exists() and ancestor != ancestor.parent:
        ancestor = ancestor.parent
    if not ancestor.is_dir():
        raise UserError(f"{path}: cannot create the {what} ({ancestor} is not a folder); choose another path")
    if not os.access(ancestor, os.W_OK | os.X_OK):
        raise UserError(f"{path}: cannot create the {what} ({ancestor} is not writable); choose another path")
    return path


_umask_lock = threading.Lock()


def current_umask() -> int:
    """The process's umask, read without changing it where Linux tells it (/proc), else by a locked round trip."""
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except (OSError, ValueError, IndexError):
        pass
    with _umask_lock:
        mask = os.umask(0o022)
        os.umask(mask)
    return mask


def give_plain_permissions(path: Path) -> None:
    """Set `path`'s permissions to what `open()` would create under the umask (executable bits kept
    where the writer set them)."""
    mask = current_umask()
    mode = 0o666 & ~mask
    if os.stat(path).st_mode & stat.S_IXUSR:
        mode |= 0o111 & ~mask
    os.chmod(path, mode)


def _give_folder_plain_permissions(folder: Path) -> None:
    for root, _, files in os.walk(folder):
        for name in files:
            path = Path(root) / name
            if not path.is_symlink():
                give_plain_permissions(path)


class AtomicFile:
    """A temporary file that becomes `path` on `commit()` and disappears on `discard()` (for writers
    that stream into a file over many calls, like the episode writer)."""

    def __init__(self, path: str | os.PathLike):
        self.path = Path(path)
        self.tmp = temp_path_for(self.path)

    def commit(self) -> Path:
        try:
            with open(self.tmp, "rb+") as f:
                os.fsync(f.fileno())
            give_plain_permissions(self.tmp)
            os.replace(self.tmp, self.path)
        except OSError as e:
            self.discard()
            raise output_error(self.path, e) from None
        return self.path

    def discard(self) -> None:
        self.tmp.unlink(missing_ok=True)


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike):
    """Yield a temporary path to write; on success it is renamed to `path`."""
    target = AtomicFile(path)
    try:
        yield target.tmp
    except OSError as e:
        target.discard()
        if _about_output(e, target.tmp, target.path):
            raise output_error(target.path, e) from None
        raise
    except BaseException:
        target.discard()
        raise
    target.commit()


@contextlib.contextmanager
def atomic_open(path: str | os.PathLike, mode: str = "wb"):
    """Open a temporary file for writing; on success it replaces `path`."""
    with atomic_path(path) as tmp:
        with open(tmp, mode) as f:
            yield f


# --- folders ---------------------------------------------------------------------------------------

_RENAME_EXCHANGE = 2  # renameat2 flag (Linux >= 3.15): swap two paths in one atomic step
_AT_FDCWD = -100


def _exchange(a: Path, b: Path) -> bool:
    """Swap two existing paths atomically; False where the system cannot (then the caller falls back)."""
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        renameat2 = libc.renameat2
    except (OSError, AttributeError):
        return False
    renameat2.argtypes = [ctypes.c_int, ctypes.c_char_p, ctypes.c_int, ctypes.c_char_p, ctypes.c_uint]
    if renameat2(_AT_FDCWD, os.fsencode(a), _AT_FDCWD, os.fsencode(b), _RENAME_EXCHANGE) == 0:
        return True
    if ctypes.get_errno() in (errno.EINVAL, errno.ENOSYS, errno.EOPNOTSUPP):
        return False
    raise OSError(ctypes.get_errno(), os.strerror(ctypes.get_errno()), str(b))


def _swap_into_place(tmp: Path, final: Path) -> None:
    """Put the finished folder `tmp` at `final`, replacing what is there; the old content ends at `tmp`."""
    if not final.exists():
        os.rename(tmp, final)
        return
    if _exchange(tmp, final):
        return
    # No atomic exchange here: two renames, with the old folder kept until the new one is in place.
    old = final.with_name(f".{final.name}.old-{os.getpid()}")
    os.rename(final, old)
    os.rename(tmp, final)
    os.rename(old, tmp)


@contextlib.contextmanager
def atomic_folder(path: str | os.PathLike, replace: bool = False):
    """Yield a temporary folder to fill; on success it takes the place of `path`.

    An existing `path` is replaced only with `replace=True` (the caller checks first that it is one of
    its own outputs); otherwise it is an error. The previous content is deleted only after the new
    folder is in place."""
    final = Path(path)
    if final.exists() and not replace:
        raise UserError(f"{final}: already exists; choose another output path")
    ensure_folder(final.parent, "parent folder")
    tmp = final.with_name(f".{final.name}.tmp-{os.getpid()}")
    shutil.rmtree(tmp, ignore_errors=True)  # our own leftover from an earlier crash of this process id
    try:
        tmp.mkdir()
        yield tmp
        _give_folder_plain_permissions(tmp)
        _swap_into_place(tmp, final)
    except OSError as e:
        shutil.rmtree(tmp, ignore_errors=True)
        if e.filename is None or str(tmp) in os.fsdecode(e.filename) or str(final) in os.fsdecode(e.filename) \
                or e.errno in _WRITE_ERRNOS:
            raise output_error(final, e) from None
        raise
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    shutil.rmtree(tmp, ignore_errors=True)  # now the previous content, if there was any
