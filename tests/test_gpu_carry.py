"""benchmarks/gpu.sh pack / fetch / unpack: an outputs tree larger than one device call carries, moved in pieces.

The pieces come back a few per call (the device tool returns at most 64 MiB) and travel to the next machine a few
per call; unpack must say what is missing until every piece is there, refuse a corrupted piece, and then give back
exactly the tree that was packed.
"""
from __future__ import annotations

import os
import shutil
import subprocess
from pathlib import Path

import numpy as np

SCRIPT = Path(__file__).resolve().parent.parent / "benchmarks" / "gpu.sh"


def _gpu_sh(phase: str, cwd: Path, **env) -> subprocess.CompletedProcess:
    return subprocess.run(["bash", str(SCRIPT), phase], cwd=cwd, capture_output=True, text=True,
                          env={**os.environ, **{k: str(v) for k, v in env.items()}})


def _tree(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def test_a_run_moves_between_machines_in_pieces_and_arrives_whole(tmp_path):
    src = tmp_path / "o"  # an outputs root: an incompressible dataset chunk, a manifest, a nested partial
    (src / "dataset" / "demos" / "v001" / "data.zarr").mkdir(parents=True)
    (src / "dataset" / "demos" / "v001" / "data.zarr" / "c0").write_bytes(
        np.random.default_rng(0).integers(0, 256, 3_500_000, dtype=np.uint8).tobytes())
    (src / "dataset" / "demos" / "v001" / "manifest.json").write_text('{"episodes": 3}')
    (src / "dataset" / "demos-slice-cake" / ".partial-ab12").mkdir(parents=True)
    (src / "dataset" / "demos-slice-cake" / ".partial-ab12" / "episodes.jsonl").write_text('{"episode": 0}\n')
    want = _tree(src)

    pack, work = tmp_path / "pack", tmp_path / "work"
    work.mkdir()
    out = _gpu_sh("pack", work, ROOT=src, PACK_DIR=pack, OUT=tmp_path / "out0", PART_MB=1)
    assert out.returncode == 0, out.stderr
    pieces = sorted(p.name for p in pack.glob("o.tgz.*"))
    assert len(pieces) == 4  # 3.5 MB of random bytes gzip to ~3.5 MB: four pieces of 1 MiB at most
    assert "4 pieces" in out.stdout

    # two calls bring the pieces back (2 + the rest), each with the checksums
    for i, (start, count) in enumerate(((0, 2), (2, 5))):
        got = _gpu_sh("fetch", work, PACK_DIR=pack, OUT=tmp_path / f"back{i}", FROM=start, COUNT=count)
        assert got.returncode == 0, got.stderr
    assert sorted(p.name for p in (tmp_path / "back0").glob("o.tgz.*")) == pieces[:2]
    assert sorted(p.name for p in (tmp_path / "back1").glob("o.tgz.*")) == pieces[2:]

    # the next machine: the first call carries one batch of pieces, unpack says what is still missing
    dst, pack2 = tmp_path / "o2", tmp_path / "pack2"
    shutil.copytree(tmp_path / "back0", work / ".carry" / "a")
    first = _gpu_sh("unpack", work, ROOT=dst, PACK_DIR=pack2, CARRY=work / ".carry")
    assert first.returncode == 3 and "still missing " + " ".join(pieces[2:]) in first.stdout
    assert not dst.exists()

    # a piece damaged on the way is refused (exit 2), nothing unpacked
    shutil.copytree(tmp_path / "back1", work / ".carry" / "b")
    bad = work / ".carry" / "b" / pieces[-1]
    good = bad.read_bytes()
    bad.write_bytes(good[:-1] + bytes([good[-1] ^ 1]))
    damaged = _gpu_sh("unpack", work, ROOT=dst, PACK_DIR=pack2, CARRY=work / ".carry")
    assert damaged.returncode == 2 and "checksum" in damaged.stderr
    assert not dst.exists()

    # the piece carried again, intact: the tree arrives byte for byte
    (pack2 / pieces[-1]).unlink()
    bad.write_bytes(good)
    done = _gpu_sh("unpack", work, ROOT=dst, PACK_DIR=pack2, CARRY=work / ".carry")
    assert done.returncode == 0, done.stdout + done.stderr
    assert _tree(dst) == want


def test_pack_paths_carries_only_the_named_globs(tmp_path):
    """PACK_PATHS: a machine's demonstration shards without its own merge of them (dataset/demos)."""
    src = tmp_path / "o"
    for name in ("demos", "demos-slice-cake-e0-9", "demos-dice-ham-e0-9", "other"):
        (src / "dataset" / name / "v001").mkdir(parents=True)
        (src / "dataset" / name / "v001" / "manifest.json").write_text(f'{{"name": "{name}"}}')
    (src / "runs").mkdir()
    (src / "runs" / "log.txt").write_text("x")
    work = tmp_path / "work"
    work.mkdir()
    out = _gpu_sh("pack", work, ROOT=src, PACK_DIR=tmp_path / "pack", OUT=tmp_path / "out", PACK_PATHS="dataset/demos-*")
    assert out.returncode == 0, out.stderr
    shutil.copytree(tmp_path / "pack", work / ".carry" / "a")
    done = _gpu_sh("unpack", work, ROOT=tmp_path / "o2", PACK_DIR=tmp_path / "pack2", CARRY=work / ".carry")
    assert done.returncode == 0, done.stdout + done.stderr
    assert sorted(_tree(tmp_path / "o2")) == ["dataset/demos-dice-ham-e0-9/v001/manifest.json",
                                              "dataset/demos-slice-cake-e0-9/v001/manifest.json"]


def test_pack_of_a_live_tree_warns_and_still_packs_but_a_failed_tar_fails(tmp_path):
    """tar's status 1 (files changed while read: a run still writing) leaves usable pieces; 2 (fatal) fails."""
    src = tmp_path / "o"
    (src / "dataset").mkdir(parents=True)
    (src / "dataset" / "f.txt").write_text("x")
    fake = tmp_path / "bin"
    fake.mkdir()
    real = shutil.which("tar")
    for status in (1, 2):
        (fake / "tar").write_text(f"#!/bin/bash\n{real} \"$@\"\nexit {status}\n")
        (fake / "tar").chmod(0o755)
        out = _gpu_sh("pack", tmp_path, ROOT=src, PACK_DIR=tmp_path / f"pack{status}", OUT=tmp_path / "out",
                      PATH=f"{fake}:{os.environ['PATH']}")
        if status == 1:
            assert out.returncode == 0 and "changed while packing" in out.stdout
            assert (tmp_path / "pack1" / "SHA256SUMS").read_text().count("o.tgz.") == 1
        else:
            assert out.returncode == 1 and not (tmp_path / "pack2" / "SHA256SUMS").exists()
