"""Evaluation protocol and Table 1 report, on an analytic fake environment (no simulator)."""
from __future__ import annotations

import csv
import json
import math
import re
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from topocut.eval import EvalConfig, episode_specs, evaluate_episode, run_evaluation, smoke
from topocut.eval.protocol import EpisodeSpec, _diverged_type, episode_path
from topocut.eval.report import PAPER_TABLE1, load_episodes, summarize, write_report
from topocut.sim.action import KnifeAction, cut_mask
from topocut.sim.objects import random_pose

SPACING, GAP, BOARD_Z = 0.01, 0.03, 0.05


class FakeDiverged(_diverged_type()):  # a subclass of the simulator's SimulationDiverged, free message
    def __init__(self, msg):
        RuntimeError.__init__(self, msg)


# -- fakes ----------------------------------------------------------------------------------------------
class BoxEnv:
    """A particle box of side 0.2 centred on the pose; a cut moves the +n side of the plane by GAP along +x."""

    def __init__(self, diverge_at: int | None = None):
        self.cfg = SimpleNamespace(board_z=BOARD_Z, spacing=SPACING)
        self.batch_size, self.resets, self.cuts, self.pushes, self.diverge_at = 1, [], 0, 0, diverge_at

    def reset(self, obj, pose=None, seed=0):
        self.resets.append((obj, pose, seed))
        g = np.arange(20) * SPACING + SPACING / 2 - 0.1  # 20 points per axis across 0.2
        X, Y, Z = np.meshgrid(g, g, g[:10] + 0.05, indexing="ij")
        self.x = np.stack([X.ravel() + pose.x, Y.ravel() + pose.y, Z.ravel() + BOARD_Z], -1).astype(np.float32)
        self.cuts = 0

    def cut(self, action):
        self.cuts += 1
        if self.diverge_at is not None and self.cuts == self.diverge_at:
            raise FakeDiverged(f"fake divergence at cut {self.cuts}")
        m = cut_mask(self.x, action, BOARD_Z).astype(bool)
        self.x[m, 0] += GAP

    def push(self):
        self.pushes += 1

    def state(self):
        return SimpleNamespace(x=self.x[None], damage=np.zeros((1, len(self.x)), bool), sweeps=[[]])

    def get_state(self, b=0):
        return {"x": self.x.copy()}


def fake_goal(task_cfg, obj, pose, spacing, seed=0):
    """Slice goal: four slabs 0.04 wide (x extent 0.04 - spacing between outer particle centres)."""
    x0 = pose.x - 0.1
    frags = [np.array([[x0 + 0.005 + i * 0.05, 0, 0], [x0 + 0.045 + i * 0.05, 0, 0]]) for i in range(4)]
    planes = [KnifeAction(x0 + 0.05 * k, pose.y) for k in (3, 2, 1)]  # right to left: moved pieces stay clear
    pts = np.concatenate(frags).astype(np.float32)
    return SimpleNamespace(fragments=frags, planes=planes, points=pts, labels=np.repeat(np.arange(4), 2))


def fake_discover(x, damage, sweeps, previous, cfg):
    pairs = cKDTree(x).query_pairs(1.5 * SPACING, output_type="ndarray")
    from scipy.sparse import coo_matrix

    adj = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(len(x), len(x)))
    return connected_components(adj, directed=False)[1].astype(np.int32)


def fake_reward(fragments, goal_fragments, cfg):
    """A piece matches a goal piece when their x extents agree within 5 mm (greedy, one-to-one)."""
    free = [np.ptp(g[:, 0]) for g in goal_fragments]
    count = 0
    for f in fragments:
        w = np.ptp(f[:, 0])
        hit = [i for i, gw in enumerate(free) if abs(gw - w) < 0.005]
        if hit:
            free.pop(hit[0])
            count += 1
    return SimpleNamespace(total=count / len(goal_fragments), cut_count=count)


class PlanePolicy:
    """Executes goal.planes, then stops (None); records what it observed."""

    def __init__(self, limit: int | None = None):
        self.limit, self.seen = limit, []

    def reset(self, goal):
        self.planes, self.t = list(goal.planes), 0

    def act(self, obs):
        self.seen.append(obs)
        if self.t >= len(self.planes) or (self.limit is not None and self.t >= self.limit):
            return None
        self.t += 1
        return self.planes[self.t - 1]


FAKES = dict(goal_fn=fake_goal, discover_fn=fake_discover, reward_fn=fake_reward)


def slice_task(push=False):
    return SimpleNamespace(name="slice", push=push, success_threshold=0.99)


# -- episode specs -------------------------------------------------------------------------------------
def test_paper_specs_are_405_deterministic_and_pose_from_seed():
    specs = episode_specs(EvalConfig())
    assert len(specs) == 405 == EvalConfig().num_episodes
    assert sum(s.split == "in" for s in specs) == 5 * 3 * 15 and sum(s.split == "out" for s in specs) == 4 * 3 * 15
    assert len({(s.task, s.key) for s in specs}) == 405
    assert specs == episode_specs(EvalConfig())  # deterministic
    assert {s.object for s in specs if s.split == "out"} == {"donut", "burger", "sushi", "steak"}
    for s in specs[::37]:
        assert s.pose == random_pose(np.random.default_rng(s.seed), 0.03, 15.0, (0.8, 1.2))
        assert abs(s.pose.x - 0.5) <= 0.03 and abs(s.pose.yaw) <= np.deg2rad(15) and 0.8 <= s.pose.scale <= 1.2
    assert len({s.pose for s in specs}) == 405  # every episode its own pose
    other = episode_specs(EvalConfig(seed=1))
    assert all(a.seed != b.seed for a, b in zip(specs, other))


def test_bad_eval_config_names_key():
    with pytest.raises(ValueError, match="eval.tasks.*pyramidal.*slice"):
        episode_specs(EvalConfig(tasks=["pyramidal"]))
    with pytest.raises(ValueError, match="eval.observation"):
        EvalConfig(observation="rgb").validate()
    with pytest.raises(ValueError, match="eval.policies: unknown policy 'dp4'.*dp3"):
        EvalConfig(policies=["oracle", "dp4"]).validate()
    with pytest.raises(ValueError, match="eval.checkpoints.mppi: only learned policies"):
        EvalConfig(policies=["oracle", "mppi"], checkpoints={"mppi": "v001"}).validate()
    EvalConfig(policies=["oracle", "pddp"], checkpoints={"pddp": "v001"}).validate()
    with pytest.raises(ValueError, match="eval.reference='heuristic'"):
        EvalConfig(reference="heuristic").validate()
    with pytest.raises(ValueError, match="runs with eval.reference=dp3 and joins .*table1.py --reference"):
        EvalConfig(policies=["dp3"]).validate()  # a piece of learned policies only: the message says what to do
    EvalConfig(policies=["dp3"], reference="dp3").validate()


# -- one episode ---------------------------------------------------------------------------------------------
def test_episode_rewards_cut_counts_and_history_hand_computed():
    spec = smoke().validate() and episode_specs(smoke())[0]
    env, pol = BoxEnv(), PlanePolicy()
    res = evaluate_episode(spec, pol, env, slice_task(push=True), observe_fn=lambda x, l, seed: (x[::2], l[::2]),
                           policy_name="oracle", **FAKES)
    # box x-extent 0.19 matches no slab: initial 0; cuts at +0.05, 0.0, -0.05 from the centre leave
    # 1, 2, then 4 slabs of extent 0.04 (the last cut makes two at once)
    assert res.initial_reward == 0.0 and res.cut_counts == [1, 2, 4] and res.rewards == [0.25, 0.5, 1.0]
    assert res.num_pieces == [2, 3, 4] and res.num_cuts == 3 and res.status == "ok" and env.pushes == 3
    assert res.final_reward == 1.0 and res.final_cut_count == 4
    assert env.resets == [(spec.object, spec.pose, spec.seed)]
    # observations: the observe_fn's points, the goal, and the history of executed pose features
    assert len(pol.seen) == 4 and len(pol.seen[0]["points"]) == len(env.x) // 2
    assert np.all(pol.seen[0]["history"] == 0) and pol.seen[0]["history"].shape == (3, 7)
    h2 = pol.seen[2]["history"]
    assert np.all(h2[0] == 0)
    np.testing.assert_allclose(h2[1], pol.planes[0].pose_feature(BOARD_Z), atol=1e-6)
    np.testing.assert_allclose(h2[2], pol.planes[1].pose_feature(BOARD_Z), atol=1e-6)
    np.testing.assert_array_equal(pol.seen[0]["goal"], fake_goal(None, None, spec.pose, 0).points)


def test_a_policy_declaring_history_len_2_receives_histories_of_length_2():
    """The engine takes the history length from the policy (its ``history_len``, a learned policy's
    policy.net.history_len); a policy declaring none gets topocut.episode.HISTORY_LEN = 3."""
    from topocut.episode import HISTORY_LEN, history_len_of

    spec = episode_specs(smoke())[0]
    pol = PlanePolicy()
    pol.history_len = 2
    res = evaluate_episode(spec, pol, BoxEnv(), slice_task(), **FAKES)
    assert res.num_cuts == 3 and [o["history"].shape for o in pol.seen] == [(2, 7)] * 4
    assert np.all(pol.seen[1]["history"][0] == 0)
    np.testing.assert_allclose(pol.seen[3]["history"], [p.pose_feature(BOARD_Z) for p in pol.planes[1:3]], atol=1e-6)
    assert history_len_of(PlanePolicy()) == HISTORY_LEN == 3


def test_observed_points_are_made_only_for_a_policy_that_reads_them():
    """The FPS of every scene (eval.observation) runs for a policy that reads ``points`` (one that declares no
    ``observation_fields``: a learned policy, your own) and not for one whose ``observation_fields`` leave them out
    (the scripted policies); both cut the same and get the same history, goal and labels.  Each scripted policy's
    class declares the inputs the registry lists for it; PDDP's ``inputs`` method does not read as a declaration."""
    from topocut.episode import reads_points
    from topocut.planning.heuristic import HeuristicPolicy
    from topocut.planning.mppi import MPPIPolicy
    from topocut.planning.oracle import OraclePolicy
    from topocut.policies import registry

    spec = episode_specs(smoke())[0]
    calls = []

    def observe(x, labels, seed):
        calls.append(seed)
        return x[::2], labels[::2]

    reader, blind = PlanePolicy(), PlanePolicy()
    blind.observation_fields = ("goal",)
    a = evaluate_episode(spec, reader, BoxEnv(), slice_task(), observe_fn=observe, **FAKES)
    assert len(calls) == 4 and all("points" in o and "labels" in o for o in reader.seen)
    calls.clear()
    b = evaluate_episode(spec, blind, BoxEnv(), slice_task(), observe_fn=observe, **FAKES)
    assert calls == [] and not any("points" in o or "labels" in o for o in blind.seen)
    assert a.actions == b.actions and a.rewards == b.rewards and len(blind.seen) == len(reader.seen) == 4
    for o1, o2 in zip(reader.seen, blind.seen):
        for k in ("history", "goal", "goal_labels", "particle_labels"):
            np.testing.assert_array_equal(o1[k], o2[k])
    classes = {"oracle": OraclePolicy, "heuristic": HeuristicPolicy, "mppi": MPPIPolicy}
    assert set(classes) == set(registry.scripted())
    for name, cls in classes.items():
        assert cls.observation_fields == registry.get(name).inputs and not reads_points(cls), name
    assert reads_points(PlanePolicy()) and reads_points(SimpleNamespace(observation_fields=("labels",)))
    from topocut.policies.deploy import PDDPPolicy

    assert callable(PDDPPolicy.inputs) and reads_points(PDDPPolicy)  # a learned policy: it reads them


def test_episode_max_cuts_and_divergence():
    spec = episode_specs(smoke())[0]
    res = evaluate_episode(spec, PlanePolicy(), BoxEnv(), slice_task(), max_cuts=2, **FAKES)
    assert res.num_cuts == 2 and res.cut_counts == [1, 2]
    res = evaluate_episode(spec, PlanePolicy(), BoxEnv(diverge_at=3), slice_task(), **FAKES)
    assert res.status == "failed" and "cut 3" in res.error and res.cut_counts == [1, 2]
    assert res.final_reward == 0.5  # the last simulated state's reward
    res = evaluate_episode(spec, PlanePolicy(), BoxEnv(diverge_at=1), slice_task(), **FAKES)
    assert res.status == "failed" and res.final_reward == res.initial_reward == 0.0 and res.final_cut_count == 0
    # a scoring error (e.g. in topology discovery) ends the episode as "error", keeping earlier cuts
    calls = []

    def flaky_discover(*a):
        calls.append(1)
        if len(calls) == 3:
            raise IndexError("boom")
        return fake_discover(*a)

    with pytest.warns(UserWarning, match="scoring cut 2: IndexError: boom"):
        res = evaluate_episode(spec, PlanePolicy(), BoxEnv(), slice_task(), **dict(FAKES, discover_fn=flaky_discover))
    assert res.status == "error" and res.cut_counts == [1] and res.final_reward == 0.25


# -- whole evaluation: same episodes across policies, resume ------------------------------------------------
def test_run_evaluation_same_episodes_and_resume(tmp_path):
    specs = episode_specs(smoke())
    assert len(specs) == 6
    tasks = {t: slice_task() for t in ("slice", "stick", "dice")}
    env = BoxEnv()
    pols = {"oracle": PlanePolicy(), "short": PlanePolicy(limit=1)}
    out = run_evaluation(specs, pols, env, tasks, tmp_path, progress=False, **FAKES)
    assert len(env.resets) == 12
    by_policy = {n: [r for i, r in enumerate(env.resets) if i % 2 == k] for k, n in enumerate(pols)}
    assert by_policy["oracle"] == by_policy["short"]  # identical (object, pose, seed) for both
    files = sorted((tmp_path / "episodes").glob("*/*.json"))
    assert len(files) == 12
    assert [e["final_cut_count"] for e in out["oracle"]] == [4] * 6 and [e["num_cuts"] for e in out["short"]] == [1] * 6
    # kill simulation: remove three results, leave a half-written temp file; re-run only those three
    for p in files[:3]:
        p.unlink()
    (files[5].parent / ".junk.json.tmp-1").write_text("{")
    env2 = BoxEnv()
    out2 = run_evaluation(specs, pols, env2, tasks, tmp_path, progress=False, **FAKES)
    assert len(env2.resets) == 3
    assert len(list((tmp_path / "episodes").glob("*/*.json"))) == 12 and len(load_episodes(tmp_path)) == 12
    untimed = lambda d: {n: [{k: v for k, v in e.items() if "time" not in k} for e in es] for n, es in d.items()}  # noqa: E731
    assert untimed(out2) == untimed(out)  # re-run episodes reproduce the originals (timings aside)
    assert episode_path(tmp_path, "oracle", specs[0]).name == f"{specs[0].key}.json"


class RecordingFilm:
    """A Filming double: wants the given spec keys of every run, keeps what write() was handed."""
    frames_per_cut = 0  # states only: BoxEnv records no snapshots during a cut

    def __init__(self, keys, out_dir):
        self.keys, self.out_dir, self.written = set(keys), out_dir, {}

    def wants(self, run, spec):
        return spec.key in self.keys and (run, spec.key) not in self.written

    def write(self, run, spec, log, board_z):
        json_written = episode_path(self.out_dir, run, spec).exists()
        self.written[run, spec.key] = (json_written, [(x.copy(), what) for x, _, what, _ in log.frames], board_z)


def test_run_evaluation_films_the_evaluated_episodes_without_running_them_again(tmp_path):
    specs = episode_specs(smoke())
    tasks = {t: slice_task() for t in ("slice", "stick", "dice")}
    env, pols = BoxEnv(), {"oracle": PlanePolicy(), "short": PlanePolicy(limit=1)}
    film = RecordingFilm([specs[0].key, specs[2].key], tmp_path)
    out = run_evaluation(specs, pols, env, tasks, tmp_path, progress=False, film=film, **FAKES)
    assert len(env.resets) == 12  # 6 specs x 2 policies, each once: no episode runs again to be filmed
    assert sorted(film.written) == sorted((n, specs[i].key) for n in pols for i in (0, 2))
    for (name, key), (json_written, frames, board_z) in film.written.items():
        [episode] = [e for e in out[name] if EpisodeSpec(**e["spec"]).key == key]
        assert not json_written  # the video is written before the episode's JSON
        assert board_z == BOARD_Z
        # the film is the evaluated episode: reset, then a state after each of its cuts, ending where it ended
        assert [w for _, w in frames] == ["reset"] + [f"cut {k + 1}: R={r:.2f}" for k, r in enumerate(
            episode["rewards"])], frames
        assert len(frames) == 1 + episode["num_cuts"] == 1 + (3 if name == "oracle" else 1)
        moved = np.sort(frames[-1][0][:, 0]) - np.sort(frames[0][0][:, 0])  # BoxEnv moves cut-off sides by GAP
        assert np.isclose(moved.max(), episode["num_cuts"] * GAP, atol=1e-6)
    # filmed once: a second evaluation of the same directory runs and films nothing
    env2 = BoxEnv()
    run_evaluation(specs, pols, env2, tasks, tmp_path, progress=False, film=film, **FAKES)
    assert env2.resets == [] and len(film.written) == 4


def test_cutting_sequences_are_filmed_as_the_evaluation_goes_beside_the_videos(tmp_path):
    """eval.gifs (topocut.eval.sequences): PDDP's first training seed's first episode per task as a GIF, written
    before the episode's JSON from the evaluated episode's own states, the figure's rows kept until it is drawn;
    the videos' film still gets its episodes (Films), and no episode runs twice."""
    from PIL import Image

    from topocut.eval.sequences import Sequences
    from topocut.eval.videos import Films

    cfg = smoke(gifs=1)
    specs = episode_specs(cfg)
    tasks = {t: slice_task() for t in ("slice", "stick", "dice")}
    env, pols = BoxEnv(), {"oracle": PlanePolicy(), "pddp@s0": PlanePolicy(limit=2), "pddp@s1": PlanePolicy()}
    seq = Sequences.of(specs, cfg, list(pols), tmp_path / "gifs")
    videos = RecordingFilm([specs[0].key], tmp_path)
    film = Films.of(videos, seq)
    assert seq.run == "pddp@s0" and seq.frames_per_cut == film.frames_per_cut == 0 and Films.of(None, None) is None
    assert Films(SimpleNamespace(keys={"a"}, frames_per_cut=3), seq).frames_per_cut == 3  # the most a member asks
    firsts = [next(s for s in specs if s.task == t) for t in cfg.tasks]  # the first episode of each task
    assert seq.keys == {s.key for s in firsts} and [key for _, key, _ in seq.rows] == [s.key for s in firsts]
    out = run_evaluation(specs, pols, env, tasks, tmp_path, progress=False, film=film, **FAKES)
    assert len(env.resets) == 18  # 6 specs x 3 runs, each once
    assert sorted(videos.written) == sorted((n, specs[0].key) for n in pols)  # the other member still films
    gifs = sorted(p.name for p in (tmp_path / "gifs").glob("*.gif"))
    assert gifs == sorted(f"{s.key}_pddp@s0.gif" for s in firsts)
    for spec in firsts:
        episode = [e for e in out["pddp@s0"] if EpisodeSpec(**e["spec"]).key == spec.key][0]
        gif, panels = seq.gif_path(spec), seq.panels_path(spec.key)
        assert gif.stat().st_mtime_ns <= episode_path(tmp_path, "pddp@s0", spec).stat().st_mtime_ns
        with Image.open(gif) as im:  # the reset, then the state after each executed cut
            assert im.n_frames == 1 + episode["num_cuts"] == 3
        assert panels.exists() and not seq.wants("pddp@s0", spec)
    assert not seq.wants("oracle", firsts[0]) and not seq.figure.exists()
    # the figure from the rows' panels: a row per task, its panels the initial state, the goal and each cut
    import pickle

    with open(seq.panels_path(firsts[0].key), "rb") as f:
        assert [caption for *_, caption in pickle.load(f)][:2] == ["initial", "goal"]
    assert seq.draw(BOARD_Z) == seq.figure and seq.figure.stat().st_size > 0
    assert not (tmp_path / "gifs" / "panels").exists() and not list(tmp_path.rglob("*.tmp-*"))
    # a GIF lost after its JSON (an evaluation killed in between, by an older version) is what film_episodes redoes
    seq.gif_path(firsts[1]).unlink()
    assert [s.key for s in specs if film.wants("pddp@s0", s)] == [firsts[1].key]


def test_videos_an_interrupted_evaluation_left_out_are_filmed_by_running_their_episodes_again(tmp_path):
    """film_episodes: the fallback for episodes committed without their video (a run killed between the two, or
    evaluated without the film): exactly those run again, and the film shows the committed episode."""
    from topocut.eval.videos import film_episodes

    specs = episode_specs(smoke())
    tasks = {t: slice_task() for t in ("slice", "stick", "dice")}
    pols = {"oracle": PlanePolicy(), "short": PlanePolicy(limit=1)}
    out = run_evaluation(specs, pols, BoxEnv(), tasks, tmp_path, progress=False, **FAKES)  # filmed nothing
    film = RecordingFilm([specs[1].key], tmp_path)
    film.written["short", specs[1].key] = "filmed already"
    env = BoxEnv()
    cfg = EvalConfig(videos=2)
    assert film_episodes(specs, pols, env, tasks, tmp_path, cfg, None, None, None, SPACING, film=film, **FAKES) == 1
    assert [(obj, seed) for obj, _, seed in env.resets] == [(specs[1].object, specs[1].seed)]  # that one alone
    json_written, frames, _ = film.written["oracle", specs[1].key]
    [episode] = [e for e in out["oracle"] if EpisodeSpec(**e["spec"]).key == specs[1].key]
    assert json_written and [w for _, w in frames][1:] == [f"cut {k + 1}: R={r:.2f}"
                                                          for k, r in enumerate(episode["rewards"])]


# -- report ---------------------------------------------------------------------------------------------
def _ep(policy, task, split, reward, nc, status="ok", i=0):
    return {"policy": policy, "spec": {"task": task, "object": "cube", "split": split, "episode": i},
            "final_reward": reward, "final_cut_count": nc, "status": status}


EPISODES = [_ep("oracle", "slice", "in", 2.0, 4), _ep("oracle", "slice", "in", 4.0, 4, i=1),
            _ep("oracle", "slice", "out", 6.0, 3),
            _ep("dp3", "slice", "in", 1.5, 2), _ep("dp3", "slice", "in", 3.0, 4, "failed", i=1),
            _ep("dp3", "slice", "out", 2.0, 1), _ep("pddp", "slice", "in", 4.0, 5), _ep("pddp", "slice", "out", 1.0, 0)]


def test_summary_normalises_by_reference_hand_computed():
    rows = {(r["policy"], r["split"]): r for r in summarize(EPISODES, "oracle", "task")}
    dp3 = rows["dp3", "in"]  # reference mean over slice = (2 + 4 + 6) / 3 = 4
    assert dp3["episodes"] == 2 and dp3["failures"] == 1 and dp3["reference_R_mean"] == 4.0
    assert math.isclose(dp3["R_hat_mean"], (1.5 / 4 + 3 / 4) / 2) and math.isclose(dp3["R_hat_std"], 0.1875)
    # two episodes: the bootstrap means are 0.375, 0.5625 or 0.75, so the 95% interval is the extremes
    assert (dp3["R_hat_lo"], dp3["R_hat_hi"]) == (0.375, 0.75) and (dp3["N_C_lo"], dp3["N_C_hi"]) == (2.0, 4.0)
    assert dp3["pairs"] == 2 and dp3["dR_hat_mean"] == -0.1875 and dp3["dR_hat_tie"] is False  # 1.5-2, 3-4 over 4
    assert math.isnan(rows["dp3", "out"]["R_hat_lo"]) and rows["dp3", "out"]["dR_hat_tie"] is None  # one episode
    assert dp3["N_C_mean"] == 3.0 and dp3["N_C_std"] == 1.0 and dp3["R_mean"] == 2.25
    assert math.isclose(rows["dp3", "out"]["R_hat_mean"], 0.5) and rows["oracle", "in"]["R_hat_mean"] == 0.75
    rows = {(r["policy"], r["split"]): r for r in summarize(EPISODES, "oracle", "task_split")}
    assert math.isclose(rows["dp3", "in"]["R_hat_mean"], (1.5 / 3 + 3 / 3) / 2)  # in-split reference mean 3
    assert math.isclose(rows["dp3", "out"]["R_hat_mean"], 2 / 6)
    rows = summarize(EPISODES, "teleop")  # reference absent: R̂ undefined, raw R still reported
    assert all(math.isnan(r["R_hat_mean"]) for r in rows) and rows[0]["R_mean"] == 3.0


def test_write_report_files(tmp_path):
    for e in EPISODES:
        p = tmp_path / "episodes" / e["policy"] / f"{e['spec']['task']}_{e['spec']['split']}_{e['spec']['episode']}.json"
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_text(json.dumps(e))
    out = write_report(tmp_path, "oracle", console=False)
    with open(out["csv"]) as f:
        rows = list(csv.DictReader(f))
    # per policy: two Table-1 cells (in, out), the task over both splits, everything
    assert len(rows) == 12 and {r["policy"] for r in rows} == {"oracle", "dp3", "pddp"}
    assert [(r["task"], r["split"], r["object"]) for r in rows if r["policy"] == "dp3"] == [
        ("slice", "in", "all"), ("slice", "out", "all"), ("slice", "all", "all"), ("all", "all", "all")]
    md = out["md"].read_text()
    # our table: oracle row shows raw R (3.00 in-distribution), PDDP best in-distribution R̂ 4/4 = 1.00 bold,
    # DP3 best out-of-distribution R̂ 2/4 = 0.50 bold; means with their 95% intervals where a cell has two
    # episodes; the paper's table follows with its numbers
    ours, paper = md.split("Paper (Table 1)")
    assert "| Oracle (goal planes) (reference, raw R) | 3.00 [2.00, 4.00] | 4.00 [4.00, 4.00] |" in ours
    assert "| PDDP (Ours) | **1.00** | **5.00** |" in ours and "| DP3 | 0.56 [0.38, 0.75] | 3.00 [2.00, 4.00] |" in ours
    assert re.search(r"\| DP3 \| [^\n]*\*\*0\.50\*\* \| \*\*1\.00\*\*", ours)
    assert "| 3D Diffuser Actor | 0.83 | 2.91 | 0.66 | 1.00 | 0.52 | 2.54 | 0.58 | 2.42 | 0.31 | **0.95** |" in paper
    assert out["png"].read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and out["wandb"] is False


def test_paper_table_constant_matches_the_tex():
    tex = Path("/work/shared/reference/topocut-paper.tex")
    if not tex.exists():
        pytest.skip("paper source not available")
    text = tex.read_text()
    names = {"heuristic": "Heuristic", "dp3": "DP3", "3dda": "3D Diffuser Actor",
             "pddp_noperc": "Ours w/o Perception", "pddp": r"\textbf{PDDP (Ours)}"}
    cols = [(s, t) for s in ("in", "out") for t in ("slice", "stick", "dice")]
    for key, name in names.items():
        body = re.split(r"\n" + re.escape(name) + r"[ \t]*\n", text, maxsplit=1)[1].split(r"\\", 1)[0]
        nums = [float(v) for v in re.findall(r"\d+\.\d+", body)]
        assert nums == [v for c in cols for v in PAPER_TABLE1[key][c]], key


def test_particle_observation_fps_keeps_labels_aligned():
    from topocut.eval import make_observe_fn

    rng = np.random.default_rng(0)
    x = rng.uniform(0, 1, (300, 3)).astype(np.float32)
    labels = (x[:, 0] > 0.5).astype(np.int32)  # label is a function of position
    pts, lab = make_observe_fn("particles", num_points=40)(x, labels)
    assert pts.shape == (40, 3) and len({tuple(p) for p in pts}) == 40
    np.testing.assert_array_equal(lab, (pts[:, 0] > 0.5).astype(np.int32))
    # FPS spreads points: the sampled set's minimum pairwise distance beats a random subset's
    d = lambda p: cKDTree(p).query(p, k=2)[0][:, 1].min()  # noqa: E731
    assert d(pts) > d(x[:40])
    with pytest.raises(ValueError, match="particles, depth"):
        make_observe_fn("rgb")


def _lattice_box():
    """Particles on a 5 mm lattice filling [0.45,0.55]^2 x [0.05,0.10]; label = (x > 0.5)."""
    g = np.arange(21) * 0.005
    X, Y, Z = np.meshgrid(0.45 + g, 0.45 + g, 0.05 + g[:11], indexing="ij")
    x = np.stack([X.ravel(), Y.ravel(), Z.ravel()], 1)
    return x, (x[:, 0] > 0.5).astype(np.int32)


def test_depth_observation_is_the_camera_pipeline_whatever_the_observation_group_says():
    from topocut.eval import make_observe_fn
    from topocut.topology.observation import ObservationConfig

    x, labels = _lattice_box()
    tree = cKDTree(x)
    particles = make_observe_fn("particles", 256, ObservationConfig(mode="depth"))(x, labels, 0)
    assert tree.query(particles[0])[0].max() < 1e-6  # FPS picks particles themselves (float32)
    # the observation group defaults to mode=particles; eval.observation=depth must still see through cameras
    depth = make_observe_fn("depth", 256, ObservationConfig())
    pts, lab = depth(x, labels, 7)
    assert pts.shape == (256, 3) and lab.shape == (256,)
    assert np.median(tree.query(pts)[0]) > 1e-3  # jittered carved voxels, not particle positions
    margin = 0.004 + 0.0075  # one voxel of carving slack + the splat disc (0.75 spacing) + noise
    assert np.all(pts >= [0.45 - margin, 0.45 - margin, 0.05 - margin])
    assert np.all(pts <= [0.55 + margin, 0.55 + margin, 0.10 + margin])
    away = np.abs(pts[:, 0] - 0.5) > 0.006  # off the label boundary the nearest particle's label is x > 0.5
    np.testing.assert_array_equal(lab[away], (pts[away, 0] > 0.5).astype(np.int32))
    # the seed drives the sensor noise: same seed, same points; another seed, other points
    np.testing.assert_array_equal(depth(x, labels, 7)[0], pts)
    assert not np.array_equal(depth(x, labels, 8)[0], pts)


class SeedRecorder(PlanePolicy):
    def reset(self, goal, seed=None):
        super().reset(goal)
        self.seeds = getattr(self, "seeds", []) + [seed]


def test_observation_and_policy_seeds_depend_on_the_episode_only():
    from topocut.eval.protocol import step_seed

    specs = episode_specs(smoke())
    seen = []

    def observe(x, labels, seed):
        seen.append(seed)
        return x, labels

    pol = SeedRecorder()
    evaluate_episode(specs[0], pol, BoxEnv(), slice_task(), observe_fn=observe, **FAKES)
    evaluate_episode(specs[1], pol, BoxEnv(), slice_task(), observe_fn=observe, **FAKES)
    after_other = seen[4:]  # specs[0] observed 4 times (3 planes, then the None)
    seen.clear()
    evaluate_episode(specs[1], SeedRecorder(), BoxEnv(), slice_task(), observe_fn=observe, **FAKES)
    assert seen == after_other and len(set(seen)) == 4  # one seed per cut, whatever ran before
    assert seen == [(specs[1].seed * 7919 + k + 1) % (2**31 - 1) for k in range(4)] == \
        [step_seed(specs[1].seed, k) for k in range(4)]
    assert pol.seeds == [specs[0].seed, specs[1].seed]  # the policy is re-seeded from each episode


def test_teleop_is_not_a_policy_eval_runs():
    with pytest.raises(ValueError, match="'teleop' is not a policy.*eval.reference=teleop"):
        EvalConfig(policies=["oracle", "teleop"]).validate()
    EvalConfig(reference="teleop").validate()  # as the reference it is fine (replayed logs)


def test_eval_artifact_key_covers_sampler_and_task_parameters():
    import dataclasses

    from pipelines.eval import artifact_config
    from topocut.data.store import config_key
    from topocut.eval.runner import task_configs
    from topocut.policies.config import SamplerConfig

    tasks = task_configs(["slice"], 5)
    args = (smoke(), None, None, None, None, None)
    key = config_key(artifact_config(*args, SamplerConfig(), tasks, 0))
    assert key == config_key(artifact_config(*args, SamplerConfig(), task_configs(["slice"], 5), 0))
    assert key != config_key(artifact_config(*args, SamplerConfig(steps=8), tasks, 0))
    assert key != config_key(artifact_config(*args, SamplerConfig(plane="lsq"), tasks, 0))
    other = {"slice": dataclasses.replace(tasks["slice"], push=not tasks["slice"].push)}
    assert key != config_key(artifact_config(*args, SamplerConfig(), other, 0))
    # a pin names a version; the version's fingerprint (an input) keys the artifact: pinned == unpinned config
    pinned = (smoke(policies=["oracle", "pddp"], checkpoints={"pddp": "v001"}), *args[1:])
    unpinned = (smoke(policies=["oracle", "pddp"]), *args[1:])
    assert (config_key(artifact_config(*pinned, SamplerConfig(), tasks, 0))
            == config_key(artifact_config(*unpinned, SamplerConfig(), tasks, 0)))


# -- teleop as the reference ------------------------------------------------------------------------------
def _commit_teleop_log(store, task, obj, actions, seed=0, pose=None, replay_config=0):
    w, _ = store.begin("dataset", f"teleop-{task}-{obj}", {"actions": actions, "seed": seed, "sim": replay_config})
    log = {"object": obj, "task": task, "seed": seed, "pose": pose or {"x": 0.5, "y": 0.5}, "actions": actions}
    (w.path / "teleop_log.json").write_text(json.dumps(log))
    return w.commit()


def test_teleop_reference_replays_committed_logs_like_a_policy(tmp_path):
    """eval.reference=teleop: each committed teleop log becomes one reference episode (undos applied), scored by
    the same evaluate_episode as the policies it normalises; a task without a log fails before any episode."""
    from topocut.data.store import ArtifactStore
    from topocut.eval.teleop import TeleopReplay, effective_cuts, teleop_references
    from topocut.sim.objects import ObjectPose

    pose = {"x": 0.5, "y": 0.5, "yaw": 0.0, "scale": 1.0}
    x0 = 0.5 - 0.1  # the fake goal's planes are at x0 + 0.05 k (k = 3, 2, 1)
    cut = lambda k: {"type": "cut", "action": [x0 + 0.05 * k, 0.5, 0.0, 0.0]}  # noqa: E731
    wrong = {"type": "cut", "action": [x0 + 0.013, 0.5, 0.0, 0.0]}
    # the human cuts a wrong slice, undoes it, then makes the three goal cuts with a push in between
    full = [cut(3), wrong, {"type": "undo", "action": None}, cut(2), {"type": "push", "action": None}, cut(1)]
    assert effective_cuts({"actions": full}) == [c["action"] for c in (cut(3), cut(2), cut(1))]
    with pytest.raises(ValueError, match=r"my.json: actions\[1\] is a cut without"):
        effective_cuts({"actions": [cut(3), {"type": "cut"}]}, "my.json")

    store = ArtifactStore(tmp_path / "store")
    with pytest.raises(ValueError, match="no teleop log for task 'slice'.*stage=teleop task=slice"):
        teleop_references(store, ["slice"])
    _commit_teleop_log(store, "slice", "cube", full, seed=5, pose=pose)
    _commit_teleop_log(store, "slice", "cube", full, seed=5, pose=pose, replay_config=1)  # same log, replayed again
    _commit_teleop_log(store, "slice", "donut", [cut(3)], seed=6, pose=pose)  # one of three cuts
    _commit_teleop_log(store, "stick", "cube", [cut(3)], pose=pose)  # not an evaluated task here
    refs = teleop_references(store, ["slice"], unseen=["donut"])
    assert [(r.spec.object, r.spec.split, r.spec.seed, len(r.cuts)) for r in refs] == [("cube", "in", 5, 3),
                                                                                       ("donut", "out", 6, 1)]
    assert refs[0].spec.pose == ObjectPose(**pose) and refs[0].ref.startswith("dataset/teleop-slice-cube:v002@")
    with pytest.warns(UserWarning, match="made 3 cuts; the protocol replays the first 2"):
        assert len(teleop_references(store, ["slice"], max_cuts=2)[0].cuts) == 3  # the policy stops at max_cuts
    with pytest.raises(ValueError, match="no teleop log for task 'dice'"):
        teleop_references(store, ["slice", "dice"])

    env, tasks = BoxEnv(), {"slice": slice_task()}
    for r in refs:
        run_evaluation([r.spec], {"teleop": TeleopReplay(r.cuts)}, env, tasks, tmp_path, progress=False, **FAKES)
    assert [(o, s) for o, _, s in env.resets] == [("cube", 5), ("donut", 6)]
    eps = {e["spec"]["object"]: e for e in load_episodes(tmp_path)}
    # three goal cuts make four 0.04 slabs: all four match (R = 1); one cut leaves one matching slab (R = 1/4)
    assert (eps["cube"]["final_reward"], eps["cube"]["final_cut_count"], eps["cube"]["num_cuts"]) == (1.0, 4, 3)
    assert (eps["donut"]["final_reward"], eps["donut"]["final_cut_count"]) == (0.25, 1)
    rows = {r["split"]: r for r in summarize(load_episodes(tmp_path), "teleop")}
    assert rows["in"]["reference_R_mean"] == pytest.approx((1.0 + 0.25) / 2)  # one mean per task, both splits


def test_eval_task_overrides_reach_the_task_configs_and_are_checked():
    """eval.task_overrides puts task parameters over each task's own config (the smoke scale's 5 cm slabs); a
    key the task does not have (dice's thickness) is refused naming its keys."""
    from topocut.eval.runner import task_configs

    cfgs = task_configs(["slice", "dice"], 2, {"slice": {"thickness": 0.05}})
    assert (cfgs["slice"].thickness, cfgs["slice"].max_cuts, cfgs["slice"].push) == (0.05, 2, False)
    assert (cfgs["dice"].size, cfgs["dice"].push, cfgs["dice"].max_cuts) == (0.03, True, 3)  # DiceConfig's; 3 cuts
    with pytest.raises(ValueError, match=r"eval\.task_overrides\.slice\.max_cuts: not a parameter of task=slice "
                                         r"\(eval\.max_cuts"):
        EvalConfig(task_overrides={"slice": {"max_cuts": 3}}).validate()
    with pytest.raises(ValueError, match=r"eval\.task_overrides\.dice\.width: not a parameter of task=dice; valid "
                                         r"keys of DiceConfig: success_threshold, push, num_goal_points, sample_tilt, size$"):
        EvalConfig(task_overrides={"dice": {"width": 0.05}}).validate()
    with pytest.raises(ValueError, match=r"eval\.task_overrides\.slize: unknown task"):
        EvalConfig(task_overrides={"slize": {"thickness": 0.05}}).validate()
    with pytest.raises(ValueError, match=r"task\.thickness=-0\.01 must be > 0"):
        task_configs(["slice"], 2, {"slice": {"thickness": -0.01}})
