"""Gymnasium environments (topocut.envs, docs/gym.md): the docs' example runs, the vector env's spaces / reset /
step contracts hold, and the single-scene env passes gymnasium's env checker.  Tiny: n_grid 32, cube."""
import re
from pathlib import Path

import numpy as np
import pytest

gym = pytest.importorskip("gymnasium")

DOC = Path(__file__).resolve().parents[1] / "docs" / "gym.md"


@pytest.fixture(scope="module")
def example():
    code = re.search(r"```python\n(.*?)```", DOC.read_text(), re.S).group(1)
    assert len(code.strip().splitlines()) <= 10, "docs/gym.md promises a ten-line example"
    ns = {}
    exec(compile(code, str(DOC), "exec"), ns)  # noqa: S102 - the documented example, verbatim
    return ns


def test_docs_example_and_vector_contracts(example):
    from gymnasium.vector import AutoresetMode, VectorEnv

    env, obs, B = example["env"], example["obs"], 2
    assert isinstance(env, VectorEnv) and env.num_envs == B
    assert env.metadata["autoreset_mode"] == AutoresetMode.DISABLED
    assert env.single_action_space.shape == (4,) and env.single_action_space.dtype == np.float32
    assert env.action_space.shape == (B, 4)
    assert env.single_action_space.high[3] == env.single_action_space.low[3] == 0  # slice: vertical cuts
    shapes = {"points": (256, 3), "labels": (256,), "history": (3, 7), "goal": (256, 3), "goal_labels": (256,),
              "cuts_done": ()}
    for k, shape in shapes.items():
        assert env.single_observation_space[k].shape == shape, k
        assert env.observation_space[k].shape == (B,) + shape, k
        assert obs[k].shape == (B,) + shape and obs[k].dtype == env.observation_space[k].dtype, k
    assert env.observation_space.contains(obs)
    reward, term, trunc, info = example["reward"], example["terminated"], example["truncated"], example["info"]
    assert reward.shape == (B,) and reward.dtype == np.float64
    assert term.shape == trunc.shape == (B,) and term.dtype == trunc.dtype == np.bool_
    assert (term | trunc).all()  # max_cuts = 1: every episode ended
    assert (obs["cuts_done"] == 1).all() and (info["num_pieces"] >= 2).all()  # both cuts went through
    np.testing.assert_allclose(reward, info["reward_total"])  # reward_mode "total": R after the cut
    assert not np.array_equal(obs["labels"][0], obs["labels"][1]) or not np.allclose(obs["points"][0],
                                                                                     obs["points"][1])
    # reset with the same seed gives the same observation; scene b holds the episode of seed 5 + b (its own pose)
    o1, i1 = env.reset(seed=5)
    o2, _ = env.reset(seed=5)
    for k in o1:
        np.testing.assert_array_equal(o1[k], o2[k], err_msg=k)
    assert i1["episode_seed"].tolist() == [5, 6] and not np.allclose(o1["points"][0], o1["points"][1])
    assert (o1["cuts_done"] == 0).all() and not o1["history"].any()
    with pytest.raises(ValueError, match="reset_mask"):
        env.reset(seed=5, options={"reset_mask": np.array([True, False])})
    env.close()


def test_single_env_passes_gymnasium_env_checker():
    from gymnasium.utils.env_checker import check_env

    from topocut.envs import CuttingEnvGym
    from topocut.sim.config import SimConfig

    env = CuttingEnvGym(task="slice", objects="cube", sim_cfg=SimConfig(n_grid=32), max_cuts=2, num_points=128,
                        num_goal_points=128)
    check_env(env, skip_render_check=True, skip_close_check=True)
    obs, info = env.reset(seed=1)
    assert env.observation_space.contains(obs) and info["num_pieces"] == 1
    obs, r, term, trunc, info = env.step(np.array([0.5, 0.5, 0.0, 0.0], np.float32))
    assert isinstance(r, float) and isinstance(term, bool) and isinstance(trunc, bool)
    assert obs["cuts_done"] == 1 and not trunc  # 1 of max_cuts = 2
    env.close()


def test_scenes_of_different_objects_and_an_idle_scene():
    """Each scene draws its own object; a scene whose episode ended idles while the other cuts on."""
    from topocut.envs import CuttingVectorEnv
    from topocut.sim.config import SimConfig

    env = CuttingVectorEnv(task="slice", objects=["cube", "cake"], num_envs=2, sim_cfg=SimConfig(n_grid=32),
                           max_cuts=2, num_points=128, num_goal_points=128)
    for seed in range(20):  # a seed whose two scenes drew different objects
        obs, info = env.reset(seed=seed)
        if len(set(env.object)) == 2:
            break
    assert len(set(env.object)) == 2 and len(set(map(len, env.engine.xs))) == 2  # two particle counts
    a = np.array([[0.5, 0.5, 0.0, 0.0], [0.5, 0.5, 0.0, 0.0]], np.float32)
    env.done[1] = True  # as if scene 1 had ended: it must not move
    x1 = env.engine.xs[1].copy()
    obs, r, term, trunc, info = env.step(a)
    assert info["_num_pieces"].tolist() == [True, False] and r[1] == 0.0 and obs["cuts_done"].tolist() == [1, 0]
    assert np.array_equal(env.sim.get_state(1)["x"], x1) and info["num_pieces"][0] >= 2
    env.close()
