"""MPPI's executed cut is its best rollout's own first cut (topocut.episode.simulated, docs/data.md "The executed
cut"): the rollouts keep every scene after its first cut on the device (CuttingEnv.snapshot_scenes), MPPI keeps the
best sequence's (save_scene_from) and the episode restores it instead of cutting again.

Scenes do not depend on their batch-mates and this session's Taichi runs on one CPU thread (tests/conftest.py), so
a rollout's scene equals the same cut made in scene 0 alone bit for bit: the episode with the cut restored must
equal the episode that cuts again, every state and label, with one cut fewer a step.
"""
from types import SimpleNamespace

import numpy as np
import pytest

from topocut.sim.action import KnifeAction

pytest.importorskip("taichi")

QUICK = dict(n_grid=32, arch="cpu", cut_substeps=40, dwell_time=0.0005, push_time=0.002, settle_time=0.002)
SIM = dict(n_grid=32, arch="cpu", push_time=0.008, settle_time=0.0074)
FIELDS = ("x", "v", "C", "F", "Jp", "sigma_y", "damage", "body", "material")


def _fields(env, b):
    n = int(env.counts[b])
    return {k: getattr(env.solver, k).to_numpy()[b, :n] for k in FIELDS}


def test_a_snapshot_keeps_every_scene_and_gives_back_the_one_asked_for():
    from topocut.sim import CuttingEnv, SimConfig

    env = CuttingEnv(SimConfig(**QUICK), batch_size=2)
    env.reset("cube", seed=0)
    env.cut([KnifeAction.from_plane(np.array([1.0, 0, 0]), np.array([0.5, 0.5, 0.1])),
             KnifeAction.from_plane(np.array([0, 1.0, 0]), np.array([0.5, 0.48, 0.1]))])
    want = [(_fields(env, b), env.piece[b].copy(), list(env.sweeps[b]), int(env.push_side[b])) for b in (0, 1)]
    assert not np.array_equal(want[0][0]["x"], want[1][0]["x"])  # two different cuts
    snap = env.snapshot_scenes("t")
    env.cut(KnifeAction.from_plane(np.array([1.0, 1.0, 0]), np.array([0.47, 0.5, 0.1])))  # the scenes move on
    for b in (1, 0):
        saved = env.save_scene_from(snap, b, f"kept {b}")
        assert env.restore_scene(saved)
        fields, piece, sweeps, side = want[b]
        for s in (0, 1):  # scene b as it was at the snapshot, in every scene
            now = _fields(env, s)
            for k, v in fields.items():
                np.testing.assert_array_equal(now[k], v, err_msg=f"scene {b} -> {s}: {k}")
            np.testing.assert_array_equal(env.piece[s], piece)
            assert env.sweeps[s] == sweeps
        assert env.push_side.tolist() == [side, side] and side != 0  # the cut's outcome can still be pushed
    env.snapshot_scenes("t")  # a later snapshot under the same name: the earlier is gone
    assert env.save_scene_from(snap, 0, "kept 0") is None


def _episode(reuse: bool, push_last: bool):
    """A stick (a push after each cut, a turn after the first) planned by MPPI: 2 sequences in 2 scenes, horizon 1,
    one iteration.  Returns the steps, the summary, the final particles, the scenes each executed cut was taken
    from (None: cut again) and how many cuts the simulator made."""
    from topocut.planning import MPPIConfig, MPPIPolicy, run_episode, sim_rollout_factory
    from topocut.sim import CuttingEnv, SimConfig
    from topocut.sim.objects import ObjectPose
    from topocut.tasks import make_goal, task_config
    from topocut.topology.config import TopologyConfig

    env = CuttingEnv(SimConfig(**SIM), batch_size=2)
    pose = ObjectPose(0.5, 0.5, 0.1, 1.0)
    env.reset("cube", pose, seed=11)
    goal = make_goal(task_config("stick", thickness=0.05), "cube", pose, env.cfg.spacing, board_z=env.cfg.board_z,
                     seed=11)
    topo = TopologyConfig(resolution=48)
    factory = sim_rollout_factory(env, topo_cfg=topo, board_z=env.cfg.board_z, push=True, push_last=push_last)
    cfg = MPPIConfig(noise_sigma=[0.02, 0.02, 0.3, 0.1], num_samples=2, iterations=1, horizon=1, push_last=push_last,
                     include_mean=False, stop_at_success=False, reuse_rollout_cut=reuse)
    policy, taken, cuts = MPPIPolicy(cfg, factory, seed=2), [], []
    act, cut = policy.act, env.cut

    def spy_act(obs):
        a = act(obs)
        taken.append(None if policy.simulated_cut is None else policy.simulated_cut.scene)
        return a

    policy.act = spy_act
    env.cut = lambda *a, **k: cuts.append(1) or cut(*a, **k)
    steps, summary = run_episode(env, goal, policy, topo_cfg=topo, max_cuts=2, push=True, seed=0)
    return steps, summary, env.state().x[0].copy(), taken, len(cuts)


@pytest.mark.parametrize("push_last", [False, True], ids=["the-episode-pushes", "the-rollout-pushed"])
def test_the_restored_best_rollout_is_the_cut_made_again_bit_for_bit(push_last):
    """push_last false: the rollout's cut is not pushed, the episode pushes the restored state; true: the rollout
    pushed, the episode discovers on the rollout's state before the push and takes the pushed one."""
    again, s_again, x_again, taken_again, cuts_again = _episode(False, push_last)
    kept, s_kept, x_kept, taken_kept, cuts_kept = _episode(True, push_last)
    assert s_again["status"] == s_kept["status"] == "ok" and s_kept["turns"] == [1]
    assert taken_again == [None, None] and None not in taken_kept
    assert 1 in taken_kept  # a sequence in scene 1 was the best: its scene, not scene 0, became the episode's
    assert (cuts_again, cuts_kept) == (2 + 2, 2)  # a step: its 2 rollouts in one batched cut (and the executed one)
    assert s_again["actions"] == s_kept["actions"] and s_again["rewards"] == s_kept["rewards"]
    assert len(again) == len(kept) == 2
    for i, (a, b) in enumerate(zip(again, kept)):
        for k in ("x_t", "f_t", "x_t1", "f_t1", "history"):
            np.testing.assert_array_equal(a[k], b[k], err_msg=f"step {i}: {k}")
    np.testing.assert_array_equal(x_again, x_kept)


def test_the_engine_takes_a_simulated_cut_only_for_the_action_and_push_it_was_made_with():
    from topocut.episode.engine import EpisodeBatch
    from topocut.episode.simulated import SimulatedCut

    engine = EpisodeBatch(SimpleNamespace(batch_size=2), scoring=SimpleNamespace(discover_fn=lambda *a: None))
    engine.alone, engine.n, engine.live, engine.tasks = True, 1, [True], [SimpleNamespace(push=False)]
    a = KnifeAction(0.5, 0.5, yaw=0.3)
    unpushed = SimulatedCut(a, after=None, before_push=None, scene=1)
    pushed = SimulatedCut(a, after=None, before_push=(np.zeros((1, 3)), np.zeros(1, bool), []), scene=1)
    assert engine.simulated(unpushed, [a]) is unpushed
    assert engine.simulated(pushed, [a]) is None  # the task does not push
    engine.tasks = [SimpleNamespace(push=True)]
    assert engine.simulated(pushed, [a]) is pushed and engine.simulated(unpushed, [a]) is unpushed  # step pushes it
    assert engine.simulated(unpushed, [KnifeAction(0.5, 0.5, yaw=0.3 + 1e-6)]) is None  # another plane
    assert engine.simulated(unpushed, [None]) is None and engine.simulated(None, [a]) is None
    engine.cut_frames = 4  # frames during the cut: they come from cutting
    assert engine.simulated(unpushed, [a]) is None
    engine.cut_frames, engine.alone = 0, False  # batched episodes have no planner
    assert engine.simulated(unpushed, [a]) is None


class _Env:
    """Two scenes of 50 particles; scene 1 diverges (frozen, ``dead``) in every cut; the snapshot and the kept
    scene are tokens."""

    batch_size = 2

    def __init__(self):
        rng = np.random.default_rng(0)
        self.x = np.repeat((rng.random((1, 50, 3)) * [0.1, 0.1, 0.05] + [0.45, 0.45, 0.05]).astype(np.float32), 2, 0)
        self.dead, self.snapshots = np.zeros(2, bool), 0

    def set_state(self, state, b=None):
        self.dead[:] = False

    def cut(self, acts):
        self.dead[1] = True

    def state(self):
        return SimpleNamespace(x=self.x, damage=np.zeros((2, 50), bool), sweeps=[["sweep 0"], ["sweep 1"]])

    def snapshot_scenes(self, name):
        self.snapshots += 1
        return f"snapshot {self.snapshots}"

    def save_scene_from(self, snap, b, name):
        return (snap, b)


class _Scorer:
    topo_cfg = None

    def labels(self, x, damage, sweeps, previous=None):
        return np.zeros(len(x), np.int32)

    def rewards(self, xs, labels):
        return np.array([0.5, 0.9][:len(xs)])  # scene 1 scores best: what is kept must still not be a diverged scene


def test_a_rollout_keeps_no_diverged_scene_and_nothing_when_its_sequences_take_two_chunks():
    from topocut.planning.rollout import make_sim_rollout

    env = _Env()
    goal = SimpleNamespace(steps=[])
    seqs = np.array([[[0.5, 0.5, 0.0, 0.0]], [[0.48, 0.5, 0.3, 0.0]]], np.float32)  # K=2,H=1,4
    rollout = make_sim_rollout(env, {"x": env.x[0]}, goal, scorer=_Scorer(), board_z=0.05)
    np.testing.assert_allclose(rollout(seqs), [-0.5, -0.9])
    assert env.snapshots == 1
    rollout.keep(1)
    assert rollout.kept() is None  # scene 1 diverged in its cut: the episode cuts again
    rollout.keep(0)
    cut = rollout.kept()
    assert cut.scene == 0 and cut.after == ("snapshot 1", 0) and not cut.pushed
    assert cut.is_of(KnifeAction.from_vector(seqs[0, 0])) and not cut.is_of(KnifeAction.from_vector(seqs[1, 0]))
    rollout.keep(1)
    assert rollout.kept() is None  # not the earlier best's either
    three = np.concatenate([seqs, seqs[:1]])  # K=3 > B=2: two chunks, the first one's snapshot overwritten
    rollout(three)
    rollout.keep(0)
    assert env.snapshots == 1 and rollout.kept() is None
