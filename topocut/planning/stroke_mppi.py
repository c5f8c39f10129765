"""MPPI over the shape of each letter's stroke (cream writing), scored by its reward against its letter.

``StrokeMPPI`` plans one letter at a time: the stroke is the scripted polyline plus a smooth
offset field (``controls`` points along the arc length, linearly interpolated), MPPI samples K
offset fields, writes them in the K scenes of the batch from the same state, scores each new stroke
against its letter and keeps the best scene's state (no re-simulation).  The pen's scene and the
scripted primitives it executes are cream writing's (topocut.tasks.writing_scene).
"""
from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass

import numpy as np

from topocut.planning.mppi import mppi_weights
from topocut.tasks.writing_scene import execute, letter_distances, letter_rewards, segment_splits, stroke_actions


@dataclass
class StrokeMPPIConfig:
    num_samples: int = 4  # K: one per scene of the batch
    iterations: int = 1
    controls: int = 4  # offset control points along each stroke
    sigma: float = 0.006  # std of a control point's offset [units]
    temperature: float = 0.1
    settle_substeps: int = 120  # before a rollout's stroke is scored (the last cream is still falling)
    cost_delta: float = 1.1  # MPPI ranks samples by the reward with this tail slope (R > 0 up to d ~ 0.9)


def offset_field(poly: np.ndarray, controls: np.ndarray) -> np.ndarray:
    """Vertex offsets (m,2) of poly (m,2): controls (q,2) placed evenly along the arc length, linearly interpolated."""
    seg = np.linalg.norm(np.diff(poly, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)]) / max(seg.sum(), 1e-12)
    knots = np.linspace(0.0, 1.0, len(controls))
    return np.stack([np.interp(s, knots, controls[:, d]) for d in range(2)], -1)


class StrokeMPPI:
    """MPPI over the shape of each letter's stroke, scored by its reward against the letter (letter_distances)."""

    def __init__(self, pen, goals, cfg: StrokeMPPIConfig | None = None, reward_cfg=None, seed: int = 0):
        self.pen, self.goals, self.cfg, self.reward_cfg = pen, list(goals), cfg or StrokeMPPIConfig(), reward_cfg
        if pen.B != self.cfg.num_samples:
            raise ValueError(f"StrokeMPPI needs one scene per sample: pen batch {pen.B} != num_samples "
                             f"{self.cfg.num_samples}")
        self.rng = np.random.default_rng(seed)
        from topocut.reward import RewardConfig

        # the default reward is 0 beyond d ~ 0.1-0.2 (most perturbed strokes): rank by a gentler tail instead
        base = reward_cfg or RewardConfig()
        self.cost_cfg = dataclasses.replace(base, delta=max(self.cfg.cost_delta, base.gamma * 1.01))

    def _score(self, x, stroke, sid: int, goal) -> float:
        """R(d) of the new stroke against its letter (d as letter_rewards measures it), with the gentler tail."""
        from topocut.reward import piecewise_reward

        frag = x[stroke == sid]
        if len(frag) < 4:
            return 0.0
        D, _ = letter_distances([frag], [goal], self.cost_cfg, spacing=self.pen.spacing)
        return float(piecewise_reward(D[0, 0], self.cost_cfg))

    def plan_letter(self, poly: np.ndarray, goal: np.ndarray, state: dict) -> tuple[dict, dict]:
        """Best stroke for one letter from ``state``: (state after writing it, info)."""
        cfg, pen, K = self.cfg, self.pen, self.cfg.num_samples
        mean = np.zeros((cfg.controls, 2))
        best = (-np.inf, None, None)
        history = []
        for _ in range(cfg.iterations):
            eps = self.rng.standard_normal((K, cfg.controls, 2)) * cfg.sigma
            eps[0] = 0.0  # sample 0 is the mean
            polys = [poly + offset_field(poly, mean + e) for e in eps]
            pen.set_state(state)
            sid = pen.num_strokes  # the id the new stroke gets
            splits = segment_splits([poly], state["pen"], pen.pen.step)
            acts = np.stack([stroke_actions([p], state["pen"], pen.pen.step, splits) for p in polys])  # K,T,3
            execute(pen, acts)
            pen.settle(cfg.settle_substeps)
            x, stroke = pen.particles()
            rewards = np.array([self._score(x[k], stroke, sid, goal) for k in range(K)])
            k = int(np.argmax(rewards))
            if rewards[k] > best[0]:
                best = (float(rewards[k]), pen.get_state(k), polys[k])
            w = mppi_weights(-rewards, cfg.temperature, normalize=True)
            mean = mean + np.einsum("k,kqd->qd", w, eps)
            history.append(rewards.tolist())
        return best[1], {"cost_reward": best[0], "cost_rewards": history, "polyline": best[2]}

    def write(self, strokes, on_letter=None) -> dict:
        """Plan and write every letter in turn; returns rewards, per-letter MPPI info and timings."""
        t0 = time.perf_counter()
        state = self.pen.get_state(0)
        infos = []
        for i, (poly, goal) in enumerate(zip(strokes, self.goals)):
            state, info = self.plan_letter(np.asarray(poly, np.float64), goal, state)
            infos.append(info)
            if on_letter is not None:
                on_letter(i, state)
        self.pen.set_state(state)
        self.pen.settle()
        x, stroke = self.pen.particles()
        out = letter_rewards(x[0], stroke, self.goals, self.reward_cfg, spacing=self.pen.spacing)
        out.update(letters=[{k: v for k, v in f.items() if k != "polyline"} for f in infos],
                   polylines=[f["polyline"] for f in infos], particles=int(self.pen.n),
                   rollouts=self.cfg.num_samples * self.cfg.iterations * len(strokes),
                   seconds=time.perf_counter() - t0)
        return out
