"""stage=merge: merge the dataset shards of ``data.dataset`` (written by stage=mppi multiruns) into one version.

A shard is any committed dataset whose manifest says ``shard_of: <data.dataset>``; the latest version of
each shard is merged, in the order one stage=all run would give them (``cell_order``): cell by cell
(data.tasks x data.objects), each cell's parts by their first episode.  So the shards of a paper run made on
several machines (each its own range of episodes, carried here) merge into the episodes of one run.  Shards of
every sweep that wrote to this name are included (a sweep that repeats a job's config reuses its shard): start a
new collection under another ``data.dataset``.  The shards and their order: topocut.data.collection.
"""
from __future__ import annotations

from topocut.data.collection import cell_order, shards_of
from topocut.data.store import MissingArtifact
from topocut.utils.context import RunContext


def run(ctx: RunContext, data, only: list[str] | None = None) -> dict:
    """``only``: merge just these shards (stage=all passes the ones its cells wrote); [] = every shard."""
    from topocut.data.episodes import EpisodeDataset, merge

    shards = shards_of(ctx.store, data.dataset)
    if only:
        missing = [n for n in only if n not in shards]
        if missing:
            raise MissingArtifact(f"stage.run.only: {missing[0]!r} is no shard of {data.dataset!r}; valid: "
                                  f"{', '.join(sorted(shards)) or '(none)'}")
        shards = {n: shards[n] for n in only}
    else:
        shards = {n: shards[n] for n in cell_order(ctx.store, shards, data)}
    if not shards:
        raise MissingArtifact(f"no dataset shards of {data.dataset!r} (manifest shard_of: {data.dataset}) under "
                              f"{ctx.store.root / 'dataset'}; run a multirun first, e.g. "
                              f"`python -m topocut.run -m stage=mppi task=slice,stick data.dataset={data.dataset}`")
    for path in shards.values():
        ctx.store.verify(path)
    inputs = {name: ctx.store.ref(path) for name, path in shards.items()}
    writer, existing = ctx.store.begin("dataset", data.dataset, {"merge_of": sorted(inputs.values())}, inputs)
    if existing is not None:
        return {"dataset": str(existing), "reused": True}
    merge([p / "data.zarr" for p in shards.values()], writer.path / "data.zarr")
    ds = EpisodeDataset(writer.path / "data.zarr")
    summary = {"shards": len(shards), "episodes": ds.num_episodes, "steps": len(ds)}
    path = writer.commit(summary)
    return {"dataset": str(path), **summary}
