"""Demonstration dataset: a zarr replay buffer of cutting episodes (docs/data.md).

Layout (diffusion_policy's ReplayBuffer style: arrays concatenated over steps,
episodes delimited by cumulative ends)::

    data/x_t (P,3) f32   x_t1 (P,3) f32   f_t (P,) i32   f_t1 (P,) i32   mask (P,) u8      per point
    data/action (S,4) pose (S,4,4) history (S,3,7) reward (S,) success (S,)
        episode (S,) step (S,) step_point_ends (S,) i64                                    per step
    data/goal (Q,3) f32   goal_labels (Q,) i32                                             per goal point
    data/goal_point_ends (E,) i64                                                          per episode
    meta/episode_ends (E,) i64        (in steps; the commit record)
    meta.attrs["episodes"]            list of E JSON dicts (task, object, pose, seed, status, ...)

Commit protocol: an episode's arrays are appended first, its JSON entry
second, and ``meta/episode_ends`` last.  Every zarr key is written by
temp-file + rename, so the committed prefix is always readable; a writer that
opens a buffer truncates whatever lies beyond the last committed episode.
"""
from __future__ import annotations

import dataclasses
import json
from collections.abc import Iterable
from pathlib import Path

import numpy as np

DEFAULT_POINTS_PER_STEP = 2048
FORMAT = "topocut-episodes-v1"  # the root's "format" attribute; any other layout is refused, not guessed at
KEY_FIELDS = ("task", "object", "seed")

# name -> (trailing shape, dtype)
POINT_ARRAYS = {"x_t": ((3,), "float32"), "f_t": ((), "int32"), "mask": ((), "uint8"),
                "x_t1": ((3,), "float32"), "f_t1": ((), "int32")}
STEP_ARRAYS = {"action": ((4,), "float32"), "pose": ((4, 4), "float32"), "history": ((3, 7), "float32"),
               "reward": ((), "float32"), "success": ((), "bool"), "episode": ((), "int32"),
               "step": ((), "int32"), "step_point_ends": ((), "int64")}
GOAL_ARRAYS = {"goal": ((3,), "float32"), "goal_labels": ((), "int32")}
EPISODE_ARRAYS = {"goal_point_ends": ((), "int64")}
CHUNK_ROWS = {"point": 1 << 16, "step": 1024, "goal": 1 << 16, "episode": 1024}
REQUIRED = (*(f"data/{n}" for n in (*POINT_ARRAYS, *STEP_ARRAYS, *GOAL_ARRAYS, *EPISODE_ARRAYS)), "meta/episode_ends")
STEP_KEYS = ("x_t", "f_t", "x_t1", "f_t1", "action", "pose", "history", "reward", "success")


def _jsonable(obj):
    """Config dataclasses, numpy scalars/arrays and paths -> plain JSON values."""
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return _jsonable(dataclasses.asdict(obj))
    if isinstance(obj, dict):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, Path):
        return str(obj)
    if hasattr(obj, "asdict"):
        return _jsonable(obj.asdict())
    if obj is None or isinstance(obj, (bool, int, float, str)):
        return obj
    return str(obj)


def _downsample(n_points: int, points: np.ndarray, seed: int) -> np.ndarray:
    """Indices of at most n_points points chosen by farthest point sampling."""
    if len(points) <= n_points:
        return np.arange(len(points))
    from topocut.metrics import fps

    return np.asarray(fps(points, n_points, seed=seed), dtype=np.int64)


def format_episode(steps: list[dict], meta: dict, points_per_step: int, board_z: float = 0.05) -> dict:
    """Planner step dicts -> the concatenated arrays of one episode (FPS-downsampled)."""
    from topocut.sim.action import KnifeAction, cut_mask

    missing = [(i, k) for i, s in enumerate(steps) for k in STEP_KEYS if k not in s]
    if missing:
        raise KeyError(f"step {missing[0][0]} lacks key {missing[0][1]!r}; required: {', '.join(STEP_KEYS)}")
    for k in ("goal", "goal_labels"):
        if k not in meta:
            raise KeyError(f"episode meta lacks {k!r}; it must hold the goal point cloud and its labels")
    seed = int(meta.get("seed", 0))
    cols = {k: [] for k in (*POINT_ARRAYS, *STEP_ARRAYS)}
    n_total = 0
    for t, s in enumerate(steps):
        x_t = np.asarray(s["x_t"], np.float32).reshape(-1, 3)  # n,3
        idx = _downsample(points_per_step, x_t, seed + t)  # m,
        action = s["action"] if isinstance(s["action"], KnifeAction) else KnifeAction.from_vector(s["action"])
        mask = s.get("mask")
        mask = cut_mask(x_t[idx], action, board_z) if mask is None else np.asarray(mask)[idx]
        cols["x_t"].append(x_t[idx])
        cols["f_t"].append(np.asarray(s["f_t"])[idx])
        cols["mask"].append(mask)
        cols["x_t1"].append(np.asarray(s["x_t1"], np.float32).reshape(-1, 3)[idx])  # particles are conserved
        cols["f_t1"].append(np.asarray(s["f_t1"])[idx])
        cols["action"].append(action.to_vector())
        cols["pose"].append(np.asarray(s["pose"], np.float32).reshape(4, 4))
        cols["history"].append(np.asarray(s["history"], np.float32).reshape(3, 7))
        cols["reward"].append(float(s["reward"]))
        cols["success"].append(bool(s["success"]))
        cols["step"].append(t)
        n_total += len(idx)
        cols["step_point_ends"].append(n_total)  # relative to the episode; made global on append
        cols["episode"].append(0)  # set on append
    goal = np.asarray(meta["goal"], np.float32).reshape(-1, 3)
    gidx = _downsample(points_per_step, goal, seed)
    out = {}
    for name, (shape, dtype) in {**POINT_ARRAYS, **STEP_ARRAYS}.items():
        vals = cols[name]
        if name in POINT_ARRAYS:
            out[name] = np.concatenate(vals).astype(dtype) if vals else np.zeros((0, *shape), dtype)
        else:
            out[name] = np.asarray(vals, dtype=dtype).reshape(-1, *shape)
    out["goal"] = goal[gidx]
    out["goal_labels"] = np.asarray(meta["goal_labels"]).astype(np.int32)[gidx]
    return out


def _create(group, name: str, shape: tuple, dtype: str, chunk_rows: int, fill_value=0):
    make = getattr(group, "create_array", None) or group.create_dataset  # zarr 3 / zarr 2
    return make(name, shape=(0, *shape), chunks=(chunk_rows, *shape), dtype=dtype, fill_value=fill_value)


class _Buffer:
    """The committed prefix of an episode buffer; shared by the writer and the reader."""

    def __init__(self, path, mode: str):
        import zarr

        self.path = Path(path)
        self.root = zarr.open_group(str(self.path), mode=mode)
        self.writable = mode != "r"
        if self.writable and self.root.attrs.get("format") is None:
            self._init_layout()
        self._check_layout()
        self.data, self.meta = self.root["data"], self.root["meta"]
        self._load_committed()

    def _init_layout(self) -> None:
        """Create what is missing: a new buffer, or one whose writer was killed while laying it out."""
        self.root.attrs["format"] = FORMAT
        data = self.root.require_group("data")
        meta = self.root.require_group("meta")
        for kind, arrays in (("point", POINT_ARRAYS), ("step", STEP_ARRAYS), ("goal", GOAL_ARRAYS),
                             ("episode", EPISODE_ARRAYS)):
            for name, (shape, dtype) in arrays.items():
                if name not in data:
                    _create(data, name, shape, dtype, CHUNK_ROWS[kind])
        if "episode_ends" not in meta:
            _create(meta, "episode_ends", (), "int64", CHUNK_ROWS["episode"], fill_value=-1)
        if "episodes" not in meta.attrs:
            meta.attrs["episodes"] = []

    def _check_layout(self) -> None:
        """Another format (a future schema) fails here, naming what differs, not later as a bare KeyError."""
        from topocut.data.store import UnsupportedSchema

        found = self.root.attrs.get("format")
        missing = [k for k in REQUIRED if k not in self.root]
        if found != FORMAT or missing:
            raise UnsupportedSchema(f"{self.path}: episode buffer format {found!r}"
                                    + (f" without {', '.join(missing)}" if missing else "")
                                    + f"; this topocut reads {FORMAT} (docs/data.md). Re-create the dataset with "
                                    "this version (re-run the stage that made it) or read it with the one that wrote it")

    def _load_committed(self) -> None:
        """Longest prefix of episodes whose arrays and JSON entries are all complete."""
        ends = np.asarray(self.meta["episode_ends"][:], np.int64)
        infos = list(self.meta.attrs.get("episodes", []))
        spe = np.asarray(self.data["step_point_ends"][:], np.int64)
        gpe = np.asarray(self.data["goal_point_ends"][:], np.int64)
        n_steps, n_goal = self.data["action"].shape[0], self.data["goal"].shape[0]
        n_points = self.data["x_t"].shape[0]
        e, prev, prev_g = 0, 0, 0
        while e < len(ends):
            # episode_ends is filled with -1, so an entry resized into existence but never written is < prev
            end = int(ends[e])
            ok = (prev <= end <= min(n_steps, len(spe)) and e < len(infos) and e < len(gpe)
                  and prev_g <= gpe[e] <= n_goal and (end == 0 or spe[end - 1] <= n_points))
            if not ok:
                break
            prev, prev_g, e = end, int(gpe[e]), e + 1
        self.num_episodes = e
        self.episode_ends = ends[:e]
        self.num_steps = int(ends[e - 1]) if e else 0
        self.step_point_ends = spe[: self.num_steps]
        self.goal_point_ends = gpe[:e]
        self.num_points = int(self.step_point_ends[-1]) if self.num_steps else 0
        self.num_goal = int(self.goal_point_ends[-1]) if e else 0
        self.infos = infos[:e]

    def truncate_uncommitted(self) -> None:
        sizes = {"point": self.num_points, "step": self.num_steps, "goal": self.num_goal,
                 "episode": self.num_episodes}
        for kind, arrays in (("point", POINT_ARRAYS), ("step", STEP_ARRAYS), ("goal", GOAL_ARRAYS),
                             ("episode", EPISODE_ARRAYS)):
            for name, (shape, _) in arrays.items():
                if self.data[name].shape[0] != sizes[kind]:
                    self.data[name].resize((sizes[kind], *shape))
        if self.meta["episode_ends"].shape[0] != self.num_episodes:
            self.meta["episode_ends"].resize((self.num_episodes,))
        if len(self.meta.attrs.get("episodes", [])) != self.num_episodes:
            self.meta.attrs["episodes"] = self.infos


class EpisodeWriter:
    """Append episodes to a buffer one atomic commit at a time; resumable after a kill."""

    def __init__(self, path, points_per_step: int = DEFAULT_POINTS_PER_STEP, key_fields=KEY_FIELDS,
                 board_z: float = 0.05):
        if points_per_step < 1:
            raise ValueError(f"points_per_step must be >= 1, got {points_per_step}")
        self.points_per_step, self.key_fields, self.board_z = points_per_step, tuple(key_fields), board_z
        self._buf = _Buffer(path, mode="a")
        self._buf.truncate_uncommitted()
        self.path = self._buf.path

    @property
    def num_episodes(self) -> int:
        return self._buf.num_episodes

    @property
    def num_steps(self) -> int:
        return self._buf.num_steps

    def episode_key(self, meta: dict) -> tuple:
        vals = (_jsonable(meta.get(k)) for k in self.key_fields)
        return tuple(json.dumps(v, sort_keys=True) if isinstance(v, (dict, list)) else v for v in vals)

    def committed_keys(self) -> set:
        """Keys (e.g. (task, object, seed)) of committed episodes: skip these when resuming."""
        return {self.episode_key(info) for info in self._buf.infos}

    def add_episode(self, steps: list[dict], meta: dict) -> int:
        """Downsample and commit one episode; returns its index."""
        arrays = format_episode(steps, meta, self.points_per_step, float(meta.get("board_z", self.board_z)))
        info = {k: v for k, v in meta.items() if k not in ("goal", "goal_labels")}
        return self.append_arrays(arrays, info)

    def append_arrays(self, arrays: dict, info: dict) -> int:
        """Commit one episode given its already formatted arrays (as from format_episode)."""
        b = self._buf
        e = b.num_episodes
        n_steps = len(arrays["action"])
        arrays = dict(arrays)
        arrays["episode"] = np.full(n_steps, e, np.int32)
        arrays["step_point_ends"] = np.asarray(arrays["step_point_ends"], np.int64) + b.num_points
        for name in (*POINT_ARRAYS, *GOAL_ARRAYS, *STEP_ARRAYS):
            shape, dtype = {**POINT_ARRAYS, **GOAL_ARRAYS, **STEP_ARRAYS}[name]
            vals = np.asarray(arrays[name], dtype=dtype).reshape(-1, *shape)
            if len(vals):
                b.data[name].append(vals, axis=0)
        gpe = b.num_goal + len(arrays["goal"])
        b.data["goal_point_ends"].append(np.array([gpe], np.int64), axis=0)
        info = {**_jsonable(info), "num_steps": n_steps}
        info.setdefault("status", "ok")
        b.meta.attrs["episodes"] = b.infos + [info]
        end = b.num_steps + n_steps
        b.meta["episode_ends"].append(np.array([end], np.int64), axis=0)  # the commit
        b.infos.append(info)
        b.episode_ends = np.append(b.episode_ends, end)
        b.step_point_ends = np.concatenate([b.step_point_ends, arrays["step_point_ends"]])
        b.goal_point_ends = np.append(b.goal_point_ends, gpe)
        b.num_episodes, b.num_steps, b.num_goal = e + 1, end, gpe
        b.num_points = int(b.step_point_ends[-1]) if end else 0
        return e


class EpisodeDataset:
    """Read-only view of the committed episodes; ``ds[i]`` is one step dict (docs/contracts.md)."""

    def __init__(self, path, in_memory: bool = False):
        self._buf = _Buffer(path, mode="r")
        self.path = self._buf.path
        b = self._buf
        self._cache = None
        if in_memory:  # one read per array: fast random access for training
            sizes = {**{k: b.num_points for k in POINT_ARRAYS}, **{k: b.num_steps for k in STEP_ARRAYS},
                     **{k: b.num_goal for k in GOAL_ARRAYS}}
            self._cache = {k: np.asarray(b.data[k][:n]) for k, n in sizes.items()}

    def __len__(self) -> int:
        return self._buf.num_steps

    @property
    def num_episodes(self) -> int:
        return self._buf.num_episodes

    def _arr(self, name: str, lo: int, hi: int) -> np.ndarray:
        src = self._cache[name] if self._cache is not None else self._buf.data[name]
        return np.asarray(src[lo:hi])

    def meta(self, e: int) -> dict:
        if not 0 <= e < self.num_episodes:
            raise IndexError(f"episode {e} out of range [0, {self.num_episodes})")
        return dict(self._buf.infos[e])

    def episode_range(self, e: int) -> tuple[int, int]:
        """Global step indices [start, end) of episode e."""
        self.meta(e)
        ends = self._buf.episode_ends
        return (int(ends[e - 1]) if e else 0), int(ends[e])

    def __getitem__(self, i: int) -> dict:
        b = self._buf
        i = int(i) + (len(self) if int(i) < 0 else 0)
        if not 0 <= i < len(self):
            raise IndexError(f"step {i} out of range [0, {len(self)})")
        e = int(np.searchsorted(b.episode_ends, i, side="right"))
        p0, p1 = (int(b.step_point_ends[i - 1]) if i else 0), int(b.step_point_ends[i])
        g0, g1 = (int(b.goal_point_ends[e - 1]) if e else 0), int(b.goal_point_ends[e])
        out = {k: self._arr(k, p0, p1) for k in POINT_ARRAYS}
        out.update({k: self._arr(k, i, i + 1)[0] for k in ("action", "pose", "history")})
        out["goal"], out["goal_labels"] = self._arr("goal", g0, g1), self._arr("goal_labels", g0, g1)
        out["reward"] = np.float32(self._arr("reward", i, i + 1)[0])
        out["success"] = bool(self._arr("success", i, i + 1)[0])
        out["episode"] = np.int32(e)
        out["step"] = np.int32(self._arr("step", i, i + 1)[0])
        info = b.infos[e]
        out["task"], out["object"] = str(info.get("task", "")), str(info.get("object", ""))
        return out

    def episode(self, e: int) -> list[dict]:
        lo, hi = self.episode_range(e)
        return [self[i] for i in range(lo, hi)]

    def episode_arrays(self, e: int) -> dict:
        """The raw concatenated arrays of episode e, in format_episode's layout (for merging)."""
        b = self._buf
        lo, hi = self.episode_range(e)
        p0 = int(b.step_point_ends[lo - 1]) if lo else 0
        p1 = int(b.step_point_ends[hi - 1]) if hi > lo else p0
        g0, g1 = (int(b.goal_point_ends[e - 1]) if e else 0), int(b.goal_point_ends[e])
        out = {k: self._arr(k, p0, p1) for k in POINT_ARRAYS}
        out.update({k: self._arr(k, lo, hi) for k in STEP_ARRAYS})
        out["step_point_ends"] = out["step_point_ends"] - p0
        out.update({k: self._arr(k, g0, g1) for k in GOAL_ARRAYS})
        return out


def merge(shards: Iterable, out_path, points_per_step: int = DEFAULT_POINTS_PER_STEP) -> list[str]:
    """Concatenate shard buffers into ``out_path`` (episode ids renumbered); returns the shard list.

    Resumable: an episode already copied (same shard path and index) is not copied again.
    """
    shards = [Path(s) for s in shards]
    writer = EpisodeWriter(out_path, points_per_step=points_per_step, key_fields=("source",))
    done = writer.committed_keys()
    for shard in shards:
        ds = EpisodeDataset(shard)
        for e in range(ds.num_episodes):
            info = ds.meta(e)
            info.pop("num_steps", None)
            info["source"] = {"shard": str(shard), "episode": e}
            if writer.episode_key(info) in done:
                continue
            writer.append_arrays(ds.episode_arrays(e), info)
    return [str(s) for s in shards]


def dumps_meta(meta: dict) -> str:
    """JSON text of an episode meta dict (as stored)."""
    return json.dumps(_jsonable(meta), sort_keys=True)
