"""Simulator rollouts for MPPI: K action sequences from one episode state, each scored by the episode core's
one-goal ``Scorer`` (topocut.episode: topology discovery after every cut, consistent cluster ids carried from
the previous labels, and the spectral reward of the resulting fragments against the goal's pieces).

Turns: where the goal's oracle (``Goal.steps``) lays pieces down between two cut directions (a Turn after its
k-th cut: stick, dice), the episode performs it after its k-th cut (``CuttingEnv.turn``; discovery then runs
with the previous labels and no sweep, so cluster ids are kept).  A rollout performs the turns that fall
between two of its cuts (one at the end of its horizon cannot change the pose-invariant reward of what it
scored).  The demonstrations' episode runner (``run_episode``) is the episode core's.
"""
from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from topocut.episode import Scorer, simulation_diverged_error, topology_device
from topocut.episode.scene import scene_of
from topocut.episode.scoring import takes_start_positions
from topocut.sim.action import KnifeAction, executed_action, plane_splits
from topocut.sim.primitives import TurnRefused
from topocut.tasks.base import turns_after

# The one rule from a policy's action to the executed knife pose (topocut.sim.action.executed_action), under its
# older name: demonstrations, MPPI's rollouts, evaluation and teleop replay all run ``executed_action(action)``.
quantize_action = executed_action


def _as_actions(vectors: np.ndarray) -> list[KnifeAction]:
    return [executed_action(KnifeAction.from_vector(v)) for v in vectors]


def discover_scenes(scorer, xs: list, damages: list, sweeps: list, previous: list,
                    starts: list | None = None) -> list[np.ndarray]:
    """Labels of several scenes: one batched discovery where the scorer offers it (``labels_batch``) and its
    topology config allows it (``batch_scenes``, default on), else one ``labels`` call per scene.  ``starts``:
    each scene's particles where the cut's blade started, passed where the scorer takes them."""
    if not xs:
        return []
    cfg = getattr(scorer, "topo_cfg", None)
    batch = getattr(scorer, "labels_batch", None)
    if batch is not None and getattr(cfg, "batch_scenes", True):
        kw = {"start_positions": starts} if starts is not None and takes_start_positions(batch) else {}
        return list(batch(xs, damages, sweeps, previous, **kw))
    kws = [{"start_positions": s} for s in starts] if starts is not None and takes_start_positions(scorer.labels) \
        else [{}] * len(xs)
    return [scorer.labels(x, d, s, p, **kw) for x, d, s, p, kw in zip(xs, damages, sweeps, previous, kws)]


class TurnFailed(RuntimeError):
    """CuttingEnv.turn refused a turn (e.g. the turned pieces would leave the simulation box)."""


def execute_turns(env, turns: list, scorer: Scorer, labels: list, xs: list) -> int:
    """Perform ``turns`` (topocut.tasks.Turn) in every scene of ``env`` (CuttingEnv.turn: per scene, the piece
    nearest the turn's centre), then re-discover scenes 0..len(labels)-1 with their previous labels and the
    scene's (now empty) sweeps, so cluster ids are kept.  ``labels`` and ``xs`` (per scene) are updated in place.
    Returns the number of turns made; a refused turn raises TurnFailed."""
    for turn in turns:
        try:
            env.turn(turn)
        except TurnRefused as e:
            raise TurnFailed(str(e)) from e
    if turns:
        st = env.state()
        scenes = range(len(labels))
        labels[:] = discover_scenes(scorer, [st.x[b] for b in scenes], [st.damage[b] for b in scenes],
                                    [st.sweeps[b] for b in scenes], [labels[b] for b in scenes])
        for b in scenes:
            xs[b] = np.asarray(st.x[b])
    return len(turns)


def make_sim_rollout(env, state_dict: dict, goal, reward_cfg=None, topo_cfg=None, board_z: float = 0.05,
                     labels=None, push: bool = False, scorer: Scorer | None = None, cuts_done: int = 0,
                     saved=None, push_last: bool = False, success_fn=None):
    """A batched MPPI cost: sequences (K,H,4) -> -(spectral reward after executing them) (K,).

    ``success_fn(RewardResult) -> bool`` (the task's success): the rollout then returns (costs (K,), success
    (K,) bool), each sequence's success after its cuts, for MPPI's ``stop_at_success`` (a diverged chunk, or a
    scorer without batched ``results``, succeeds nowhere).

    ``push``: the task pushes, so the rollout pushes after each cut of its horizon but the last (``push_last``:
    after the last too; planner.push_last, docs/data.md "The rollout's last push").

    Every chunk of env.batch_size sequences starts from ``state_dict`` (one
    scene, env.get_state(0)); a chunk that diverges, or whose turn cannot be made, costs +inf (weight 0).
    ``cuts_done``: the episode's cuts before ``state_dict``, so that the goal's turn after its k-th cut happens
    between the rollout's cuts where the episode's would.  ``saved``: the same state kept on the device
    (CuttingEnv.save_scene; the episode engine's ``obs["sim_saved"]``): chunks restore it with one kernel where
    it is this env's; otherwise the first chunk loads ``state_dict`` and keeps it on the device for the others.
    """
    scorer = scorer or Scorer(goal, reward_cfg, topo_cfg, device=topology_device(env))
    B = int(getattr(env, "batch_size", 1))
    Diverged = simulation_diverged_error()
    labels0 = None if labels is None else np.asarray(labels, np.int32)
    x0 = np.asarray(state_dict["x"], np.float32).reshape(-1, 3)  # N,3 what set_state loads
    saved = [] if saved is None else [saved]  # the start kept on the device (CuttingEnv.save_scene)
    # every scene after the first cut of its sequence (and its push), kept on the device where the env can
    # (CuttingEnv.snapshot_scenes) and the sequences fit one chunk: ``keep(k)`` then keeps sequence k's, which the
    # episode restores as its executed cut instead of simulating it again (docs/data.md, "The executed cut")
    first: list = []  # [Snapshot, the host state after the cut before the push, pushed, actions (None: diverged)]
    kept: list = []  # [SimulatedCut]

    def start() -> None:
        """Every scene at ``state_dict``: restored on the device where it was saved, else loaded and saved."""
        if saved and env.restore_scene(saved[0]):
            return
        env.set_state(state_dict, b=None)
        if hasattr(env, "save_scene"):
            saved[:] = [env.save_scene(0, "rollout")]

    def rollout(seqs: np.ndarray) -> np.ndarray:
        seqs = np.asarray(seqs, np.float64)  # K,H,4
        K, H = seqs.shape[:2]
        costs = np.empty(K)
        success = np.zeros(K, bool)
        for c0 in range(0, K, B):
            chunk = seqs[c0:c0 + B]
            n = len(chunk)
            if n < B:  # pad the last chunk by repeating its final sequence; padded scenes are ignored
                chunk = np.concatenate([chunk, np.repeat(chunk[-1:], B - n, axis=0)])
            start()
            first.clear()
            lab0 = np.zeros(len(x0), np.int32) if labels0 is None else labels0
            labs = [lab0.copy() for _ in range(n)]
            xs = [x0] * n
            try:
                for h in range(H):
                    acts = _as_actions(chunk[:, h])
                    env.cut(acts if B > 1 else acts[0])
                    st = env.state()
                    todo = []  # the scenes to discover, all in one call where the scorer batches them
                    for b in range(n):
                        # a plane that misses every particle cannot change the topology: skip discovery
                        if plane_splits(xs[b], acts[b], board_z):
                            todo.append(b)
                    # discovery where the blade left the pieces, then the push and discovery again without the
                    # sweep (as the episode engine: docs/topology.md#discovery-and-the-push)
                    found = discover_scenes(scorer, [st.x[b] for b in todo], [st.damage[b] for b in todo],
                                            [st.sweeps[b] for b in todo], [labs[b] for b in todo],
                                            [xs[b] for b in todo])
                    cut_state, pushed = st, push and (push_last or h + 1 < H)
                    if pushed:
                        env.push()
                        st = env.state()
                        found = discover_scenes(scorer, [st.x[b] for b in todo], [st.damage[b] for b in todo],
                                                [[] for _ in todo], found)
                    for b, lab in zip(todo, found):
                        labs[b] = lab
                    for b in range(n):
                        xs[b] = np.asarray(st.x[b])
                    if h == 0 and K <= B and hasattr(env, "snapshot_scenes"):  # before the goal's turn
                        dead = np.asarray(getattr(env, "dead", np.zeros(B, bool)))  # frozen where they diverged
                        first[:] = [env.snapshot_scenes("first cuts"), cut_state, pushed,
                                    [None if dead[b] else a for b, a in enumerate(acts[:n])]]
                    if h + 1 < H:  # the goal's turn between this cut and the next
                        execute_turns(env, turns_after(goal, cuts_done + h + 1), scorer, labs, xs)
            except (Diverged, TurnFailed):
                costs[c0:c0 + n] = np.inf
                continue
            if success_fn is not None and hasattr(scorer, "results"):
                results = scorer.results(xs, labs)
                costs[c0:c0 + n] = [-float(r.total) for r in results]
                success[c0:c0 + n] = [bool(success_fn(r)) for r in results]
                continue
            batched = getattr(scorer, "rewards", None)  # a scorer may offer only per-scene reward()
            costs[c0:c0 + n] = -(batched(xs, labs) if batched is not None
                                 else np.array([scorer.reward(x, lab)[0] for x, lab in zip(xs, labs)]))
        return costs if success_fn is None else (costs, success)

    def keep(k: int) -> None:
        """Keep sequence k's state after its first cut (MPPI calls this for each new best sequence)."""
        from topocut.episode.simulated import SimulatedCut

        kept.clear()  # an earlier best's cut is not this sequence's
        if not first or not 0 <= k < len(first[3]) or first[3][k] is None:  # none kept, or its scene diverged
            return
        snap, cut_state, pushed, acts = first
        after = env.save_scene_from(snap, k, "executed cut")
        if after is None:
            return
        before = None
        if pushed:  # what the episode's discovery before the push needs: the scene where the blade left it
            x, damage = scene_of(cut_state, k)
            before = (np.array(x), np.array(damage), list(cut_state.sweeps[k]))
        kept[:] = [SimulatedCut(acts[k], after, before, k)]

    rollout.keep = keep
    rollout.kept = lambda: kept[0] if kept else None  # the last kept sequence's first cut, or None
    return rollout


def sim_rollout_factory(env, reward_cfg=None, topo_cfg=None, board_z: float = 0.05,
                        push: bool | Mapping[str, bool] = False, push_last: bool = False, success=None):
    """``factory(obs, goal) -> rollout`` for MPPIPolicy: plans from obs['sim_state'] / obs['particle_labels']
    (and obs['cuts_done'], the episode's cuts so far: where the goal's turns fall in the horizon).

    ``push``: whether a rollout pushes after its cuts; a mapping {task: push} follows the goal's task, so
    that the rollouts of an evaluation over several tasks push where the executed episode does; ``push_last``:
    also after the horizon's last cut (make_sim_rollout).  ``success``: the task's success (RewardResult ->
    bool), or a mapping {task: success}; the rollouts then report each sequence's success (MPPI's
    ``stop_at_success``).  None: they report none, and MPPI runs every iteration.
    """

    def for_task(setting, goal, what: str):
        if not isinstance(setting, Mapping):
            return setting
        task = getattr(goal, "task", None)
        if task not in setting:
            raise KeyError(f"sim_rollout_factory: no {what} setting for task {task!r}; known: {', '.join(setting)}")
        return setting[task]

    def factory(obs: dict, goal):
        for k in ("sim_state", "particle_labels"):
            if k not in obs:
                raise KeyError(f"MPPI needs obs[{k!r}] (set by run_episode); obs has {', '.join(obs)}")
        return make_sim_rollout(env, obs["sim_state"], goal, reward_cfg, topo_cfg, board_z,
                                labels=obs["particle_labels"], push=bool(for_task(push, goal, "push")),
                                cuts_done=int(obs.get("cuts_done", 0)), saved=obs.get("sim_saved"),
                                push_last=push_last, success_fn=for_task(success, goal, "success"))

    return factory
