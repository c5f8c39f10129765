"""Why an episode scores what it scores: the oracle's cuts, fragment by fragment (docs/tasks.md, docs/results.md).

Simulated (default): runs the oracle (the goal's own steps at the episode's true pose, topocut.planning.oracle)
through the episode engine on evaluation episodes and prints, after every cut, each fragment's role (goal piece,
rest, planned offcut, waste), its distance d to its goal piece, its weight w and value, and the simulator's own
pieces (its bond components, ``CuttingEnv.piece``) beside what topology discovery reports: their counts and the
worst IoU of a discovered fragment with its best simulator piece.  ``--render`` writes the cutting sequence.

    python experiments/oracle_audit.py --task dice --object potato                       # CPU, 64^3, 5 cm pieces
    python experiments/oracle_audit.py --task stick --object cube --episodes 2 --render /tmp/seq.png
    python experiments/oracle_audit.py --device cuda --n-grid 128 --size 0.03 --task dice --object cake
    python experiments/oracle_audit.py --task slice --object potato --episodes 4 --batch 4 --save /tmp/a  # as eval

Summary (``--summary DIR``): an evaluation artifact's oracle episodes (``stage=eval "eval.policies=[oracle]"``): mean
raw R per task x split and per object, the least, success, and the simulator's pieces against discovery's
(the worst IoU of a discovered piece with its simulator piece, ``EpisodeResult.piece_iou``).

    python experiments/oracle_audit.py --summary outputs/eval/table1/v001

Ideal (``--ideal``): the goal's steps on the ideal particle set, no physics (topocut.tasks.ideal), for every
evaluation object at four poses: R, N_C / G and the pieces, one line each (tests/test_answer_key.py's check).

    python experiments/oracle_audit.py --ideal --n-grid 128 --size 0.03
"""
import argparse
import json
import os
import time

import numpy as np
import yaml

POSES = [(0.5, 0.5, 0.0, 1.0), (0.52, 0.48, 0.2, 0.8), (0.48, 0.515, -0.25, 1.2), (0.505, 0.49, 0.1, 1.0)]


def roles(res) -> list[str]:
    """Each fragment's role in a RewardResult."""
    out = ["waste"] * len(res.values)
    for f, g in res.matching:
        out[f] = f"goal {g}"
    if res.stock is not None:
        out[res.stock] = "rest"
    for f, share in res.offcuts:
        out[f] = "offcut" if share >= 1 - 1e-9 else f"offcut {share:.0%}"
    return out


def best_iou(ids: np.ndarray, piece: np.ndarray) -> float:
    owners, counts = np.unique(piece[ids], return_counts=True)
    p = owners[np.argmax(counts)]
    inter = counts.max()
    return float(inter / (len(ids) + (piece == p).sum() - inter))


def audit_cut(k, x, labels, piece, goal, reward_cfg):
    from topocut.reward import spectral_reward

    ids = [c for c in np.unique(labels) if c >= 0 and (labels == c).sum() >= 4]
    frags = [x[labels == c] for c in ids]
    res = spectral_reward(frags, goal.fragments, reward_cfg, offcuts=goal.offcuts)
    sim_pieces = int((np.bincount(piece) >= 4).sum())
    ious = [best_iou(np.flatnonzero(labels == c), piece) for c in ids]
    print(f"  cut {k}: R {res.total:.3f} (unclipped {res.unclipped:+.3f}), N_C {res.cut_count} of "
          f"{len(goal.fragments)}; pieces: discovered {len(ids)}, simulator {sim_pieces}; "
          f"min IoU {min(ious):.3f}")
    role = roles(res)
    for i, c in enumerate(ids):
        g = next((g for f, g in res.matching if f == i), None)
        d = f"{res.distances[i, g]:.3f}" if g is not None else "  -  "
        # unmatched: how far the nearest goal piece is (the reward's d; inf where the fragment is too small)
        near = "" if g is not None or not np.isfinite(res.distances[i]).any() else \
            f"  nearest goal {int(np.argmin(res.distances[i]))} d {float(np.min(res.distances[i])):.3f}"
        print(f"    cluster {c:3d}: {len(frags[i]):6d} particles  {role[i]:12s} d {d}  w {res.weights[i]:.3f}  "
              f"value {res.values[i]:+.3f}  IoU {ious[i]:.3f}  extents {extents(frags[i])}{near}")
    return res, min(ious)


def simulated_batch(args):
    """``--batch B``: the episodes in batches of B scenes, as stage=eval runs them (sim.batch_size), one line per cut
    and scene: discovery's pieces against the simulator's and R.  Where they disagree (IoU < 0.95) and ``--save`` is
    given, the cut's inputs are saved (positions, damage, sweep, previous labels, start positions, the simulator's
    pieces) so that discovery can be re-run on them anywhere (topocut.topology.discover)."""
    from topocut.episode import Episode, EpisodeBatch, eval_episode_seed, make_scoring, piece_agreement
    from topocut.eval.config import EvalConfig
    from topocut.eval.protocol import episode_pose
    from topocut.planning.oracle import OraclePolicy
    from topocut.reward import RewardConfig
    from topocut.sim.config import SimConfig
    from topocut.sim.env import CuttingEnv
    from topocut.sim.runtime import init_taichi
    from topocut.tasks import piece_sizes, task_config

    init_taichi(args.device)
    sim = SimConfig(n_grid=args.n_grid, arch=args.device,
                    **{k: yaml.safe_load(v) for k, v in (a.split("=", 1) for a in args.sim)})
    env = CuttingEnv(sim, batch_size=args.batch)
    reward_cfg = RewardConfig(**{k: yaml.safe_load(v) for k, v in (a.split("=", 1) for a in args.reward)}).on(args.device)
    scoring = make_scoring(reward_cfg, device=args.topology_device or args.device, board_z=sim.board_z)
    task = task_config(args.task, **piece_sizes(args.task, args.size), max_cuts=args.max_cuts,
                       push=args.task in ("stick", "dice"))
    ids = list(range(args.first, args.first + args.episodes))
    for c0 in range(0, len(ids), args.batch):
        chunk = ids[c0:c0 + args.batch]
        eps = []
        for e in chunk:
            seed = eval_episode_seed(args.seed, args.task, args.object, e)
            eps.append(Episode(args.object, episode_pose(EvalConfig(seed=args.seed), seed), seed, task))
        engine = EpisodeBatch(env, scoring, max_cuts=args.max_cuts)
        engine.start(eps, alone=False)
        pols = [OraclePolicy(g, board_z=sim.board_z) for g in engine.goals]
        k = 0
        while any(engine.live):
            acts = [None] * len(chunk)
            for b in range(len(chunk)):
                if engine.live[b]:
                    obs = engine.observation(b)
                    obs["particles"] = engine.xs[b]
                    acts[b] = pols[b].act(obs)
            if not any(a is not None for a in acts):
                break
            before = [np.asarray(lab).copy() for lab in engine.labels]
            starts = [np.asarray(x).copy() for x in engine.xs]
            engine.step(acts)
            k += 1
            st = env.state()
            for b, e in enumerate(chunk):
                if acts[b] is None or not engine.logs[b].rewards:
                    continue
                n_sim, iou = piece_agreement(engine.labels[b], env.piece[b, :len(engine.labels[b])])
                print(f"{args.task}/{args.object} episode {e} (scene {b}) cut {k}: R {engine.logs[b].rewards[-1]:.3f}, "
                      f"pieces discovered {engine.logs[b].num_pieces[-1]}, simulator {n_sim}, min IoU {iou:.3f}")
                if args.save and iou < 0.95:
                    x, dmg = st.scene(b) if hasattr(st, "scene") else (st.x[b], st.damage[b])
                    np.savez_compressed(f"{args.save}_{args.task}_{args.object}_{e}_cut{k}_batch.npz",
                                        x=np.asarray(x), damage=np.asarray(dmg), labels=engine.labels[b],
                                        previous=before[b], start=starts[b], piece=env.piece[b, :len(x)],
                                        sweeps=json.dumps([w.asdict() for w in st.sweeps[b]]))
        for b, log in enumerate(engine.finish()):
            print(f"{args.task}/{args.object} episode {chunk[b]}: final R "
                  f"{log.rewards[-1] if log.rewards else float('nan'):.3f}")


def extents(x: np.ndarray) -> str:
    """A fragment's principal extents (largest first) in mm: what the size term of d compares."""
    if len(x) < 4:
        return "-"
    proj = (x - x.mean(0)) @ np.linalg.svd(x - x.mean(0), full_matrices=False)[2].T  # k,3 in principal axes
    return "x".join(f"{1000 * e:.0f}" for e in np.ptp(proj, axis=0))


def simulated(args):
    from topocut.episode import Episode, EpisodeBatch, eval_episode_seed, make_scoring, piece_agreement
    from topocut.eval.config import EvalConfig
    from topocut.eval.protocol import episode_pose
    from topocut.planning.oracle import OraclePolicy
    from topocut.reward import RewardConfig
    from topocut.sim.config import SimConfig
    from topocut.sim.env import CuttingEnv
    from topocut.sim.render import render_sequences
    from topocut.sim.runtime import init_taichi
    from topocut.tasks import piece_sizes, task_config

    init_taichi(args.device)
    overrides = {k: yaml.safe_load(v) for k, v in (a.split("=", 1) for a in args.sim)}
    sim = SimConfig(n_grid=args.n_grid, arch=args.device, **overrides)
    env = CuttingEnv(sim, batch_size=1)
    reward_cfg = RewardConfig(**{k: yaml.safe_load(v) for k, v in (a.split("=", 1) for a in args.reward)}).on(args.device)
    dev = args.topology_device or ("cuda" if args.device == "cuda" else "cpu")
    scoring = make_scoring(reward_cfg, device=dev, board_z=sim.board_z)
    rows = []
    for e in range(args.first, args.first + args.episodes):
        seed = eval_episode_seed(args.seed, args.task, args.object, e)
        pose = episode_pose(EvalConfig(seed=args.seed), seed)
        task = task_config(args.task, **piece_sizes(args.task, args.size), max_cuts=args.max_cuts,
                           push=args.task in ("stick", "dice"))
        engine = EpisodeBatch(env, scoring, max_cuts=args.max_cuts, frames=bool(args.render))
        t0 = time.perf_counter()
        engine.start([Episode(args.object, pose, seed, task)], alone=True)
        policy = OraclePolicy(engine.goals[0], board_z=sim.board_z)
        goal = engine.goals[0]
        print(f"{args.task}/{args.object} episode {e} (seed {seed}, scale {pose.scale:.2f}, yaw {pose.yaw:+.2f}): "
              f"{len(goal.fragments)} goal pieces, {len(goal.offcuts)} planned offcuts, steps "
              f"{' '.join(s.kind for s in goal.steps)}")
        print("  goal pieces: " + ", ".join(f"{g} {len(f)} particles {extents(np.asarray(f))}"
                                            for g, f in enumerate(goal.fragments)))
        k = 0
        while engine.live[0]:
            obs = engine.observation(0)
            obs["particles"] = engine.xs[0]
            action = policy.act(obs)
            if action is None:
                break
            before = np.asarray(engine.labels[0]).copy()
            engine.step([action])
            k += 1
            if args.compare_cpu and engine.logs[0].status == "ok":  # the same inputs, discovered on the host
                from topocut.topology import discover

                st = env.state()
                x, dmg = st.scene(0) if hasattr(st, "scene") else (st.x[0], st.damage[0])
                lab = discover(np.asarray(x), np.asarray(dmg, bool), st.sweeps[0], previous_labels=before,
                               device="cpu").labels
                n_sim, iou = piece_agreement(lab, env.piece[0, :len(lab)])
                print(f"  cut {k} discovered on the CPU: {len(np.unique(lab[lab >= 0]))} pieces, min IoU {iou:.3f}")
            if engine.logs[0].status != "ok":
                print(f"  {engine.logs[0].status}: {engine.logs[0].error}")
                break
            audit_cut(k, engine.xs[0], engine.labels[0], env.piece[0, :len(engine.xs[0])], goal, reward_cfg)
            if args.save:  # the state after the cut, to compare runs (e.g. CPU against GPU) particle by particle
                np.savez_compressed(f"{args.save}_{args.task}_{args.object}_{e}_cut{k}.npz", x=engine.xs[0],
                                    labels=engine.labels[0], piece=env.piece[0, :len(engine.xs[0])])
        log = engine.finish()[0]
        print(f"  final R {log.rewards[-1] if log.rewards else float('nan'):.3f}, success "
              f"{bool(log.successes and log.successes[-1])}, turns after cuts {log.turns}, "
              f"{time.perf_counter() - t0:.1f} s")
        if args.render:
            rows.append((f"{args.object} e{e}", [(x, lab, knife, what) for x, lab, what, knife in log.frames]))
    if args.render:
        print(render_sequences(rows, args.render, board_z=sim.board_z))


def ideal_sweep(args):
    from topocut.eval.config import EvalConfig
    from topocut.reward import spectral_reward
    from topocut.sim.objects import ObjectPose, sample_object
    from topocut.tasks import get_task, ideal, piece_sizes, task_config

    spacing = 0.5 / args.n_grid
    objects = [args.object] if args.object != "all" else EvalConfig().seen + EvalConfig().unseen
    tasks = [args.task] if args.task != "all" else ["slice", "stick", "dice"]
    worst = 1.0
    print("| task | object | pose | G | planned offcuts | pieces | R | N_C |\n|---|---|---|---|---|---|---|---|")
    for task in tasks:
        for obj in objects:
            for i, p in enumerate(POSES):
                pose = ObjectPose(*p)
                # push=False: the audit's plans as recorded (docs/results.md), whatever the task's own push
                cfg = task_config(task, **piece_sizes(task, args.size), max_cuts=args.max_cuts, push=False)
                goal = get_task(task).make_goal(cfg, obj, pose, spacing, seed=args.seed)
                pts, _ = sample_object(obj, pose, spacing, seed=args.seed)
                run = ideal.execute(pts.astype(np.float64), goal.steps, ideal.sim_config_for(spacing, 0.05))
                frags = [run.x[run.piece == q] for q in np.unique(run.piece)]
                res = spectral_reward(frags, goal.fragments, offcuts=goal.offcuts)
                worst = min(worst, res.total)
                print(f"| {task} | {obj} | {i} | {len(goal.fragments)} | {len(goal.offcuts)} | {len(frags)} | "
                      f"{res.total:.3f} | {res.cut_count} |", flush=True)
    print(f"lowest R: {worst:.3f}")


def summary(path):
    import json
    from collections import defaultdict
    from pathlib import Path

    eps = [json.loads(p.read_text()) for p in sorted(Path(path).glob("episodes/oracle/*.json"))]
    if not eps:
        raise SystemExit(f"--summary: no oracle episodes under {path}/episodes/oracle")
    cells, objects = defaultdict(list), defaultdict(list)
    for e in eps:
        cells[(e["spec"]["task"], e["spec"]["split"])].append(e)
        objects[(e["spec"]["task"], e["spec"]["object"])].append(e["final_reward"])
    print(f"{len(eps)} oracle episodes in {path}")
    print("| task | split | episodes | mean raw R | least R | success | worst piece IoU | not ok |")
    print("|---|---|---|---|---|---|---|---|")
    for (task, split), es in sorted(cells.items()):
        r = [e["final_reward"] for e in es]
        iou = [min(e["piece_iou"]) for e in es if e.get("piece_iou")]
        print(f"| {task} | {split} | {len(es)} | {np.mean(r):.3f} | {min(r):.3f} | "
              f"{np.mean([e['success'] for e in es]):.2f} | {min(iou) if iou else float('nan'):.3f} | "
              f"{sum(e['status'] != 'ok' for e in es)} |")
    print("\n| task | object | mean raw R | least |\n|---|---|---|---|")
    for (task, obj), r in sorted(objects.items()):
        print(f"| {task} | {obj} | {np.mean(r):.3f} | {min(r):.3f} |")


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--task", default=None, help="slice | stick | dice (default dice; --ideal: or all, the default)")
    ap.add_argument("--object", default=None, help="an object (default potato; --ideal: or all, the default)")
    ap.add_argument("--device", default="cpu", choices=["cpu", "cuda"])
    ap.add_argument("--n-grid", type=int, default=64)
    ap.add_argument("--size", type=float, default=0.05, help="thickness = width = die size [units]")
    ap.add_argument("--max-cuts", type=int, default=5)
    ap.add_argument("--seed", type=int, default=0, help="the evaluation's base seed (--ideal: the sampling seed)")
    ap.add_argument("--episodes", type=int, default=1)
    ap.add_argument("--first", type=int, default=0, help="first episode index of the (task, object) cell")
    ap.add_argument("--render", default="", help="write the cutting sequence here (PNG)")
    ap.add_argument("--ideal", action="store_true", help="no physics: the steps on the ideal particle set")
    ap.add_argument("--topology-device", default="", help="where discovery runs (default: the simulator's device)")
    ap.add_argument("--compare-cpu", action="store_true", help="also discover each state on the CPU")
    ap.add_argument("--sim", nargs="*", default=[], metavar="KEY=VALUE",
                    help="simulator settings (SimConfig keys), e.g. --sim kerf_half_width=0.006")
    ap.add_argument("--reward", nargs="*", default=[], metavar="KEY=VALUE",
                    help="reward settings (RewardConfig keys), e.g. --reward backend=torch eig_solver=subspace "
                         "(stage=eval's reward=torch on the GPU)")
    ap.add_argument("--save", default="", help="write each cut's state to <SAVE>_<task>_<object>_<e>_cut<k>.npz")
    ap.add_argument("--batch", type=int, default=0,
                    help="run the episodes in batches of this many scenes, as stage=eval does (sim.batch_size)")
    ap.add_argument("--summary", default="", help="summarise the oracle episodes of this evaluation artifact")
    args = ap.parse_args()
    if args.save and os.path.dirname(args.save):
        os.makedirs(os.path.dirname(args.save), exist_ok=True)
    if args.summary:
        summary(args.summary)
    elif args.ideal:
        args.task, args.object = args.task or "all", args.object or "all"
        ideal_sweep(args)
    else:
        args.task, args.object = args.task or "dice", args.object or "potato"
        simulated_batch(args) if args.batch else simulated(args)


if __name__ == "__main__":
    main()
