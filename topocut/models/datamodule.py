"""Transitions (topo_t, a_t, topo_{t+1}) for pretraining F, from any indexable of step dicts.

``TransitionDataset`` turns a step dict (keys of docs/contracts.md: x_t, f_t, mask, x_t1, f_t1, ...)
into fixed-size tensors:
  1. farthest point sampling of x_t to ``num_points`` (indices cached; applied to x_t1, labels and
     mask alike, since row j of x_t and x_t1 is the same particle); clouds with fewer points are
     padded by repeating points, and ``valid`` marks each particle's first row: losses and metrics
     count only those (a padding copy would weigh its particle twice);
  2. optional sort along x (Table 2 "With Sort");
  3. cluster ids of f_t and f_t1 renamed jointly to 0..K-1 (consistent between t and t+1; ids past
     ``num_labels`` merged into the last, -1 = unassigned kept);
  4. optional Gaussian jitter of the *input* positions while training (targets stay clean).
``EpisodeDataModule`` splits an episode dataset by episode into train / val and puts every step of
held-out objects (unseen) into validation too, tagged ``seen=False``.  Its loaders keep their workers between
epochs (``num_workers`` > 0) and pin batches in page-locked memory when CUDA is present (``pin_memory``), so
the per-sample work (sampling, relabelling, collate) stays in the workers and the copy to the GPU is async.
"""
from __future__ import annotations

from collections.abc import Sequence

import lightning as L
import numpy as np
import torch
from torch.utils.data import ConcatDataset, DataLoader, Dataset, Subset

REQUIRED = ("x_t", "f_t", "mask", "x_t1", "f_t1")


def relabel(f_t: np.ndarray, f_t1: np.ndarray, num_labels: int) -> tuple[np.ndarray, np.ndarray]:
    """Rename the non-negative ids of both label arrays jointly to 0..K-1 (ascending id order)."""
    ids = np.unique(np.concatenate([f_t[f_t >= 0], f_t1[f_t1 >= 0]]))
    def ren(f):
        out = np.searchsorted(ids, f).clip(max=num_labels - 1)
        return np.where(f >= 0, out, -1).astype(np.int64)
    return ren(f_t), ren(f_t1)


class TransitionDataset(Dataset):
    """Fixed-size training samples from step dicts; see the module docstring."""

    def __init__(self, steps_source: Sequence[dict], num_points: int = 256, sort: bool = True,
                 noise_std: float = 0.0, train: bool = False, num_labels: int = 32, seen: bool = True):
        self.steps = steps_source
        self.num_points, self.sort, self.noise_std, self.train = num_points, sort, noise_std, train
        self.num_labels, self.seen = num_labels, seen
        self._idx_cache: dict[int, np.ndarray] = {}

    def __len__(self) -> int:
        return len(self.steps)

    def _indices(self, i: int, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Row indices into the step's points and, per row, whether it is the particle's first row."""
        if i not in self._idx_cache:
            from topocut.metrics import fps, valid_rows

            n = len(x)
            if n >= self.num_points:
                idx = np.asarray(fps(x, self.num_points, seed=0), dtype=np.int64) if n > self.num_points \
                    else np.arange(n)
            else:  # too few points: repeat some so every sample has num_points rows
                idx = np.resize(np.arange(n), self.num_points)
            if self.sort:
                idx = idx[np.argsort(x[idx, 0], kind="stable")]
            self._idx_cache[i] = idx, valid_rows(idx)
        return self._idx_cache[i]

    def __getitem__(self, i: int) -> dict:
        s = self.steps[i]
        missing = [k for k in REQUIRED if k not in s]
        if missing:
            raise KeyError(f"step {i} lacks key {missing[0]!r}; required: {', '.join(REQUIRED)}")
        x = np.asarray(s["x_t"], dtype=np.float32)
        if len(x) == 0:
            raise ValueError(f"step {i} has an empty point cloud x_t")
        idx, valid = self._indices(i, x)
        f_t, f_t1 = relabel(np.asarray(s["f_t"])[idx], np.asarray(s["f_t1"])[idx], self.num_labels)
        x_t = torch.from_numpy(x[idx])  # N,3
        if self.train and self.noise_std > 0:
            x_t = x_t + self.noise_std * torch.randn_like(x_t)
        return {"x_t": x_t, "f_t": torch.from_numpy(f_t), "mask": torch.from_numpy(np.asarray(s["mask"])[idx]).long(),
                "x_t1": torch.from_numpy(np.asarray(s["x_t1"], dtype=np.float32)[idx]),
                "f_t1": torch.from_numpy(f_t1), "seen": torch.tensor(self.seen), "valid": torch.from_numpy(valid)}


class EpisodeDataModule(L.LightningDataModule):
    """Train/val loaders over ``topocut.data.episodes.EpisodeDataset(path)``, split by episode."""

    def __init__(self, path: str, num_points: int = 256, sort: bool = True, noise_std: float = 0.002,
                 num_labels: int = 32, batch_size: int = 16, num_workers: int = 0, val_fraction: float = 0.2,
                 held_out_objects: Sequence[str] = (), seed: int = 0, in_memory: bool = True,
                 pin_memory: bool | None = None):
        super().__init__()
        # page-locked batches (default: when CUDA is present): Lightning then copies them to the GPU asynchronously
        self.pin_memory = torch.cuda.is_available() if pin_memory is None else bool(pin_memory)
        if not 0.0 <= val_fraction < 1.0:
            raise ValueError(f"val_fraction={val_fraction} must lie in [0, 1)")
        self.path, self.batch_size, self.num_workers = str(path), batch_size, num_workers
        self.kw = dict(num_points=num_points, sort=sort, num_labels=num_labels)
        self.noise_std, self.val_fraction, self.seed, self.in_memory = noise_std, val_fraction, seed, in_memory
        self.held_out = tuple(held_out_objects)
        self.train_set = self.val_set = None
        self.split: dict[str, list[int]] = {}

    @classmethod
    def from_config(cls, path: str, cfg, **kw) -> EpisodeDataModule:
        """Input options from a DynamicsConfig (num_points, sort, noise/noise_std, num_labels); ``kw``: the rest."""
        return cls(path, num_points=cfg.num_points, sort=cfg.sort, noise_std=cfg.noise_std if cfg.noise else 0.0,
                   num_labels=cfg.num_labels, **kw)

    def split_episodes(self, objects: list[str]) -> dict[str, list[int]]:
        """Episode indices per split: ``train``, ``val`` (seen objects) and ``unseen`` (held-out objects)."""
        from topocut.utils.training import split_episodes

        return split_episodes(objects, self.val_fraction, self.seed, self.held_out)

    def setup(self, stage: str | None = None) -> None:
        if self.train_set is not None:
            return
        from topocut.data.episodes import EpisodeDataset

        ds = EpisodeDataset(self.path, in_memory=self.in_memory)
        if len(ds) == 0:
            raise ValueError(f"episode dataset {self.path} holds no steps")
        objects = [str(ds.meta(e).get("object", "")) for e in range(ds.num_episodes)]
        self.split = self.split_episodes(objects)
        if not self.split["train"]:
            raise ValueError(f"episode dataset {self.path}: no training episodes left after holding out "
                             f"{', '.join(self.held_out)}")

        def steps(episodes):
            return [i for e in episodes for i in range(*ds.episode_range(e))]

        self.train_set = TransitionDataset(Subset(ds, steps(self.split["train"])), noise_std=self.noise_std,
                                           train=True, **self.kw)
        parts = [TransitionDataset(Subset(ds, steps(self.split["val"])), seen=True, **self.kw),
                 TransitionDataset(Subset(ds, steps(self.split["unseen"])), seen=False, **self.kw)]
        self.val_set = ConcatDataset([p for p in parts if len(p)]) if any(len(p) for p in parts) else None

    def train_dataloader(self) -> DataLoader:
        from topocut.utils.training import data_loader

        return data_loader(self.train_set, self.batch_size, self.num_workers, self.pin_memory, shuffle=True,
                           drop_last=len(self.train_set) > self.batch_size)

    def val_dataloader(self):
        if self.val_set is None:
            return []
        from topocut.utils.training import data_loader

        return data_loader(self.val_set, self.batch_size, self.num_workers, self.pin_memory, shuffle=False)


def synthetic_steps(num_steps: int, num_points: int = 512, seed: int = 0, board_z: float = 0.05,
                    gap: float = 0.01) -> list[dict]:
    """Step dicts of a box cut by a vertical knife plane (smoke tests, benchmarks).

    The box [0.4,0.6]x[0.42,0.58]x[board_z, board_z+0.08] may already be split in two along y (f_t);
    the plane x = c (yaw jitter) splits every cluster it crosses: points on its +n side (mask 1) get
    the new id f_t + K and both sides move apart by ``gap`` along the normal.
    """
    from topocut.sim.action import KnifeAction, cut_mask

    rng = np.random.default_rng(seed)
    out = []
    for t in range(num_steps):
        x = rng.uniform([0.4, 0.42, board_z], [0.6, 0.58, board_z + 0.08], size=(num_points, 3)).astype(np.float32)
        f_t = (x[:, 1] > 0.5).astype(np.int32) if rng.random() < 0.5 else np.zeros(num_points, np.int32)
        action = KnifeAction(x=float(rng.uniform(0.46, 0.54)), y=0.5, yaw=float(rng.uniform(-0.3, 0.3)))
        mask = cut_mask(x, action, board_z)
        f_t1 = np.where(mask == 1, f_t + f_t.max() + 1, f_t).astype(np.int32)
        x_t1 = (x + (gap / 2) * (2.0 * mask[:, None] - 1.0) * action.normal[None]).astype(np.float32)
        out.append({"x_t": x, "f_t": f_t, "mask": mask, "x_t1": x_t1, "f_t1": f_t1, "action": action.to_vector(),
                    "pose": action.to_matrix(board_z).astype(np.float32), "history": np.zeros((3, 7), np.float32),
                    "reward": 0.0, "success": False, "episode": 0, "step": t, "task": "slice", "object": "cube"})
    return out
