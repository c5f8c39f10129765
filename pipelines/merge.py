"""stage=merge: merge the dataset shards of a multirun into one dataset version."""
from __future__ import annotations

from topocut.data.store import MissingArtifact
from topocut.utils.context import RunContext


def run(ctx: RunContext, data) -> dict:
    from topocut.data.episodes import EpisodeDataset, merge

    prefix = f"{data.dataset}-"
    shard_names = [n for n in ctx.store.names("dataset")  # shards with a committed version (not partial ones)
                   if n.startswith(prefix) and ctx.store.versions("dataset", n)]
    if not shard_names:
        raise MissingArtifact(f"no dataset shards named '{prefix}*' under {ctx.store.root / 'dataset'}; "
                              f"run a multirun first, e.g. `python -m topocut.run -m stage=mppi task=slice,stick`")
    shards = {name: ctx.store.resolve("dataset", name) for name in shard_names}
    inputs = {name: f"dataset/{name}:{path.name}" for name, path in shards.items()}
    writer, existing = ctx.store.begin("dataset", data.dataset, {"merge_of": sorted(inputs.values())}, inputs)
    if existing is not None:
        return {"dataset": str(existing), "reused": True}
    merge([p / "data.zarr" for p in shards.values()], writer.path / "data.zarr")
    ds = EpisodeDataset(writer.path / "data.zarr")
    summary = {"shards": len(shards), "episodes": ds.num_episodes, "steps": len(ds)}
    path = writer.commit(summary)
    return {"dataset": str(path), **summary}
