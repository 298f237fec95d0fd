"""The offline GPU kit's packing: the site's compressed stream is cut into pieces that each fit one 64 MiB
transfer beside the working tree (scripts/offline-gpu-host/pack_gpu_wheels.sh --resplit), and cut again, the
same bytes, when the tree grows."""

import os
import shutil
import subprocess
from pathlib import Path

ROOT = Path(__file__).parent.parent
MiB = 1 << 20


def _kit_repo(tmp_path: Path, tree_mib: int) -> Path:
    """A git repository holding the packing script and a file that makes its tree `tree_mib` MiB."""
    repo = tmp_path / "repo"
    kit = repo / "scripts" / "offline-gpu-host"
    kit.mkdir(parents=True)
    shutil.copy(ROOT / "scripts" / "offline-gpu-host" / "pack_gpu_wheels.sh", kit)
    (repo / ".gitignore").write_text("/.gpu/\n")
    with open(repo / "results.bin", "wb") as f:  # untracked files travel too; sparse: only its size counts
        f.truncate(tree_mib * MiB - 64 * 1024)  # the rest of the MiB: the script and .gitignore
    subprocess.run(["git", "init", "-q"], cwd=repo, check=True)
    return repo


def _stash_pieces(repo: Path, stream: bytes, piece_mib: int) -> None:
    gpu = repo / ".gpu"
    gpu.mkdir(exist_ok=True)
    for i in range(0, len(stream), piece_mib * MiB):
        (gpu / f"site.part.a{chr(ord('a') + i // (piece_mib * MiB))}").write_bytes(stream[i:i + piece_mib * MiB])
    subprocess.run("sha256sum site.part.* > site.sha256", shell=True, cwd=gpu, check=True)


def _resplit(repo: Path) -> subprocess.CompletedProcess:
    return subprocess.run(["bash", "scripts/offline-gpu-host/pack_gpu_wheels.sh", "--resplit"], cwd=repo,
                          capture_output=True, text=True)


def test_resplit_cuts_the_same_stream_to_the_room_beside_the_tree(tmp_path):
    repo = _kit_repo(tmp_path, tree_mib=40)
    stream = os.urandom(50 * MiB + 12345)
    _stash_pieces(repo, stream, piece_mib=20)

    r = _resplit(repo)
    assert r.returncode == 0, r.stderr
    pieces = sorted((repo / ".gpu").glob("site.part.*"))
    # 64 MiB a transfer, 40 MiB of tree, 2 MiB kept for commits: 22 MiB pieces
    assert [p.stat().st_size for p in pieces[:-1]] == [22 * MiB] * (len(pieces) - 1)
    assert "3 pieces of 22 MiB beside the 40 MiB working tree" in r.stdout
    assert b"".join(p.read_bytes() for p in pieces) == stream
    check = subprocess.run(["sha256sum", "-c", "site.sha256"], cwd=repo / ".gpu", capture_output=True, text=True)
    assert check.returncode == 0 and check.stdout.count(": OK") == len(pieces)


def test_resplit_refuses_missing_or_damaged_pieces_and_a_tree_with_no_room(tmp_path):
    repo = _kit_repo(tmp_path, tree_mib=10)
    r = _resplit(repo)
    assert r.returncode == 1 and "no .gpu/site.sha256 here; pack the site first" in r.stderr
    stream = os.urandom(3 * MiB)
    _stash_pieces(repo, stream, piece_mib=1)
    with open(repo / ".gpu" / "site.part.ab", "r+b") as f:
        f.write(b"\0")
    r = _resplit(repo)
    assert r.returncode != 0 and "FAILED" in r.stderr + r.stdout
    # left as they were (a re-cut would make one 52 MiB piece): nothing cut from a damaged stream
    assert [p.stat().st_size for p in sorted((repo / ".gpu").glob("site.part.*"))] == [MiB] * 3

    full = _kit_repo(tmp_path / "full", tree_mib=59)
    _stash_pieces(full, stream, piece_mib=1)
    r = _resplit(full)
    assert r.returncode == 1
    assert "the working tree is 59 MiB; a 64 MiB transfer has no room for a piece" in r.stderr
    assert len(list((full / ".gpu").glob("site.part.*"))) == 3  # the old pieces stay
