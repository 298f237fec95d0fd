"""The evaluation journal: `episodes.jsonl` in the output folder, one JSON line per finished episode,
appended (and flushed to disk) the moment the episode finishes. A crash of a simulator process, a
kill or a power cut keeps every finished episode; `rvt2 eval --resume` with the same options runs only
the episodes the journal does not have yet.

    line 1     {"rvt2_eval_journal": 1, "plan": {...the options that decide which episodes run...}}
    line 2..   one episode record (rvt2cli.eval.report.episode_record)
"""

import gzip
import json
import lzma
import os
from pathlib import Path

from rvt2cli.atomic import atomic_open
from rvt2cli.errors import UserError

NAME = "episodes.jsonl"
FORMAT = 1
# published results keep their journals and logs as xz (-9e: 28% smaller than gzip -9); gzip copies read too
COMPRESSED = {".gz": gzip.decompress, ".xz": lzma.decompress}


def read_text(path: Path) -> str:
    """A text file as written, or its .gz or .xz copy, by its suffix."""
    decompress = COMPRESSED.get(path.suffix)
    return decompress(path.read_bytes()).decode() if decompress else path.read_text()


def copy_in(folder: Path, name: str) -> Path | None:
    """`name` in `folder`, or its compressed copy; None where there is neither."""
    return next((p for p in (folder / name, *(folder / f"{name}{s}" for s in COMPRESSED)) if p.exists()), None)


def episode_key(record: dict) -> tuple[str, str, int]:
    return record["source"], record["task"], record["seed"]


def read_journal(path: Path) -> tuple[dict, list[dict]]:
    """(plan, episode records) of a journal (or of its compressed copy, as kept with published results); a last
    line cut off by a kill is left out."""
    text = read_text(path)
    lines = text.split("\n")[:-1]  # what follows the last newline is an unfinished line
    try:
        plan = json.loads(lines[0])["plan"]
    except (IndexError, json.JSONDecodeError, KeyError, TypeError):
        raise UserError(f"{path}: not an rvt2 evaluation journal; choose another --out") from None
    plan.setdefault("insertion_search", False)  # written before the executor could search: it pushed straight
    try:
        return plan, [json.loads(line) for line in lines[1:]]
    except json.JSONDecodeError:
        raise UserError(f"{path}: damaged journal line; choose another --out") from None


def read_records(journals) -> list[dict]:
    """The episode records of several journals (or their compressed copies), in order; one that cannot be read
    is refused in one line."""
    records = []
    for path in journals:
        try:
            records += read_journal(Path(path))[1]
        except OSError as error:
            raise UserError(f"{path}: cannot read it ({error.strerror}); give an evaluation's episodes.jsonl") from None
    return records


class Journal:
    def __init__(self, out_dir: Path, plan: dict, resume: bool):
        self.path = out_dir / NAME
        self.records: list[dict] = []
        if self.path.exists():
            if not resume:
                raise UserError(f"{out_dir}: holds an evaluation already ({NAME}); pass --resume to continue it, "
                                "or choose another --out")
            self.records = self._read(plan)
        else:
            with atomic_open(self.path, "w") as f:
                f.write(json.dumps({"rvt2_eval_journal": FORMAT, "plan": plan}) + "\n")

    def _read(self, plan: dict) -> list[dict]:
        text = self.path.read_text()
        if text and not text.endswith("\n"):  # the line being written when the run was killed: drop it
            with atomic_open(self.path, "w") as f:
                f.write(text[: text.rfind("\n") + 1])
        stored, records = read_journal(self.path)
        changed = [k for k in sorted(set(plan) | set(stored)) if plan.get(k) != stored.get(k)]
        if changed:
            k = changed[0]
            raise UserError(f"{self.path}: was run with {k} = {stored.get(k)!r}, this command has {plan.get(k)!r}; "
                            "--resume needs the same options (or choose another --out)")
        return records

    @property
    def finished(self) -> set[tuple[str, str, int]]:
        return {episode_key(r) for r in self.records}

    def append(self, record: dict) -> None:
        self.records.append(record)
        with open(self.path, "a") as f:
            f.write(json.dumps(record) + "\n")
            f.flush()
            os.fsync(f.fileno())
