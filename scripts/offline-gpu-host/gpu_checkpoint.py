"""Carry a trained checkpoint off a GPU machine without network access in pieces, and put it back together.

Such a host returns at most 64 MiB per transfer, in files of at most 16 MiB. On the GPU machine:

    python3 scripts/offline-gpu-host/gpu_checkpoint.py shrink RUN_DIR OUT_DIR     # config, and fp16 weights and the
                                                                                  # instruction embeddings in 15 MiB pieces
                                                                                  # (--exact: float32 weights)

and on the machine that receives them, once every piece has come back into one folder:

    python scripts/offline-gpu-host/gpu_checkpoint.py restore PIECES_DIR RUN_DIR  # a run folder that rvt2 eval/export/render read

Pieces come back at 15 MiB (a returned file's limit), but go out to a GPU machine one per transfer beside the
working tree; before carrying them there, cut them to the room the tree leaves (the site pieces' rule):

    python scripts/offline-gpu-host/gpu_checkpoint.py resplit PIECES_DIR          # fewer transfers, the same bytes

The weights travel as float16 (half the size) and are restored to float32; config.json records this.
Training ran under bf16 autocast, so every matrix product already used weights rounded to 8 significant
bits; float16 keeps 11. With --exact they travel as trained: an evaluation resumed on another machine
then runs the very model its first episodes ran. With --resumable the training goes on elsewhere: the exact
weights, the optimiser's and the generators' state (training_state.pt) and the run's logs (run.json,
train.csv, validation.csv) travel, and `rvt2 train --out RUN_DIR --resume` there continues the schedule as
if it had never stopped (a run stopped by `rvt2 train --time-limit`; the data must be at the same path).
"""

import argparse
import hashlib
import io
import json
import shutil
import subprocess
import sys
import tarfile
from pathlib import Path

import torch
from safetensors.torch import load, load_file, save, save_file

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # the repository root
from rvt2cli.atomic import atomic_folder, atomic_open  # noqa: E402
from rvt2cli.train.checkpoint import CONFIG, INSTRUCTIONS, STATE, WEIGHTS, checkpoint_folder, resolve  # noqa: E402

PIECE = 15 * 2**20
RUN_LOGS = ("run.json", "train.csv", "validation.csv")   # what a resumed run reads back from its folder


def _split(blob: bytes, stem: str, out: Path, piece: int = PIECE) -> list[str]:
    """`blob` as files STEM.partNNN of at most `piece` bytes in `out`; their names, in order."""
    names = []
    for i in range(0, len(blob), piece):
        names.append(f"{stem}.part{i // piece:03d}")
        (out / names[-1]).write_bytes(blob[i:i + piece])
    return names


def _join(pieces_dir: Path, names: list[str], sha256: str, what: str) -> bytes:
    missing = [p for p in names if not (pieces_dir / p).is_file()]
    if missing:
        sys.exit(f"{pieces_dir}: missing {', '.join(missing)}")
    blob = b"".join((pieces_dir / p).read_bytes() for p in names)
    if hashlib.sha256(blob).hexdigest() != sha256:
        sys.exit(f"{pieces_dir}: the pieces do not add up to the {what} that were sent (sha256 differs)")
    return blob


def _pieces(blob: bytes, stem: str, out: Path, piece: int = PIECE) -> dict:
    return {"pieces": _split(blob, stem, out, piece), "sha256": hashlib.sha256(blob).hexdigest()}


def _run_logs(run: Path) -> bytes:
    buffer = io.BytesIO()
    with tarfile.open(fileobj=buffer, mode="w") as tar:
        for name in RUN_LOGS:
            if (run / name).is_file():
                tar.add(run / name, arcname=name)
    return buffer.getvalue()


def shrink(run: Path, out: Path, exact: bool = False, resumable: bool = False) -> None:
    """`exact`: the weights as trained (float32, twice the pieces), for an evaluation that goes on elsewhere
    with `rvt2 eval --resume` and must run the model its first episodes ran. `resumable`: exact, and what
    `rvt2 train --resume` needs besides (the training state and the run's logs)."""
    exact = exact or resumable
    ckpt = resolve(run)
    if resumable and not (ckpt / STATE).is_file():
        sys.exit(f"{ckpt}: has no {STATE} (a checkpoint restored for evaluation); it cannot be trained on")
    out.mkdir(parents=True, exist_ok=True)
    weights = load_file(str(ckpt / WEIGHTS))
    dtype = torch.float32 if exact else torch.float16
    blob = save({k: (v.to(dtype) if v.is_floating_point() else v).contiguous() for k, v in weights.items()})
    pieces = _split(blob, "weights", out)
    # the instruction embeddings (every phrasing of every variation: 68 MB for rvt2-18) travel in pieces too
    instructions = (ckpt / INSTRUCTIONS).read_bytes()
    instruction_pieces = _split(instructions, "instructions", out)
    config = json.loads((ckpt / CONFIG).read_text())
    if not exact:
        config["transfer"] = {"weights_dtype": "float16", "note": "weights rounded to float16 to leave the GPU machine"}
    (out / CONFIG).write_text(json.dumps(config, indent=2))
    manifest = {"step": config["step"], "pieces": pieces, "sha256": hashlib.sha256(blob).hexdigest(),
                "instruction_pieces": instruction_pieces,
                "instructions_sha256": hashlib.sha256(instructions).hexdigest()}
    size = len(blob) + len(instructions)
    if resumable:
        state, logs = (ckpt / STATE).read_bytes(), _run_logs(run)
        manifest["state"], manifest["run_logs"] = _pieces(state, "state", out), _pieces(logs, "run_logs", out)
        size += len(state) + len(logs)
    (out / "manifest.json").write_text(json.dumps(manifest, indent=2))
    print(f"{ckpt}: {len(all_pieces(manifest))} pieces, {size / 2**20:.1f} MiB")


def all_pieces(manifest: dict) -> list[str]:
    """Every piece a manifest names, in the order they are sent: weights, instructions, then what resuming needs."""
    return (manifest["pieces"] + manifest["instruction_pieces"]
            + [p for part in ("state", "run_logs") if part in manifest for p in manifest[part]["pieces"]])


def _manifest(pieces_dir: Path) -> dict:
    if not (pieces_dir / "manifest.json").is_file():
        hint = "`tar -xf meta.tar` there first" if (pieces_dir / "meta.tar").is_file() else \
            "give the folder the pieces came back into (gpu_onebox.sh weights)"
        sys.exit(f"{pieces_dir}: no manifest.json; {hint}")
    return json.loads((pieces_dir / "manifest.json").read_text())


def carry_room_mib() -> int:
    """MiB a piece may have to travel beside today's working tree: pack_gpu_wheels.sh owns the rule."""
    r = subprocess.run(["bash", str(Path(__file__).with_name("pack_gpu_wheels.sh")), "--room"],
                       capture_output=True, text=True)
    if r.returncode != 0:
        sys.exit(r.stderr.strip() or f"pack_gpu_wheels.sh --room failed ({r.returncode})")
    return int(r.stdout)


def resplit(pieces_dir: Path, piece_mib: float | None = None) -> None:
    """Cut every part of a pieces folder again, `piece_mib` MiB a piece (default: the room beside the tree):
    each part is checked against its sha256 first, and the folder is replaced only once the new one is whole."""
    manifest = _manifest(pieces_dir)
    piece = int((piece_mib if piece_mib is not None else carry_room_mib()) * 2**20)
    if piece < 1:
        sys.exit(f"--piece-mib {piece_mib}: a piece must hold at least one byte")
    parts = [("weights", "pieces", "sha256", "weights"),
             ("instructions", "instruction_pieces", "instructions_sha256", "instruction embeddings")]
    blobs = {stem: _join(pieces_dir, manifest[key], manifest[sha], what) for stem, key, sha, what in parts if key in manifest}
    for stem, what in (("state", "training state"), ("run_logs", "run's logs")):
        if stem in manifest:
            blobs[stem] = _join(pieces_dir, manifest[stem]["pieces"], manifest[stem]["sha256"], what)
    old = set(all_pieces(manifest))
    with atomic_folder(pieces_dir, replace=True) as new:
        for f in pieces_dir.iterdir():  # config.json and anything else of the user's; meta.tar held the old manifest
            if f.is_file() and f.name not in old and f.name not in ("manifest.json", "meta.tar"):
                shutil.copy2(f, new / f.name)
        for stem, key, _, _ in parts:
            if stem in blobs:
                manifest[key] = _split(blobs[stem], stem, new, piece)
        for stem in ("state", "run_logs"):
            if stem in blobs:
                manifest[stem] = _pieces(blobs[stem], stem, new, piece)
        (new / "manifest.json").write_text(json.dumps(manifest, indent=2))
    print(f"{pieces_dir}: {len(old)} pieces cut again into {len(all_pieces(manifest))} of at most {piece / 2**20:g} MiB")


def restore(pieces_dir: Path, run: Path) -> None:
    manifest = _manifest(pieces_dir)
    blob = _join(pieces_dir, manifest["pieces"], manifest["sha256"], "weights")
    if "instruction_pieces" in manifest:
        instructions = _join(pieces_dir, manifest["instruction_pieces"], manifest["instructions_sha256"],
                             "instruction embeddings")
    else:  # sent whole by an earlier version of this script
        instructions = (pieces_dir / INSTRUCTIONS).read_bytes()
    weights = {k: (v.float() if v.is_floating_point() else v).contiguous() for k, v in load(blob).items()}
    state = _join(pieces_dir, manifest["state"]["pieces"], manifest["state"]["sha256"], "training state") \
        if "state" in manifest else None
    folder = checkpoint_folder(run, manifest["step"])
    with atomic_folder(folder, replace=True) as final:  # readable by all, as rvt2's own
        save_file(weights, str(final / WEIGHTS))
        shutil.copy(pieces_dir / CONFIG, final / CONFIG)
        (final / INSTRUCTIONS).write_bytes(instructions)
        if state is not None:
            (final / STATE).write_bytes(state)
    if "run_logs" in manifest:
        logs = _join(pieces_dir, manifest["run_logs"]["pieces"], manifest["run_logs"]["sha256"], "run's logs")
        with tarfile.open(fileobj=io.BytesIO(logs)) as tar:
            for log in RUN_LOGS:   # only these names: nothing else of the archive is written
                if log in tar.getnames():
                    with atomic_open(run / log, "wb") as f:
                        f.write(tar.extractfile(log).read())
    with atomic_open(run / "last", "w") as f:
        f.write(f"checkpoints/{folder.name}\n")
    print(f"{run}: checkpoint {folder.name} restored ({sum(v.numel() for v in weights.values()) / 1e6:.1f} M weights"
          + ("; training state and logs: `rvt2 train --out RUN --resume` continues it)" if state is not None else ")"))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="command", required=True)
    s = sub.add_parser("shrink")
    s.add_argument("run", type=Path)
    s.add_argument("out", type=Path)
    s.add_argument("--exact", action="store_true", help="float32 weights, as trained (default: float16, half the pieces)")
    s.add_argument("--resumable", action="store_true",
                   help="exact weights, the training state and the run's logs: training goes on elsewhere with --resume")
    r = sub.add_parser("restore")
    r.add_argument("pieces", type=Path)
    r.add_argument("run", type=Path)
    c = sub.add_parser("resplit", help="cut a pieces folder again, to the room a transfer leaves beside the tree")
    c.add_argument("pieces", type=Path)
    c.add_argument("--piece-mib", type=float, help="MiB a piece (default: the room beside the working tree)")
    args = parser.parse_args()
    if args.command == "shrink":
        shrink(args.run, args.out, args.exact, args.resumable)
    elif args.command == "resplit":
        resplit(args.pieces, args.piece_mib)
    else:
        restore(args.pieces, args.run)


if __name__ == "__main__":
    torch.set_grad_enabled(False)
    main()
