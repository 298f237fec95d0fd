"""What `rvt2 serve` runs with, kept apart from the server so that the CLI shows defaults cheaply."""

import ipaddress
import os
from dataclasses import dataclass
from pathlib import Path

from rvt2_client.wire import DEFAULT_PORT, MAX_MESSAGE_BYTES
from rvt2cli.errors import UserError


@dataclass
class ServeOptions:
    host: str = "127.0.0.1"
    port: int = DEFAULT_PORT
    token: str | None = None            # every request must carry it (required off the loopback)
    max_batch: int = 16
    max_wait_ms: float = 5.0            # how long the first request of a batch waits for others
    fixed_batch: bool = False           # every forward pass at max_batch (padded): answers independent of arrivals
    max_message_bytes: int = MAX_MESSAGE_BYTES
    cameras: tuple[str, ...] = ()       # camera names every request must carry
    prepare_threads: int = 4            # requests checked and fused at once


def is_loopback(host: str) -> bool:
    """Whether `host` is this machine's loopback (127.0.0.0/8, ::1, localhost): reachable from this machine alone."""
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def token_from_file(path: str | os.PathLike) -> str:
    """The shared secret in a file (its first line, without surrounding white space)."""
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as e:
        raise UserError(f"{path}: cannot read the token file ({e.strerror}); write a secret into it, e.g. "
                        f"`python -c 'import secrets; print(secrets.token_urlsafe(32))' > {path}`") from None
    token = text.strip().splitlines()[0].strip() if text.strip() else ""
    if len(token) < 16:
        raise UserError(f"{path}: the token is {'empty' if not token else f'{len(token)} characters'}; use at least 16, e.g. "
                        f"`python -c 'import secrets; print(secrets.token_urlsafe(32))' > {path}`")
    return token
