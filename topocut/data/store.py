"""A versioned artifact store on the local file system.

Layout::

    <root>/<kind>/<name>/<version>/        committed, immutable
        manifest.json                      schema, sha256 of every file, config, lineage, provenance
        ...files...
    <root>/<kind>/<name>/.partial-<key>/   work in progress of one config (resumable)

A version directory appears only through ``os.replace`` of a fully written
partial directory, so a writer killed half-way leaves earlier versions intact
and its own partial work in place for the next run with the same config to
resume from.  Two runs with the same config and inputs share one key: a
finished one is reused instead of being redone.
"""
from __future__ import annotations

import hashlib
import json
import logging
import os
import re
import shutil
import subprocess
import sys
import time
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

SCHEMA_VERSION = 1  # of manifest.json; a manifest with another one is refused, never guessed at
KINDS = ("dataset", "checkpoint", "eval", "sim")
_VERSION_RE = re.compile(r"^v(\d{3,})$")
# No '/' and no leading '.': a name is one directory directly under <root>/<kind>, never '..' or a hidden one
NAME_PATTERN = r"[A-Za-z0-9][A-Za-z0-9._-]*"
_NAME_RE = re.compile(rf"^{NAME_PATTERN}$")


# which stage makes each kind of artifact (the hint of a MissingArtifact)
PRODUCED_BY = {"dataset": "`make mppi` (or stage=mppi, stage=teleop) for demonstrations",
               "checkpoint": "`make pretrain` for the perception checkpoint, `make bc` for the policies' "
                             "(or `make run`: every stage in order)",
               "sim": "`make simulate`", "eval": "`make eval`"}


class MissingArtifact(FileNotFoundError):
    """A requested artifact (kind/name/version) does not exist."""


class ArtifactBusy(RuntimeError):
    """Another process is writing the same version (same kind, name and key) right now."""


class CorruptArtifact(RuntimeError):
    """A committed artifact's files do not match its manifest (or it has none)."""


class UnsupportedSchema(CorruptArtifact):
    """An artifact written in a layout this version of topocut does not read (manifest or data schema)."""


class InvalidName(ValueError):
    """An artifact name that would not stay one directory under its kind."""


def check_name(kind: str, name: str, key: str | None = None) -> str:
    """``name`` if it is a valid artifact name; ``key`` (e.g. ``data.dataset``) is the setting it came from."""
    if kind not in KINDS:
        raise ValueError(f"unknown artifact kind {kind!r}; valid kinds: {', '.join(KINDS)}")
    if not isinstance(name, str) or not _NAME_RE.match(name):
        raise InvalidName(f"{key or kind + ' name'}={name!r} is not a valid artifact name: it must match "
                          f"{NAME_PATTERN} (letters, digits, '.', '_', '-'; no '/'), so that it is stored as "
                          f"<outputs_root>/{kind}/<name>")
    return name


@dataclass(frozen=True)
class ArtifactRef:
    kind: str
    name: str
    version: str = "latest"

    @classmethod
    def parse(cls, text: str, default_kind: str | None = None) -> ArtifactRef:
        """``kind/name[:version]`` or ``name[:version]`` with ``default_kind``."""
        body, _, version = text.partition(":")
        kind, _, name = body.rpartition("/")
        kind = kind or default_kind
        if not kind or not name:
            raise ValueError(f"artifact reference {text!r} must look like 'kind/name[:version]' with kind in {KINDS}")
        return cls(kind, check_name(kind, name), version or "latest")

    def __str__(self) -> str:
        return f"{self.kind}/{self.name}:{self.version}"


def sha256_file(path: Path, chunk: int = 1 << 20) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while block := f.read(chunk):
            h.update(block)
    return h.hexdigest()


def config_key(config: Any, inputs: Iterable[str] = ()) -> str:
    """Stable short hash of a (JSON-able) config and the resolved input versions."""
    blob = json.dumps({"config": config, "inputs": sorted(inputs)}, sort_keys=True, default=str)
    return hashlib.sha256(blob.encode()).hexdigest()[:16]


def write_atomic(path, write) -> Path:
    """``write(tmp)`` to a temporary name beside ``path`` (the same suffix: writers such as imageio's pick the format by
    it), then os.replace: the file is whole or absent (a killed run's ``.*.tmp-*`` leftover is dropped by the
    artifact's commit)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.stem}.tmp-{os.getpid()}{path.suffix}")
    try:
        write(tmp)
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return path


def write_json_atomic(path: Path, obj: Any) -> Path:
    """Write to a temp file in the same directory, then os.replace: readers see the old or the new file,
    never half of one."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    try:
        with open(tmp, "w") as f:
            json.dump(obj, f, indent=1, sort_keys=True, default=str)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)  # a full disk must not leave half a file behind
        raise
    return path


def provenance() -> dict:
    """git SHA and dirty flag, package versions, interpreter."""
    def git(*args: str) -> str | None:
        try:
            return subprocess.run(["git", *args], capture_output=True, text=True, timeout=5,
                                  cwd=Path(__file__).resolve().parent).stdout.strip() or None
        except (OSError, subprocess.SubprocessError):
            return None

    from importlib import metadata

    packages = {}
    for pkg in ("topocut", "taichi", "warp-lang", "torch", "lightning", "hydra-core", "zarr", "numpy", "scipy"):
        try:
            packages[pkg] = metadata.version(pkg)
        except metadata.PackageNotFoundError:
            packages[pkg] = None
    return {
        "git_sha": git("rev-parse", "HEAD"),
        "git_dirty": bool(git("status", "--porcelain")),
        "packages": packages,
        "python": sys.version.split()[0],
        "created": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
    }


def _distributed_rank() -> int:
    """This process's global rank as Lightning's launchers and Slurm set it (0 outside distributed runs)."""
    for var in ("RANK", "LOCAL_RANK", "SLURM_PROCID"):
        if os.environ.get(var, "").isdigit():
            return int(os.environ[var])
    return 0


class VersionWriter:
    """Work area for one new version; ``commit()`` hashes, writes the manifest and renames."""

    def __init__(self, store: ArtifactStore, kind: str, name: str, key: str, config: Any,
                 inputs: dict[str, str], extra: dict | None = None, lock=None):
        self.store, self.kind, self.name, self.key = store, kind, name, key
        self.config, self.inputs, self.extra = config, inputs, dict(extra or {})
        self.path = store.root / kind / name / f".partial-{key}"
        self._lock = lock  # held until commit/abandon; the OS drops it if the process dies (resume works)
        self.resumed = self.path.exists()
        if self.resumed:
            logging.getLogger("topocut").info("resuming %s/%s from %s (work an interrupted run committed is kept)",
                                              kind, name, self.path)
        self.path.mkdir(parents=True, exist_ok=True)
        self.committed: Path | None = None

    def commit(self, summary: dict | None = None) -> Path:
        files = {}
        for p in sorted(self.path.rglob("*")):
            if not p.is_file():
                continue
            rel = str(p.relative_to(self.path))
            if ".tmp-" in p.name:  # a killed atomic write's leftover: the version holds exactly its listed files
                p.unlink()
            elif rel != "manifest.json":
                files[rel] = sha256_file(p)
        manifest = {
            "schema_version": SCHEMA_VERSION, "kind": self.kind, "name": self.name, "key": self.key,
            "files": files, "config": self.config, "inputs": self.inputs,
            "summary": summary or {}, "provenance": provenance(), **self.extra,
        }
        # Runs of a parallel sweep (joblib/submitit) may commit to the same name at once: the rename is
        # the arbiter.  Renaming onto an existing (non-empty) version fails, and the loser takes the next.
        for _ in range(1000):
            version = self.store._next_version(self.kind, self.name)
            write_json_atomic(self.path / "manifest.json", {**manifest, "version": version})
            final = self.store.root / self.kind / self.name / version
            try:
                os.rename(self.path, final)
            except OSError:
                if final.exists():
                    continue
                raise
            self.committed = final
            self._release()
            return final
        raise RuntimeError(f"could not commit {self.kind}/{self.name}: no free version after 1000 tries")

    def abandon(self) -> None:
        shutil.rmtree(self.path, ignore_errors=True)
        self._release()

    def _release(self) -> None:
        if self._lock is not None:
            self._lock.release(force=True)
            self._lock = None


class ArtifactStore:
    def __init__(self, root: str | os.PathLike):
        self.root = Path(root).resolve()
        self.root.mkdir(parents=True, exist_ok=True)

    # -- reading ------------------------------------------------------------
    def _numbered(self, kind: str, name: str) -> list[str]:
        """Every ``vNNN`` directory, committed or not (a copy interrupted before its manifest counts too)."""
        d = self.root / kind / check_name(kind, name)
        if not d.is_dir():
            return []
        return sorted((p.name for p in d.iterdir() if p.is_dir() and _VERSION_RE.match(p.name)),
                      key=lambda v: int(v[1:]))

    def versions(self, kind: str, name: str) -> list[str]:
        """The committed versions (those with a manifest), oldest first."""
        return [v for v in self._numbered(kind, name) if (self.root / kind / name / v / "manifest.json").exists()]

    def names(self, kind: str) -> list[str]:
        """Names with at least one version directory (a name holding only partial work is not listed)."""
        d = self.root / kind
        return sorted(p.name for p in d.iterdir() if p.is_dir() and _NAME_RE.match(p.name)
                      and self._numbered(kind, p.name)) if d.is_dir() else []

    def ref(self, path: Path) -> str:
        """``kind/name:version@fingerprint`` of a committed version, for a consumer's ``inputs``.

        The fingerprint hashes the manifest's key and file digests: a version number that comes back after its
        directory was deleted (numbers continue from the highest one left) names different content, and the
        consumers keyed by it are not reused by mistake.
        """
        path = Path(path)
        m = self.manifest(path)
        blob = json.dumps({"key": m.get("key"), "files": m.get("files", {})}, sort_keys=True)
        return f"{path.parent.parent.name}/{path.parent.name}:{path.name}@{hashlib.sha256(blob.encode()).hexdigest()[:12]}"

    def resolve(self, kind: str | ArtifactRef, name: str | None = None, version: str = "latest",
                verify: bool = True) -> Path:
        ref = kind if isinstance(kind, ArtifactRef) else ArtifactRef(kind, name, version)
        check_name(ref.kind, ref.name)
        numbered = self._numbered(ref.kind, ref.name)
        if not numbered:
            known = self.names(ref.kind)
            raise MissingArtifact(
                f"no committed {ref.kind} named {ref.name!r} under {self.root / ref.kind}; "
                f"known {ref.kind} names: {known or 'none'}. Run the stage that produces it first "
                f"({PRODUCED_BY.get(ref.kind, 'see docs/architecture.md')}).")
        # latest is the highest-numbered directory: one without a manifest is refused, not silently skipped
        version = numbered[-1] if ref.version == "latest" else ref.version
        if version not in numbered:
            raise MissingArtifact(f"{ref.kind}/{ref.name} has no version {ref.version!r}; "
                                  f"available: {', '.join(self.versions(ref.kind, ref.name)) or 'none'} (or 'latest')")
        path = self.root / ref.kind / ref.name / version
        if not (path / "manifest.json").is_file():
            raise CorruptArtifact(f"{path} has no manifest.json (an interrupted copy or a hand-made directory), so "
                                  f"nothing in it can be verified; restore its manifest, or delete {path} (or pin "
                                  f"another version: {', '.join(self.versions(ref.kind, ref.name)) or 'none'})")
        if verify:
            self.verify(path)
        return path

    def manifest(self, path: Path) -> dict:
        mpath = Path(path) / "manifest.json"
        try:
            m = json.loads(mpath.read_text())
        except (OSError, json.JSONDecodeError) as e:
            raise CorruptArtifact(f"{mpath}: unreadable manifest ({e}); delete {path} and re-run the stage") from e
        if not isinstance(m, dict) or m.get("schema_version") != SCHEMA_VERSION or not isinstance(m.get("files"), dict):
            found = m.get("schema_version") if isinstance(m, dict) else type(m).__name__
            raise UnsupportedSchema(f"{mpath}: schema_version {found!r} is not supported; this topocut reads "
                                    f"schema_version {SCHEMA_VERSION}. Read {path} with the topocut that wrote it, "
                                    f"or delete it and re-run the stage that made it")
        return m

    def verify(self, path: Path) -> dict:
        """Check that the version holds exactly the manifest's files, each with its sha256; raise
        CorruptArtifact naming the file.  An unlisted file counts: zarr stores no chunk equal to the fill
        value, so one written after the commit changes what readers see without touching a listed file."""
        path = Path(path)
        manifest = self.manifest(path)
        for f in sorted(path.rglob("*")):
            rel = str(f.relative_to(path))
            if f.is_file() and rel != "manifest.json" and rel not in manifest["files"]:
                raise CorruptArtifact(f"{f} is not listed in {path}/manifest.json (added after the commit); "
                                      f"remove it, or delete {path} and re-run the stage that made it")
        for rel, digest in manifest["files"].items():
            f = Path(path) / rel
            if not f.exists():
                raise CorruptArtifact(f"{f} is listed in {path}/manifest.json but missing; "
                                      f"delete {path} and re-run the stage that made it")
            if sha256_file(f) != digest:
                raise CorruptArtifact(f"{f} does not match its sha256 in {path}/manifest.json "
                                      f"(modified or truncated); delete {path} and re-run the stage that made it")
        return manifest

    def find_by_key(self, kind: str, name: str, key: str) -> Path | None:
        for v in reversed(self.versions(kind, name)):  # a directory without a manifest has no key to match
            p = self.root / kind / name / v
            if self.manifest(p).get("key") == key:
                return p
        return None

    # -- writing ------------------------------------------------------------
    def _next_version(self, kind: str, name: str) -> str:
        vs = self._numbered(kind, name)  # past every directory, manifest or not: a rename onto one would fail
        return f"v{(int(vs[-1][1:]) + 1 if vs else 1):03d}"

    def begin(self, kind: str, name: str, config: Any, inputs: dict[str, str] | None = None,
              extra: dict | None = None) -> tuple[VersionWriter | None, Path | None]:
        """Start (or resume) a version.  Returns (writer, None), or (None, existing) if the same
        config and inputs were already committed, so the caller can reuse it."""
        check_name(kind, name)
        inputs = dict(inputs or {})
        key = config_key(config, [f"{k}={v}" for k, v in inputs.items()])
        existing = self.find_by_key(kind, name, key)
        if existing is not None:
            self.verify(existing)  # reused only if intact: CorruptArtifact names the file and the way out
            return None, existing
        if _distributed_rank() > 0:  # a DDP rank re-running the stage: rank 0 holds the lock and commits
            return VersionWriter(self, kind, name, key, config, inputs, extra), None
        # Two identical runs (a re-launched sweep beside the first) would write one .partial-<key> at once.
        # An OS file lock (filelock: flock/LockFileEx) refuses the second; a killed run's lock dies with it.
        # Lock files live in <root>/.locks, outside every version directory (filelock leaves them on disk).
        # One instance per path in this process (is_singleton), so a stage retried in-process re-enters it.
        from filelock import FileLock, Timeout

        lock_path = self.root / ".locks" / f"{kind}-{name}-{key}.lock"
        lock_path.parent.mkdir(parents=True, exist_ok=True)
        lock = FileLock(lock_path, is_singleton=True)
        try:
            lock.acquire(timeout=0)
        except Timeout:
            raise ArtifactBusy(f"{kind}/{name}: another process is writing this version (.partial-{key}; "
                               f"{lock_path} is locked); wait for it to finish (its result will then be reused) "
                               "or give this run a different config or seed") from None
        existing = self.find_by_key(kind, name, key)  # committed while we took the lock
        if existing is not None:
            lock.release(force=True)
            return None, existing
        return VersionWriter(self, kind, name, key, config, inputs, extra, lock=lock), None
