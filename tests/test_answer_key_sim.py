"""The answer key in the simulator: the oracle through `stage=eval` earns full marks (issue: the reference solution).

`python -m topocut.run stage=eval` at 64^3 with 5 cm pieces (Table 1's paper-scale run), the oracle alone, on
slice, stick and dice for the cube and the potato, 5 cuts each, at the protocol's random poses: mean raw R >= 0.9
per task, every episode >= 0.75, and success (N_C = G and R >= task.success_threshold) where the episode's own R
and N_C say so.  ~5 min on one core of a 2-core CPU.

The donut (the unseen object) was the third until 2026-12-02: its three episodes cost ~140 of the test's ~440 s
and put make test past 20 min on the 2-core machine (20:28-21:37).  The cube's slabs are the ones that lean
(docs/sim.md) and the potato is the irregular seen shape; the donut's steps are executed on its particles at every
pose at 64^3 and 128^3 by tests/test_answer_key.py, and in the simulator at 128^3 by the GPU check of docs/results.md
(all nine objects).
"""
import json

import pytest

from tests.test_stages import _ok, topocut
from topocut.sim.objects import ObjectPose
from topocut.tasks import get_task, piece_sizes, task_config


@pytest.mark.slow
def test_oracle_through_the_eval_stage_scores_full_marks(tmp_path):
    proc = _ok(topocut(tmp_path, "stage=eval", "scale=smoke", "sim.n_grid=64", "eval.policies=[oracle]",
                       "eval.tasks=[slice,stick,dice]", "eval.seen=[cube,potato]", "eval.unseen=[]",
                       "eval.max_cuts=5", "eval.gifs=0", "eval.videos=0", "eval.jobs=1", "logger=none", "progress=false",
                       timeout=1200))  # one process: make test's other worker has the other core
    episodes = sorted(tmp_path.glob("eval/table1/v001/episodes/oracle/*.json"))
    assert len(episodes) == 6, proc.stdout[-2000:]
    by_task = {}
    threshold = task_config("slice").success_threshold
    for path in episodes:
        ep = json.loads(path.read_text())
        assert ep["status"] == "ok", (path.name, ep["error"])
        r = ep["final_reward"]
        assert r >= 0.75, (path.name, ep["rewards"], ep["num_pieces"])
        by_task.setdefault(ep["spec"]["task"], []).append(r)
        # one success: every goal piece made (N_C = G, G counted from the episode's own goal) and R at the threshold
        spec = ep["spec"]
        cfg = task_config(spec["task"], **piece_sizes(spec["task"], 0.05), max_cuts=5)
        G = len(get_task(spec["task"]).make_goal(cfg, spec["object"], ObjectPose(**spec["pose"]), 0.5 / 64,
                                                 seed=spec["seed"]).fragments)
        assert ep["success"] == (ep["final_cut_count"] >= G and r >= threshold), (path.name, G, ep["cut_counts"], r)
    for task, rs in by_task.items():
        assert sum(rs) / len(rs) >= 0.9, (task, rs)
