"""Issue #30 parts 1-2: one goal representation for every policy (the task is in the goal's piece labels), one
policy registry, a pose-consistent mask label and one rule from a policy's action to the executed knife pose."""
from __future__ import annotations

import dataclasses
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from topocut.policies import registry
from topocut.policies.actions import action_from_pose_feature, action_mask, orient_mask, previous_plane_mask
from topocut.policies.inputs import GOAL_FIELDS, INPUT_FIELDS, goal_inputs, policy_inputs, step_targets
from topocut.sim.action import KnifeAction, cut_mask, executed_action
from topocut.sim.objects import ObjectPose, sample_object
from topocut.tasks import make_goal, task_config

pytestmark = pytest.mark.usefixtures("one_thread")  # tests/conftest.py

SPACING = 0.008
TASKS = ("slice", "stick", "dice")
NPTS = 64
PDDP_TINY = dict(n_blocks=1, hidden=16, obs_dim=16, n_heads=2, cond_dim=16, time_freq_dim=16, goal_hidden=8,
                 dropout=0.0)


@pytest.fixture(scope="module")
def scene():
    """One object and pose, its particles (the observation before the first cut) and the three tasks' goals."""
    pose = ObjectPose(x=0.51, y=0.49, yaw=0.2, scale=1.05)
    pts = sample_object("cake", pose, SPACING)[0]
    goals = {t: make_goal(task_config(t), "cake", pose, SPACING) for t in TASKS}
    obs = {t: {"points": pts, "labels": np.zeros(len(pts), np.int32), "history": np.zeros((3, 7), np.float32),
               "goal": g.points, "goal_labels": g.labels} for t, g in goals.items()}
    return pts, goals, obs


def _perception_ckpt(path):
    from topocut.models.config import DynamicsConfig
    from topocut.models.module import DynamicsModule

    cfg = DynamicsConfig(num_points=16, hidden=16, k=4, cross_k=4, num_layers=1, num_heads=2, query_hidden=8)
    torch.manual_seed(0)
    module = DynamicsModule(cfg)
    torch.save({"state_dict": module.state_dict(), "hyper_parameters": {"cfg": dataclasses.asdict(cfg)}}, path)
    return str(path)


def _tiny_policy(name, tmp_path):
    """An untrained policy of the registry's learned ``name`` (its inputs are what is tested, not its skill)."""
    spec = registry.get(name)
    torch.manual_seed(0)
    if spec.family == "pddp":
        from topocut.policies import PDDPConfig, PolicyTrainConfig
        from topocut.policies.module import PDDPModule, PDDPPolicy

        ckpt = _perception_ckpt(tmp_path / "perception.ckpt") if spec.encoder == "pretrained" else None
        train = PolicyTrainConfig(encoder=spec.encoder, encoder_ckpt=ckpt, num_points=NPTS, num_goal_points=NPTS)
        return PDDPPolicy(PDDPModule(PDDPConfig(**PDDP_TINY), spec.encoder, ckpt, train), steps=2)
    from topocut.policies.baselines.module import PoseDiffusionModule, PosePolicy

    small = dict(enc_dim=8, down_dims=(8, 16), horizon=2) if spec.kind == "dp3" else dict(dim=24, heads=2, layers=1)
    return PosePolicy(PoseDiffusionModule(kind=spec.kind, num_points=NPTS, num_goal_points=NPTS, **small))


def test_goal_points_alone_are_task_blind_the_piece_labels_are_not(scene):
    """The issue's finding: the goal cloud of slice, stick and dice is the same uncut posed object; the labels
    are what differ, so they are what encodes the task."""
    _, goals, _ = scene
    for t in TASKS[1:]:
        np.testing.assert_array_equal(goals[t].points, goals["slice"].points)
        assert not np.array_equal(goals[t].labels, goals["slice"].labels)


def test_pddp_goal_input_differs_across_tasks_and_every_learned_policy_gets_the_same_goal_fields(scene, tmp_path):
    _, goals, obs = scene
    policies = {n: _tiny_policy(n, tmp_path) for n in registry.learned()}
    assert set(policies) == {"dp3", "3dda", "pddp_noperc", "pddp_graphconv", "pddp"}
    for name in policies:  # the registry: every learned policy reads the same fields, goal labels included
        assert registry.get(name).inputs == INPUT_FIELDS and "goal_labels" in INPUT_FIELDS
    for task in TASKS:
        fields = {n: p.inputs(obs[task], seed=n_seed) for (n, p), n_seed in zip(policies.items(), range(5))}
        ref = goal_inputs(goals[task].points, goals[task].labels, NPTS)  # seed-free: the same for every policy
        for name, inp in fields.items():
            for k in GOAL_FIELDS:
                np.testing.assert_array_equal(inp[k], ref[k], err_msg=f"{name} {task} {k}")

    # PDDP's goal input z_g = Φ(X_g, F_g) and what the network makes of it differ across the three tasks
    for name in ("pddp", "pddp_noperc", "pddp_graphconv"):
        pol = policies[name]
        vecs = {}
        for task in TASKS:
            batch, _ = pol._batch(obs[task], seed=0)
            model = pol.module.model.eval()
            with torch.no_grad():
                z_g = model.encoder(batch["goal"], batch["goal_labels"])
                vecs[task] = (z_g, model.context(batch["points"], batch["labels"], batch["goal"], batch["history"],
                                                 batch["goal_labels"], batch["goal_valid"])["goal_vec"])
        for t in TASKS[1:]:
            assert not torch.allclose(vecs[t][0], vecs["slice"][0]), (name, t)
            assert not torch.allclose(vecs[t][1], vecs["slice"][1]), (name, t)

    # the baselines see the same labels (shifted to embedding rows, as their observation labels)
    from topocut.policies.inputs import object_frame

    for name in ("dp3", "3dda"):
        framed = object_frame(policies[name].inputs(obs["dice"]))
        np.testing.assert_array_equal(framed["goal_labels"], ref["goal_labels"] + 1)


def test_a_checkpoint_from_before_goal_input_loads_as_the_task_blind_network(tmp_path):
    """Saved configs without ``goal_input`` build the 3 -> 64 -> 96 goal encoder they were trained with."""
    import lightning

    from topocut.policies import PDDPConfig
    from topocut.policies.module import PDDPModule, PDDPPolicy

    old = PDDPModule(PDDPConfig(**PDDP_TINY, goal_input="xyz"), "none")
    hp = dict(old.hparams)
    hp["cfg"] = {k: v for k, v in hp["cfg"].items() if k != "goal_input"}  # as written before the field existed
    path = tmp_path / "old.ckpt"
    torch.save({"state_dict": old.state_dict(), "hyper_parameters": hp,
                "pytorch-lightning_version": lightning.__version__}, path)
    policy = PDDPPolicy(str(path))
    assert policy.module.cfg.goal_input == "xyz" and policy.module.model.net.goal_enc[0].in_features == 3


def test_the_registry_is_the_one_policy_list():
    from pipelines import bc
    from topocut.eval import config as eval_config
    from topocut.eval import report
    from topocut.eval import runner as eval_stage
    from topocut.policies.baselines import module as baselines

    assert registry.names() == ("oracle", "heuristic", "mppi", "dp3", "3dda", "pddp_noperc", "pddp_graphconv", "pddp")
    assert eval_stage.SCRIPTED + eval_stage.LEARNED == registry.names()
    assert baselines.KINDS == registry.pose_kinds() == ("dp3", "3dda")
    assert registry.pddp_encoders() == {"pddp_noperc": "none", "pddp_graphconv": "graphconv", "pddp": "pretrained"}
    assert bc.registry is registry
    # lists still kept outside the files this change owns must agree with it (until they read it)
    assert eval_config.POLICY_NAMES == registry.names() and eval_config.LEARNED == registry.learned()
    assert report.DISPLAY == registry.display_names()
    with pytest.raises(ValueError, match="unknown policy 'act'; valid: dp3, 3dda"):
        registry.check(["dp3", "act"], "stage.run.policies", registry.learned())


# -- part 2: the mask means the same at every pose --------------------------------------------------------
def _rotated(pts, yaw, c=(0.5, 0.5)):
    c = np.array([*c, 0.0])
    R = np.array([[np.cos(yaw), -np.sin(yaw), 0], [np.sin(yaw), np.cos(yaw), 0], [0, 0, 1]])
    return ((pts - c) @ R.T + c).astype(np.float32)


def test_the_same_cut_at_yaw_minus_and_plus_one_degree_gets_the_same_mask():
    """The stick task's width cut on the cube (normal along the object's a2: world yaw ~ +-90 deg, where the
    canonical yaw wraps) at object yaw -1 deg and +1 deg: the plane-side mask flips, the policy's label does not."""
    local = sample_object("cube", ObjectPose(), SPACING)[0]  # the same material, turned with the object
    # a width cut (normal along a2) through the cube, object frame; the task's own are made on the slab set aside
    cut = KnifeAction.from_plane([0.0, 1.0, 0.0], [0.5, 0.52, 0.05])
    new, old = {}, {}
    for deg in (-1.0, 1.0):
        yaw = np.radians(deg)
        goal = make_goal(task_config("stick"), "cube", ObjectPose(yaw=yaw), SPACING)
        normal = _rotated(cut.normal[None] + np.array([0.5, 0.5, 0.0]), yaw)[0] - np.array([0.5, 0.5, 0.0])
        width = KnifeAction.from_plane(normal, _rotated(cut.plane_point()[None], yaw)[0])  # the same cut, turned
        assert np.degrees(abs(width.yaw)) > 88.5  # canonical yaw next to the wrap: +89 deg at one pose, -89 at the other
        assert np.isclose(abs(goal.planes[1].yaw), abs(width.yaw), atol=np.radians(0.5))  # the task's own width cut
        pts = _rotated(local, yaw)
        new[deg], old[deg] = action_mask(pts, width, goal.points, goal.labels), cut_mask(pts, width)
        # the slab cut: 1 on the goal pieces' side
        slab = action_mask(goal.points, goal.planes[0], goal.points, goal.labels)
        assert slab[goal.labels > 0].all() and slab.mean() < 0.5
    assert 0.05 < new[1.0].mean() < 0.95
    assert (new[-1.0] == new[1.0]).mean() > 0.99  # the same cut, the same label
    assert (old[-1.0] == old[1.0]).mean() < 0.05  # the stored plane-side mask: complementary labels


def test_orient_mask_and_step_targets_give_the_label_rule_from_a_stored_mask():
    rng = np.random.default_rng(0)
    x = rng.uniform([0.4, 0.4, 0.05], [0.6, 0.6, 0.15], (300, 3)).astype(np.float32)
    goal = rng.uniform([0.4, 0.4, 0.05], [0.6, 0.6, 0.15], (200, 3)).astype(np.float32)
    glab = (goal[:, 1] > 0.57).astype(np.int32)  # goal piece at +y: u = +y, v = -x, r = (-x + y)/sqrt 2
    for yaw in (np.pi / 2, -np.pi / 2 + 1e-3, 0.3, -1.2):  # one plane each side of the wrap and two others
        a = executed_action(KnifeAction(0.5, 0.52, yaw, 0.1))  # as recorded: the stored vector reads back to it
        want = action_mask(x, a, goal, glab)
        np.testing.assert_array_equal(orient_mask(cut_mask(x, a), a, goal, glab), want)
        step = {"x_t": x, "f_t": np.zeros(300, np.int32), "mask": cut_mask(x, a), "action": a.to_vector(),
                "goal": goal, "goal_labels": glab, "history": np.zeros((3, 7), np.float32)}
        idx = np.arange(0, 300, 3)
        t = step_targets(step, idx)
        np.testing.assert_array_equal(t["mask"], want[idx])
        assert not t["has_prev"] and t["prev_mask"].min() == t["prev_mask"].max() == int(want[idx].mean() > 0.5)
        np.testing.assert_array_equal(step_targets(step, idx, mask_label="plane_side")["mask"], cut_mask(x, a)[idx])
    # a cut across the goal direction is 1 on the goal piece's side, whichever way its canonical normal points
    across = KnifeAction(0.5, 0.56, np.pi / 2, 0.0)
    assert action_mask(goal, across, goal, glab)[glab > 0].all()


def test_previous_plane_mask_reads_the_plane_back_from_the_history():
    from topocut.policies.base import history_from_actions

    rng = np.random.default_rng(1)
    x = rng.uniform([0.4, 0.4, 0.05], [0.6, 0.6, 0.15], (200, 3)).astype(np.float32)
    goal, glab = x, (x[:, 0] > 0.55).astype(np.int32)
    a, b = KnifeAction(0.55, 0.5, 0.1, 0.2).canonical(), KnifeAction(0.5, 0.45, 1.4, -0.1).canonical()
    hist = history_from_actions([a, b])
    back = action_from_pose_feature(hist[-1])
    assert np.allclose(back.to_vector(), b.to_vector(), atol=1e-5)
    assert action_from_pose_feature(np.zeros(7)) is None
    np.testing.assert_array_equal(previous_plane_mask(x, hist, goal, glab), action_mask(x, b, goal, glab))
    assert previous_plane_mask(x, history_from_actions([]), goal, glab) is None
    step = {"x_t": x, "f_t": np.zeros(200, np.int32), "action": a.to_vector(), "goal": goal, "goal_labels": glab,
            "history": hist}
    t = step_targets(step, np.arange(200))
    assert t["has_prev"] and np.array_equal(t["prev_mask"], action_mask(x, b, goal, glab))


def test_policy_inputs_builds_every_field_once():
    rng = np.random.default_rng(2)
    pts = rng.uniform(0, 1, (40, 3))
    obs = {"points": pts, "labels": np.arange(40) % 3, "history": np.zeros((3, 7)), "goal": pts[:10],
           "goal_labels": np.arange(10) % 2}
    a, b = policy_inputs(obs, 16, 16, seed=0), policy_inputs(obs, 16, 16, seed=1)
    assert a["points"].shape == (16, 3) and a["goal"].shape == (16, 3) and a["goal_valid"].sum() == 10
    assert not np.array_equal(a["index"], b["index"])  # the observation's FPS start follows the seed ...
    for k in GOAL_FIELDS:  # ... the goal fields do not
        np.testing.assert_array_equal(a[k], b[k])


# -- part 2: one rule from a policy's action to the executed pose ---------------------------------------------
def test_demos_evaluation_and_teleop_replay_execute_one_rule():
    """A policy's yaw just past pi/2 in float32: evaluation executes executed_action(action), whose stored
    float32 vector reads back to exactly the pose that ran (canonical() alone does not), as demos and replay do."""
    from topocut.eval.protocol import EpisodeSpec, evaluate_episode
    from topocut.eval.teleop import TeleopReplay
    from topocut.planning import rollout

    raw = KnifeAction(0.5123456789, 0.5, float(np.float32(np.pi / 2)), 0.1)
    done = executed_action(raw)
    assert executed_action(done) == done and KnifeAction.from_vector(done.to_vector()) == done
    assert KnifeAction.from_vector(raw.canonical().to_vector()) != raw.canonical()  # what evaluation ran before
    assert rollout.quantize_action is executed_action  # demonstrations (run_episode, make_step, MPPI's rollouts)

    X = np.random.default_rng(0).uniform(0.45, 0.55, (50, 3)).astype(np.float32)

    class Env:
        cfg = SimpleNamespace(board_z=0.05, spacing=0.01)

        def reset(self, obj, pose, seed=0):
            self.cuts = []

        def state(self):
            return SimpleNamespace(x=[X], damage=[np.zeros(len(X), bool)], sweeps=[None])

        def cut(self, action):
            self.cuts.append(action)

    class OneCut:
        def reset(self, goal, seed=None):
            self.n = 0

        def act(self, obs):
            self.n += 1
            return raw if self.n == 1 else None

    goal = SimpleNamespace(points=X, labels=np.zeros(len(X), np.int32), fragments=[X], steps=[])
    result = SimpleNamespace(total=0.0, cut_count=0, per_goal=[])
    spec = EpisodeSpec("slice", "cube", "in", 0, 0, ObjectPose())
    kw = dict(goal_fn=lambda *a: goal, discover_fn=lambda *a: np.zeros(len(X), np.int32),
              reward_fn=lambda *a: result, max_cuts=2)
    for policy in (OneCut(), TeleopReplay([raw.to_vector().tolist()])):
        env = Env()
        res = evaluate_episode(spec, policy, env, task_config("slice"), **kw)
        assert env.cuts == [executed_action(KnifeAction.from_vector(raw.to_vector()))
                            if isinstance(policy, TeleopReplay) else done]
        assert KnifeAction.from_vector(res.actions[0]) == env.cuts[0]  # the stored vector is the executed pose
