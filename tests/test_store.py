"""Artifact store: versioning, hashing, tamper detection, kill-safety, reuse, resume."""
import json
import subprocess
import sys
import textwrap

import pytest

from topocut.data.store import ArtifactRef, ArtifactStore, CorruptArtifact, MissingArtifact, sha256_file


def _commit(store, name, payload, config):
    writer, existing = store.begin("dataset", name, config)
    assert existing is None
    (writer.path / "data.txt").write_text(payload)
    return writer.commit({"n": len(payload)})


def test_versions_increment_and_manifest_hashes(tmp_path):
    store = ArtifactStore(tmp_path)
    p1 = _commit(store, "demos", "abc", {"k": 1})
    p2 = _commit(store, "demos", "abcd", {"k": 2})
    assert (p1.name, p2.name) == ("v001", "v002")
    assert store.resolve("dataset", "demos") == p2
    assert store.resolve(ArtifactRef.parse("dataset/demos:v001")) == p1
    m = json.loads((p2 / "manifest.json").read_text())
    assert m["files"]["data.txt"] == sha256_file(p2 / "data.txt")
    assert m["config"] == {"k": 2} and m["summary"] == {"n": 4}
    assert "git_sha" in m["provenance"] and "packages" in m["provenance"]


def test_tampered_file_is_refused_with_a_message_naming_it(tmp_path):
    store = ArtifactStore(tmp_path)
    p = _commit(store, "demos", "abc", {"k": 1})
    (p / "data.txt").write_text("abX")
    with pytest.raises(CorruptArtifact, match="data.txt.*sha256.*re-run"):
        store.resolve("dataset", "demos")


def test_missing_artifact_and_version_messages(tmp_path):
    store = ArtifactStore(tmp_path)
    with pytest.raises(MissingArtifact, match="no committed dataset named 'demos'"):
        store.resolve("dataset", "demos")
    _commit(store, "demos", "abc", {"k": 1})
    with pytest.raises(MissingArtifact, match="available: v001"):
        store.resolve("dataset", "demos", "v007")
    with pytest.raises(ValueError, match="valid kinds"):
        store.resolve("datasets", "demos")


def test_same_config_is_reused_not_redone(tmp_path):
    store = ArtifactStore(tmp_path)
    p = _commit(store, "demos", "abc", {"k": 1})
    writer, existing = store.begin("dataset", "demos", {"k": 1})
    assert writer is None and existing == p
    writer, existing = store.begin("dataset", "demos", {"k": 1}, inputs={"sim": "sim/cake:v001"})
    assert existing is None and writer is not None  # different lineage -> new version


def test_killed_writer_leaves_previous_version_intact_and_resumes(tmp_path):
    store = ArtifactStore(tmp_path)
    p1 = _commit(store, "demos", "first", {"k": 1})
    script = textwrap.dedent(f"""
        import os
        from topocut.data.store import ArtifactStore
        store = ArtifactStore({str(tmp_path)!r})
        w, _ = store.begin("dataset", "demos", {{"k": 2}})
        (w.path / "episode_0.txt").write_text("done")
        os._exit(9)  # killed before commit
    """)
    r = subprocess.run([sys.executable, "-c", script])
    assert r.returncode == 9
    assert store.versions("dataset", "demos") == ["v001"]
    assert store.resolve("dataset", "demos") == p1  # still verifies
    writer, existing = store.begin("dataset", "demos", {"k": 2})
    assert writer.resumed and (writer.path / "episode_0.txt").read_text() == "done"
    (writer.path / "episode_1.txt").write_text("done")
    p2 = writer.commit()
    assert sorted(json.loads((p2 / "manifest.json").read_text())["files"]) == ["episode_0.txt", "episode_1.txt"]


def test_racing_commits_to_one_name_both_land_on_distinct_versions(tmp_path, monkeypatch):
    """Two runs of a parallel sweep that both see v001 as free: the second rename fails and retries."""
    store = ArtifactStore(tmp_path)
    a, _ = store.begin("checkpoint", "perception", {"sort": True})
    b, _ = store.begin("checkpoint", "perception", {"sort": False})
    (a.path / "m.txt").write_text("a")
    (b.path / "m.txt").write_text("b")
    pa = a.commit()
    real, calls = ArtifactStore._next_version, []

    def stale_first(self, kind, name):  # b's first look predates a's rename
        calls.append(name)
        return "v001" if len(calls) == 1 else real(self, kind, name)

    monkeypatch.setattr(ArtifactStore, "_next_version", stale_first)
    pb = b.commit()
    assert (pa.name, pb.name, len(calls)) == ("v001", "v002", 2)
    assert (pa / "m.txt").read_text() == "a" and (pb / "m.txt").read_text() == "b"
    assert json.loads((pb / "manifest.json").read_text())["version"] == "v002"
    assert store.versions("checkpoint", "perception") == ["v001", "v002"]


def test_ref_fingerprint_tells_a_recreated_version_number_apart(tmp_path):
    import shutil

    store = ArtifactStore(tmp_path)
    _commit(store, "demos", "abc", {"k": 1})
    v2 = _commit(store, "demos", "abcd", {"k": 2})
    ref = store.ref(v2)
    assert ref.startswith("dataset/demos:v002@") and ref == store.ref(v2)
    w, _ = store.begin("checkpoint", "perception", {"lr": 1}, inputs={"dataset": ref})
    (w.path / "model.ckpt").write_text("weights")
    ckpt = w.commit()
    shutil.rmtree(v2)  # a user deletes the newest version; the next commit takes its number again
    v2b = _commit(store, "demos", "other data", {"k": 3})
    assert v2b.name == "v002" and store.ref(v2b) != ref
    writer, existing = store.begin("checkpoint", "perception", {"lr": 1}, inputs={"dataset": store.ref(v2b)})
    assert existing is None and writer is not None  # not the checkpoint trained on the deleted data
    assert store.begin("checkpoint", "perception", {"lr": 1}, inputs={"dataset": ref})[1] == ckpt


def test_names_lists_only_names_with_a_committed_version(tmp_path):
    store = ArtifactStore(tmp_path)
    store.begin("dataset", "half-written", {"k": 1})  # a partial directory only
    _commit(store, "demos", "abc", {"k": 1})
    assert store.names("dataset") == ["demos"]
    with pytest.raises(MissingArtifact, match=r"known dataset names: \['demos'\]"):
        store.resolve("dataset", "half-written")


def test_a_second_process_writing_the_same_version_is_refused_and_the_first_lands(tmp_path):
    """Two identical runs at once would interleave files in one .partial-<key>; the second must stop clearly."""
    store = ArtifactStore(tmp_path)
    writer, _ = store.begin("dataset", "demos", {"k": 7})
    (writer.path / "a.txt").write_text("first")
    script = textwrap.dedent(f"""
        import sys
        from topocut.data.store import ArtifactBusy, ArtifactStore
        try:
            ArtifactStore({str(tmp_path)!r}).begin("dataset", "demos", {{"k": 7}})
        except ArtifactBusy as e:
            print(e)
            sys.exit(3)
    """)
    r = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True)
    assert r.returncode == 3 and "dataset/demos" in r.stdout and "locked" in r.stdout
    other = subprocess.run([sys.executable, "-c", script.replace('"k": 7', '"k": 8')], capture_output=True, text=True)
    assert other.returncode == 0, other.stderr  # a different config is a different version: not blocked
    path = writer.commit()
    assert (path / "a.txt").read_text() == "first"
    r = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True)
    assert r.returncode == 0, r.stdout + r.stderr  # committed: the lock is released, the version is reused
    assert store.begin("dataset", "demos", {"k": 7}) == (None, path)


def test_ddp_ranks_above_zero_do_not_take_the_lock_and_locks_stay_out_of_versions(tmp_path, monkeypatch):
    """Lightning re-runs the stage on ranks 1..N-1 while rank 0 holds the lock: they must not be refused."""
    store = ArtifactStore(tmp_path)
    w0, _ = store.begin("checkpoint", "perception", {"k": 1})  # rank 0 (no rank variables) holds the lock
    monkeypatch.setenv("LOCAL_RANK", "1")
    w1, _ = store.begin("checkpoint", "perception", {"k": 1})
    assert w1.path == w0.path and w1._lock is None
    monkeypatch.delenv("LOCAL_RANK")
    (w0.path / "m.txt").write_text("rank 0")
    final = w0.commit()
    left = sorted(p.name for p in (tmp_path / "checkpoint" / "perception").iterdir())
    assert left == ["v001"] and sorted(json.loads((final / "manifest.json").read_text())["files"]) == ["m.txt"]


def test_a_tampered_version_is_not_reused(tmp_path):
    """Re-running a finished stage reuses its version only if every file still matches its sha256."""
    store = ArtifactStore(tmp_path)
    w, _ = store.begin("checkpoint", "pddp", {"k": 1})
    (w.path / "model.ckpt").write_bytes(b"weights" * 100)
    path = w.commit()
    assert store.begin("checkpoint", "pddp", {"k": 1}) == (None, path)
    blob = bytearray((path / "model.ckpt").read_bytes())
    blob[10] ^= 0xFF
    (path / "model.ckpt").write_bytes(bytes(blob))
    with pytest.raises(CorruptArtifact, match=r"model\.ckpt does not match its sha256.*delete"):
        store.begin("checkpoint", "pddp", {"k": 1})


def test_a_missing_artifact_names_the_stage_that_makes_it(tmp_path):
    """stage=eval on an empty outputs root: the hint names `make bc` for a policy checkpoint (it named only
    `make mppi` and `make pretrain`), and the n_grid hint agrees with the scales' own grids."""
    from topocut.data.store import ArtifactStore, MissingArtifact
    from topocut.sim.config import SimConfig

    with pytest.raises(MissingArtifact, match=r"make bc"):
        ArtifactStore(tmp_path).resolve("checkpoint", "pddp")
    with pytest.raises(MissingArtifact, match=r"make mppi"):
        ArtifactStore(tmp_path).resolve("dataset", "demos")
    with pytest.raises(ValueError, match=r"n_grid.*48: smoke, 128: paper"):
        SimConfig(n_grid=0).validate()
