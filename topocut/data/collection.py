"""A demonstration collection: the shards stage=mppi writes (``shard_of: <data.dataset>``), the order stage=merge
joins them in, and each run's episode log (``episodes.jsonl``).  Shared by the stages (pipelines.merge,
pipelines.mppi) and the collection's report (topocut.data.report)."""
from __future__ import annotations

import json
import os


def shards_of(store, dataset: str) -> dict:
    """{shard name: path of its latest version} for the shards of ``dataset``."""
    out = {}
    for name in store.names("dataset"):
        if name == dataset:
            continue
        path = store.resolve("dataset", name, verify=False)
        if store.manifest(path).get("shard_of") == dataset:
            out[name] = path
    return out


def cell_order(store, shards: dict, data) -> list[str]:
    """Shard names sorted by (task in data.tasks, object in data.objects, first episode, name); a task or object
    not listed sorts after the listed ones."""
    tasks, objects = list(data.tasks or []), list(data.objects or [])

    def key(name):
        config = store.manifest(shards[name])["config"]
        task, obj = config.get("task", {}).get("name"), config.get("object", {}).get("name")
        return (tasks.index(task) if task in tasks else len(tasks), objects.index(obj) if obj in objects
                else len(objects), int(config.get("first_episode", 0)), name)
    return sorted(shards, key=key)


def read_records(path, repair: bool = False) -> list[dict]:
    """The episode log's records, one per episode (the last one written: a re-run episode logs twice).

    A record is logged before its episode is committed, so a run killed while writing one leaves a torn last
    line whose episode is not committed and runs again: that line is dropped (``repair``: from the file too,
    so that the next record starts on a line of its own).  An unreadable line before the last raises,
    naming the file and the line.
    """
    latest = {}
    if not path.exists():
        return []
    text = path.read_text()
    lines = text.splitlines()
    last = max((i for i, line in enumerate(lines) if line.strip()), default=-1)
    keep = len(lines)
    for i, line in enumerate(lines):
        if not line.strip():
            continue
        try:
            r = json.loads(line)
            latest[r["episode"]] = r
        except (json.JSONDecodeError, KeyError, TypeError) as e:
            if i != last:
                raise ValueError(f"{path}, line {i + 1}: not an episode record ({e}); only the last line may be "
                                 f"torn (a killed run): fix or delete this one") from e
            keep = i
    if repair and (keep < len(lines) or (text and not text.endswith("\n"))):
        tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
        tmp.write_text("".join(line + "\n" for line in lines[:keep]))
        os.replace(tmp, path)
    return [latest[e] for e in sorted(latest)]
