"""Turn command-line arguments (files and folders) into episode file paths."""

from pathlib import Path

from rvt2cli.errors import UserError


def episode_paths(args: list[str]) -> list[Path]:
    """Files as given; a folder stands for the `*.mcap` files directly in it (sorted), less hidden ones:
    an interrupted writer leaves its unfinished file under a hidden name (`rvt2cli.atomic`)."""
    paths: list[Path] = []
    for arg in args:
        p = Path(arg)
        if p.is_dir():
            found = sorted(f for f in p.glob("*.mcap") if not f.name.startswith("."))
            if not found:
                raise UserError(f"{p}: folder has no .mcap episode files")
            paths.extend(found)
        else:
            paths.append(p)
    return paths
