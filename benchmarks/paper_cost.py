"""`make paper` at its own sizes, projected: every stage run for real but shortened, timed, scaled to the config.

GPU, under the processes and MPS of `make paper` (start the daemon as benchmarks/gpu.sh's mps_start does; this script
manages no daemon):

    export CUDA_MPS_PIPE_DIRECTORY=/tmp/mps-pipe CUDA_MPS_LOG_DIRECTORY=/tmp/mps-log
    mkdir -p $CUDA_MPS_PIPE_DIRECTORY $CUDA_MPS_LOG_DIRECTORY && nvidia-cuda-mps-control -d
    python benchmarks/paper_cost.py --out /tmp/paper_cost --minutes 8             # scale=paper: 128³, 3 cm pieces
    python benchmarks/paper_cost.py --out /tmp/paper_cost64 --set sim.n_grid=64   # the same at 64³
    echo quit | nvidia-cuda-mps-control

CPU (the plumbing; tests/test_paper_cost.py runs a smaller one):

    .venv/bin/python benchmarks/paper_cost.py --scale smoke --device cpu --out /tmp/paper_cost_cpu \\
        --episodes 2 --epochs 1 2 --train-episodes 4 --set sim.n_grid=32

Each stage is `make paper`'s command, `python -m topocut.run stage=all stage.run.sequence=[<stage>] scale=<scale>
device=<device> reward=torch trainer=gpu logger=csv` (trainer=cpu on the CPU), plus `--set` and `--jobs` (data.jobs,
eval.jobs), into `<out>/outputs`.  The full sizes come from the same config without the script's size overrides:

- simulate: the stage itself, its wall time.
- demonstrations: `--episodes` a cell of data.tasks x data.objects, in parts over data.jobs processes as `make paper`
  makes them, from episode data.heuristic_every - 1 so that the heuristic comparison (every n-th episode) runs in a
  warm episode.  From the episode records: each task's seconds an episode in one process (a part's first episode left
  out: compilation lands there) and a comparison's; a process's first part's extra; a part's run time outside its
  episodes; the residual of the wall time is the start-up.  Full: `make paper`'s parts (pipelines.all.demo_runs),
  list-scheduled over data.jobs workers.  merge: stage=all's merge of the parts, seconds an episode x the full count.
- pretrain, bc: the dataset just made, copied to `--train-episodes` episodes (default a quarter of the full count:
  whole batches, the full train/val ratio), trained for K1 and K2 epochs (`--epochs`; bc's default 1 and 1 +
  policy.train.val_sample_every, so that the extra epochs sample val/mask_acc as often as a long training); the
  difference is the steady epoch, the intercept the start-up.  Full: epochs x an epoch at the full episode count.
  With one size the whole epoch scales with the episodes (an upper bound: an epoch also has a fixed part); with two
  (`--train-episodes 64 256`) the line through both sizes' epochs (epoch_cost).  bc: every learned policy,
  eval.train_seeds seeds, trainer.jobs at once, as `make paper`.
- eval: `--eval-episodes` a (task, object) cell for every policy and training seed in eval.jobs processes; each work
  unit's process seconds (a batch of sim.batch_size specs, or one MPPI spec: topocut.eval.runner.eval_tasks) by
  policy.  Full: the protocol's units list-scheduled over eval.jobs workers, plus the measured start-up and report.

Every row: projected = fixed + count x rate / processes (paper_cost.json holds each term).  `--minutes` stops a stage's
command after that long: the demonstrations and the evaluation are then scaled from the episodes that finished (none:
a lower bound, marked >=); a stopped training is left unmeasured.  `--stages` runs some stages into the same `--out`,
keeping the other rows of its paper_cost.json (e.g. one device call each); a stage that would reuse an artifact of an
earlier run stops (nothing measured): use a fresh --out.  The projection errs high where the measurement cannot
separate: each command pays its own start-up (`make paper` once for its in-process stages), every part pays the
overhead of a process's first part (its simulator's build) unless some process ran two, the merge scales whole.
"""
from __future__ import annotations

import argparse
import contextlib
import heapq
import json
import math
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
STAGES = ("simulate", "mppi", "pretrain", "bc", "eval")
ROWS = ("simulate", "demonstrations", "merge", "pretrain", "bc", "eval")
TARGET_H = 3.0


# -- the arithmetic (pure; tests/test_paper_cost.py checks it by hand) -------------------------------------------
def list_schedule(costs, workers: int, first_extra: float = 0.0) -> float:
    """Makespan of ``costs`` handed out in order, each to the first free of ``workers`` (joblib, batch_size=1);
    a worker's first unit costs ``first_extra`` more."""
    ends: list[float] = []
    for c in costs:
        if len(ends) < max(1, workers):
            heapq.heappush(ends, first_extra + c)
        else:
            heapq.heappush(ends, heapq.heappop(ends) + c)
    return max(ends, default=0.0)


def fit_epochs(k1: int, w1: float, k2: int, w2: float) -> tuple[float, float]:
    """(seconds an epoch, fixed seconds) from runs of k1 < k2 epochs taking w1, w2 s; (w2 / k2, 0), an upper bound
    of the epoch, when the difference is not positive (noise)."""
    if k2 > k1 and w2 > w1:
        per = (w2 - w1) / (k2 - k1)
        return per, max(0.0, w1 - k1 * per)
    return w2 / max(k2, 1), 0.0


def epoch_cost(sizes: list[tuple[int, float]]) -> tuple[float, float]:
    """An epoch's (fixed seconds, seconds an episode) from (episodes, seconds an epoch) at one or two dataset sizes.
    One size: all of it scales with the episodes (an upper bound where an epoch has a fixed part: validation's start,
    the checkpoint, the loaders' workers).  Two: the line through both (fit_epochs' rule: no positive slope, the
    larger size's epoch over its episodes, no fixed part)."""
    if len(sizes) == 1:
        (n, per), = sizes
        return 0.0, per / n
    (n1, e1), (n2, e2) = sorted(sizes)
    per_episode, fixed = fit_epochs(n1, e1, n2, e2)
    return fixed, per_episode


def demo_costs(parts, t: dict, h: dict, every: int, overhead: float) -> tuple[list[float], float]:
    """Each demonstration part's (task, first episode, episodes) process seconds, overhead + its episodes at t[task]
    + h[task] for each episode index that is a multiple of ``every`` (the heuristic comparison; 0: none); and the
    sum over the parts without the overheads."""
    costs, work = [], 0.0
    for task, first, n in parts:
        w = n * t[task] + (h.get(task, 0.0) * sum(e % every == 0 for e in range(first, first + n)) if every else 0.0)
        costs.append(overhead + w)
        work += w
    return costs, work


def demo_rates(parts: list[dict]) -> dict:
    """From demonstration parts {"task", "pid", "started", "seconds" (the run's, or None), "records" (episodes.jsonl)}:
    t, h: each task's mean seconds of an MPPI episode and of a heuristic comparison, a part's first episode left out
    where it has more; overhead: a part's seconds outside its episodes (the parts after a process's first where
    any, else all); extra: a process's first part above that (its first episode over t + h, its overhead over the
    later parts')."""
    for p in parts:
        p["records"] = sorted(p["records"], key=lambda x: x["started"])
    steady: dict[str, list] = {}
    for p in parts:
        steady.setdefault(p["task"], []).extend(p["records"][1:] or p["records"])
    all_h = [x["heuristic_time_s"] for p in parts for x in p["records"] if "heuristic_time_s" in x]
    t, h = {}, {}
    for task, rs in steady.items():
        if not rs:  # no episode of this task finished: the caller bounds it
            continue
        t[task] = sum(x["time_s"] for x in rs) / len(rs)
        hs = [x["heuristic_time_s"] for x in rs if "heuristic_time_s" in x] or all_h
        h[task] = sum(hs) / len(hs) if hs else 0.0
    seen, firsts, later = set(), [], []
    for p in sorted(parts, key=lambda p: p["started"]):
        out = None if p["seconds"] is None else \
            p["seconds"] - sum(x["time_s"] + x.get("heuristic_time_s", 0.0) for x in p["records"])
        (firsts if p["pid"] is None or p["pid"] not in seen else later).append((p, out))
        seen.add(p["pid"])
    outs = [o for _, o in later if o is not None] or [o for _, o in firsts if o is not None]
    overhead = max(0.0, sum(outs) / len(outs)) if outs else 0.0
    extra = []
    for p, out in firsts:
        more, x = 0.0, p["records"][0] if p["records"] else {}
        if len(p["records"]) > 1:
            more += x["time_s"] - t[p["task"]] + (x["heuristic_time_s"] - h[p["task"]] if "heuristic_time_s" in x else 0)
        if later and out is not None:
            more += out - overhead
        extra.append(max(0.0, more))
    return {"t": t, "h": h, "overhead": overhead, "extra": sum(extra) / len(extra) if extra else 0.0}


def unit_costs(out: Path, units: list[tuple[str, list]]) -> tuple[list, float | None]:
    """Each evaluation work unit's (policy, specs) process seconds from the episode JSONs under ``out``: over the
    policy's runs (training seeds), the sum of the unit's batch time (its episodes ran as one batch, each recording
    the batch's time_s; an MPPI unit is one episode); None where a run has none of its episodes.  And the earliest
    episode start (file time - time_s), None without episodes."""
    runs = json.loads((out / "policies.json").read_text()) if (out / "policies.json").exists() else {}
    costs, starts = [], []
    for policy, specs in units:
        cost = 0.0
        for run in [k for k, v in runs.items() if v["policy"] == policy] or [policy]:
            files = [f for f in (out / "episodes" / run / f"{s.key}.json" for s in specs) if f.exists()]
            if not files:
                cost = None
                break
            times = [json.loads(f.read_text())["time_s"] for f in files]
            cost += max(times)
            starts += [f.stat().st_mtime - s for f, s in zip(files, times)]
        costs.append(cost)
    return costs, min(starts, default=None)


def make_row(stage: str, measured: str, rate_s: float, unit: str, count: float, count_unit: str, processes: int,
             fixed_s: float, complete: bool = True, **detail) -> dict:
    """A table row: projected_s = fixed_s + count x rate_s / processes."""
    return {"stage": stage, "measured": measured, "rate_s": rate_s, "rate_unit": unit, "count": count,
            "count_unit": count_unit, "processes": processes, "fixed_s": fixed_s,
            "projected_s": fixed_s + count * rate_s / processes, "complete": complete, "detail": detail}


# -- the config --------------------------------------------------------------------------------------------------
def compose(overrides: list[str]) -> dict:
    """The resolved config ("dict") and its eval group as topocut.eval.config.EvalConfig ("eval")."""
    from hydra import compose as hydra_compose
    from hydra import initialize_config_dir
    from omegaconf import OmegaConf

    from topocut.config import register_configs

    register_configs()
    with initialize_config_dir(config_dir=str(REPO / "conf"), version_base="1.3"):
        cfg = hydra_compose(config_name="config", overrides=overrides)
    return {"dict": OmegaConf.to_container(cfg, resolve=True), "eval": OmegaConf.to_object(cfg.eval)}


def demo_parts(config: dict) -> list[tuple[str, int, int]]:
    """stage=all's stage=mppi runs as (task, first episode, episodes), in the order they are handed out."""
    from pipelines.all import demo_runs

    data = config["data"]
    return [(own.get("task", config["task"]["name"]), int(own.get("data.first_episode", data["first_episode"])),
             int(own.get("data.episodes", data["episodes"]))) for _, own, _ in demo_runs(config)]


def eval_units(config: dict) -> tuple[list, list[tuple[str, list]], int]:
    """The protocol's specs, its work units [(policy, specs)] as the evaluation hands them out, and its runs (every
    policy once, each learned one once per training seed)."""
    from topocut.eval.protocol import episode_specs
    from topocut.eval.runner import LEARNED, eval_tasks, runs_one_at_a_time

    ev = config["eval"]
    specs, names = episode_specs(ev), list(ev.policies)
    units = eval_tasks(specs, names, max(1, int(config["dict"]["sim"]["batch_size"])),
                       {p for p in names if runs_one_at_a_time(p)})
    return specs, units, sum(ev.train_seeds if p in LEARNED else 1 for p in names)


# -- the runs ----------------------------------------------------------------------------------------------------
class Bench:
    def __init__(self, args):
        self.args, self.out = args, Path(args.out).resolve()
        self.root = self.out / "outputs"
        (self.out / "logs").mkdir(parents=True, exist_ok=True)
        jobs = [f"data.jobs={args.jobs}", f"eval.jobs={args.jobs}"] if args.jobs else []
        self.base = ["stage=all", f"scale={args.scale}", f"device={args.device}", "reward=torch",
                     f"trainer={'gpu' if args.device == 'cuda' else 'cpu'}", "logger=csv", "progress=false", *jobs,
                     *args.set]
        self.full = compose(self.base)
        self.cfg = self.full["dict"]
        self.n_full = sum(n for *_, n in demo_parts(self.cfg))  # the demonstrations, the trainings' dataset

    def run(self, tag: str, stage: str, extra: list[str]) -> dict:
        """One command: its wall seconds, launch time, stage=all status.json and run directory, whether stopped."""
        cmd = [sys.executable, "-m", "topocut.run", *self.base, f"stage.run.sequence=[{stage}]", *extra,
               f"outputs_root={self.root}"]
        log = self.out / "logs" / f"{tag}.log"
        print(f"  {tag}: {' '.join(cmd[3:])}", flush=True)
        launch, t0, stopped = time.time(), time.perf_counter(), False
        with open(log, "w") as f:
            proc = subprocess.Popen(cmd, cwd=REPO, stdout=f, stderr=subprocess.STDOUT, start_new_session=True,
                                    env={**os.environ, "WANDB_MODE": "disabled"})
            try:
                proc.wait(timeout=self.args.minutes * 60 if self.args.minutes else None)
            except subprocess.TimeoutExpired:  # the budget: SIGTERM (the stage keeps what it committed), then
                stopped = True                  # SIGKILL to what is left of the process group it started (workers)
                for sig in (signal.SIGTERM, signal.SIGKILL):
                    with contextlib.suppress(ProcessLookupError):
                        os.killpg(proc.pid, sig)
                    with contextlib.suppress(subprocess.TimeoutExpired):
                        proc.wait(timeout=60)
        wall = time.perf_counter() - t0
        if proc.returncode and not stopped:
            sys.exit(f"{tag} failed ({proc.returncode}); log {log}:\n{log.read_text()[-3000:]}")
        found = sorted(self.root.glob(f"runs/all/*-{proc.pid}/status.json"))
        status = json.loads(found[-1].read_text()) if found else {}
        if '"reused": true' in json.dumps(status.get("summary", {})):
            sys.exit(f"{tag}: reused an artifact of an earlier run under {self.root}, nothing measured: use a fresh --out")
        print(f"  {tag}: {wall:.1f} s{' (stopped at --minutes)' if stopped else ''}", flush=True)
        return {"wall": wall, "launch": launch, "status": status, "dir": found[-1].parent if found else None,
                "stopped": stopped}

    def simulate(self) -> list[dict]:
        r, c = self.run("simulate", "simulate", []), self.cfg
        return [make_row("simulate", f"the stage ({c['task']['name']}, {c['object']['name']}), start-up included",
                         r["wall"], "s", 1, "run", 1, 0.0, not r["stopped"])]

    def mppi(self) -> list[dict]:
        a, data = self.args, self.cfg["data"]
        every = int(data["heuristic_every"] or 0)
        first = every - 1 if every >= 2 and a.episodes >= 2 else 0
        sizes = [f"data.episodes={a.episodes}", f"data.first_episode={first}"]
        meas = compose(self.base + sizes)["dict"]
        r = self.run("mppi", "mppi", sizes)
        parts_m, parts_f = demo_parts(meas), demo_parts(self.cfg)
        jobs_m, jobs_f = (int(c["data"]["jobs"]) if len(p) > 1 else 1 for c, p in ((meas, parts_m), (self.cfg, parts_f)))
        tasks = data["tasks"] or [self.cfg["task"]["name"]]
        statuses = [json.loads(f.read_text()) for f in (r["dir"].glob("mppi*/status.json") if r["dir"] else [])]
        runs = {str(Path(st["summary"]["dataset"]).resolve()): st  # a committed part's run by its dataset directory
                for st in statuses if st.get("summary", {}).get("dataset")}
        parts = []  # every part's episode records, those of a part stopped before its commit too
        for f in self.root.glob("dataset/*/*/episodes.jsonl"):
            if f.stat().st_mtime >= r["launch"]:
                name, st = f.parent.parent.name, runs.get(str(f.parent.resolve()), {})
                recs = [json.loads(x) for x in f.read_text().splitlines() if x.strip()]
                parts.append({"task": next((t for t in tasks if name.startswith(f"{data['dataset']}-{t}-")), tasks[0]),
                              "pid": st.get("pid"), "started": st.get("started", 0.0), "seconds": st.get("seconds"),
                              "records": [x for x in recs if x.get("status") == "ok"] or recs})
        rates = demo_rates(parts)
        n_meas = sum(len(p["records"]) for p in parts)
        merge_s = r["status"].get("summary", {}).get("wall_s", {}).get("merge")
        seconds = [p["seconds"] for p in sorted(parts, key=lambda p: p["started"]) if p["seconds"] is not None]
        if not r["stopped"] and len(seconds) == len(parts_m):  # the residual of the wall time: start-up and the rest
            start = max(0.0, r["wall"] - (merge_s or 0.0) - list_schedule(seconds, jobs_m))
        else:  # stopped: from the launch to the first part's start
            start = min([s["started"] for s in statuses] + [x["started"] for p in parts for x in p["records"]],
                        default=r["launch"]) - r["launch"]
        # a task none of whose episodes finished within --minutes: its episode takes at least as long as the parts ran
        # (a lower bound, as is the whole row then)
        unfinished = [task for task in tasks if task not in rates["t"]]
        for task in unfinished:
            rates["t"][task] = r["wall"] - start
        costs_f, work = demo_costs(parts_f, rates["t"], rates["h"], every, rates["overhead"])
        span_f = list_schedule(costs_f, jobs_f, rates["extra"])
        rows = [make_row(
            "demonstrations", f"{n_meas} episode(s) ({a.episodes} a cell from episode {first}) in {jobs_m} process(es)",
            work / self.n_full, "s an episode in a process", self.n_full, "episodes", jobs_f,
            start + span_f - work / jobs_f, not r["stopped"] and n_meas > 0, **rates, start_up_s=start,
            parts=len(parts_f), schedule_s=span_f, lower_bound=bool(unfinished), unfinished=unfinished)]
        if len(parts_f) > 1:  # stage=all merges the parts' shards into one dataset
            ok = merge_s is not None and n_meas > 0
            rows.append(make_row("merge", f"merge of {n_meas} episodes" if ok else "not measured (no merge ran)",
                                 merge_s / n_meas if ok else 0.0, "s an episode", self.n_full, "episodes", 1, 0.0, ok))
        return rows

    def train_data(self, n: int) -> tuple[str, str, int]:
        """The latest dataset of data.dataset copied to n episodes: (name, version, episodes)."""
        from topocut.data.episodes import EpisodeDataset, EpisodeWriter
        from topocut.data.store import ArtifactStore

        store, name = ArtifactStore(self.root), self.cfg["data"]["dataset"]
        src = store.resolve("dataset", name, "latest")
        ds = EpisodeDataset(src / "data.zarr")
        writer, path = store.begin("dataset", f"{name}-train", {"copies_of": store.ref(src), "episodes": n},
                                   {"dataset": store.ref(src)})
        if writer is not None:
            w = EpisodeWriter(writer.path / "data.zarr", key_fields=("source",))
            for i in range(w.num_episodes, n):
                e = i % ds.num_episodes
                info = {k: v for k, v in ds.meta(e).items() if k != "num_steps"}
                w.append_arrays(ds.episode_arrays(e), {**info, "source": {"copy": i // ds.num_episodes, "episode": e}})
            path = writer.commit({"episodes": n, "steps": w.num_steps})
        return f"{name}-train", path.name, n

    def train(self, stage: str) -> list[dict]:
        from omegaconf import OmegaConf

        key = "trainer.max_epochs" if stage == "pretrain" else "policy.train.max_epochs"
        every = int(self.cfg["policy"]["train"]["val_sample_every"]) if stage == "bc" else 1
        k1, k2 = self.args.epochs or (1, 1 + (every if every > 1 else 2))
        sizes = sorted(self.args.train_episodes or [max(2, math.ceil(self.n_full / 4))])
        fits = []  # per dataset size: (episodes, seconds an epoch, fixed seconds, walls)
        for size in sizes:
            name, version, n = self.train_data(size)
            walls = []
            for k in (k1, k2):
                tag = f"{stage}-{k}" if len(sizes) == 1 else f"{stage}-{n}ep-{k}"
                r = self.run(tag, stage, [f"data.dataset={name}", f"data.version={version}", f"{key}={k}"])
                if r["stopped"]:
                    return [make_row(stage, f"not measured: {k} epochs of {n} episodes stopped at --minutes", 0.0, "",
                                     0, "", 1, 0.0, False)]
                walls.append(r["wall"])
            fits.append((n, *fit_epochs(k1, walls[0], k2, walls[1]), walls))
        epoch_a, per_episode = epoch_cost([(n, per) for n, per, *_ in fits])
        epochs = int(self.cfg["trainer"]["max_epochs"] if stage == "pretrain" else
                     self.cfg["policy"]["train"]["max_epochs"])
        fixed = fits[-1][2]  # the larger size's start-up, the nearer the full one's (loading the dataset grows with it)
        epoch_full = epoch_a + per_episode * self.n_full
        policies = ", ".join(OmegaConf.load(REPO / "conf" / "stage" / "bc.yaml").run.policies)
        what = "F" if stage == "pretrain" else \
            f"{policies} x {self.cfg['eval']['train_seeds']} seeds, {self.cfg['trainer']['jobs']} at once"
        of = " and ".join(f"{n} ({per:.1f} s an epoch)" for n, per, *_ in fits)
        return [make_row(stage, f"{what}: {k1} and {k2} epochs of {of} episodes; {epoch_full:.1f} s an epoch of "
                         f"{self.n_full}", epoch_full / self.n_full, "s an episode-epoch", epochs * self.n_full,
                         f"episode-epochs ({epochs} x {self.n_full})", 1, fixed, epoch_s=fits[-1][1],
                         walls_s=fits[-1][3], epochs=[k1, k2], train_episodes=fits[-1][0],
                         sizes=[{"episodes": n, "epoch_s": per, "fixed_s": f, "walls_s": w} for n, per, f, w in fits],
                         epoch_fixed_s=epoch_a, epoch_per_episode_s=per_episode,
                         epoch_upper_bound=not all(k2 > k1 and w[1] > w[0] for *_, w in fits))]

    def eval(self) -> list[dict]:
        sizes = [f"eval.episodes_per_cell={self.args.eval_episodes}"]
        meas = compose(self.base + sizes)
        r = self.run("eval", "eval", sizes)
        done = r["status"].get("summary", {}).get("eval", {}).get("eval")
        outs = [Path(done)] if done else sorted(self.root.glob(f"eval/{meas['eval'].name}/.partial-*"),
                                                key=os.path.getmtime)
        specs, units, _ = eval_units(meas)
        costs, first = unit_costs(outs[-1], units) if outs else ([None] * len(units), None)
        sub = r["dir"] / "eval" / "status.json" if r["dir"] else None
        began = json.loads(sub.read_text())["started"] if sub and sub.exists() else r["launch"]
        by = {p: [c for (q, _), c in zip(units, costs) if q == p and c is not None] for p, _ in units}
        missing = sorted(p for p, v in by.items() if not v)  # none finished: longer than the stage ran, a lower bound
        per = {p: sum(v) / len(v) if v else r["wall"] - (began - r["launch"]) for p, v in by.items()}
        jobs_m, jobs_f = (max(1, int(c["dict"]["eval"]["jobs"])) for c in (meas, self.full))
        specs_f, units_f, runs_f = eval_units(self.full)
        costs_f = [per[p] for p, _ in units_f]
        work, count = sum(costs_f), len(specs_f) * runs_f
        if not r["stopped"]:  # the residual of the wall time: start-up, the workers' set-up, the report, renders
            start = max(0.0, r["wall"] - list_schedule(costs, jobs_m))
        else:  # stopped: from the launch to the first episode's start, or the stage's
            start = max(0.0, (first or began) - r["launch"])
        n_meas = sum(c is not None for c in costs)
        return [make_row(
            "eval", f"{n_meas} of {len(units)} work units ({len(specs)} specs x {len(per)} policies, every seed) in "
            f"{jobs_m} process(es)", work / count, "s an episode in a process", count,
            f"episodes ({len(specs_f)} specs x {runs_f} runs)", jobs_f, start + list_schedule(costs_f, jobs_f) -
            work / jobs_f, not r["stopped"] and not missing, unit_s=per, units=len(units_f), start_up_s=start,
            lower_bound=missing)]


# -- the table ---------------------------------------------------------------------------------------------------
def hms(s: float) -> str:
    return f"{s / 3600:.2f} h" if s >= 3600 else f"{s / 60:.1f} min" if s >= 60 else f"{s:.1f} s"


def markdown(result: dict) -> str:
    lines = ["| stage | measured | rate | full size | processes | fixed | projected | share |", "|" + "---|" * 8]
    for r in result["rows"]:
        ge = ">= " if r["detail"].get("lower_bound") else ""
        lines.append(f"| {r['stage']}{'' if r['complete'] else ' (incomplete)'} | {r['measured']} | "
                     f"{r['rate_s']:.4g} {r['rate_unit']} | {r['count']:,} {r['count_unit']} | {r['processes']} | "
                     f"{hms(r['fixed_s'])} | {ge}{hms(r['projected_s'])} | {100 * r['share']:.1f}% |")
    t, ge = result["total_s"], ">= " if any(r["detail"].get("lower_bound") for r in result["rows"]) else ""
    missing = unmeasured(result)
    lines.append(f"| **{'the stages measured' if missing else 'make paper'}** | | | | | | **{ge}{hms(t)}** | 100% |")
    ratio = f"{t / (TARGET_H * 3600):.2f}x the target"
    if not missing:
        verdict = f"{'met' if t <= TARGET_H * 3600 else 'not met'} ({ratio})"
    elif t > TARGET_H * 3600:
        verdict = f"not met: the stages measured alone take {ratio}"
    else:  # a part of make paper under the target says nothing of the whole
        verdict = f"not decided: {', '.join(missing)} not measured (the stages measured {ratio})"
    return "\n".join(lines) + f"\n\nTarget <= {TARGET_H:g} h on one GPU: {verdict}.\n"


def unmeasured(result: dict) -> list[str]:
    """The stages of make paper with no row in ``result`` (stage mppi's rows: demonstrations, merge)."""
    have = {r["stage"] for r in result["rows"]}
    return [s for s in STAGES if ("demonstrations" if s == "mppi" else s) not in have]


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", required=True, help="paper_cost.json / .md, logs/ and the scratch outputs/")
    ap.add_argument("--scale", default="paper")
    ap.add_argument("--device", default="cuda", choices=["cuda", "cpu"])
    ap.add_argument("--stages", nargs="+", default=list(STAGES), choices=STAGES)
    ap.add_argument("--minutes", type=float, help="stop a stage's command after this many minutes")
    ap.add_argument("--episodes", type=int, default=2, help="demonstrations a cell (data.episodes)")
    ap.add_argument("--epochs", type=int, nargs=2, metavar=("K1", "K2"), help="the two training lengths")
    ap.add_argument("--train-episodes", type=int, nargs="+", metavar="N",
                    help="the trainings' dataset, one or two sizes (default: a quarter of the full one); two "
                    "separate an epoch's fixed part from its part per episode")
    ap.add_argument("--eval-episodes", type=int, default=1, help="evaluation episodes a cell (eval.episodes_per_cell)")
    ap.add_argument("--jobs", type=int, help="processes of the demonstrations and the evaluation (default: config)")
    ap.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE", help="Hydra overrides for every command")
    args = ap.parse_args(argv)
    sizes = args.train_episodes or []
    if len(sizes) > 2 or len(set(sizes)) < len(sizes) or any(n < 2 for n in sizes):
        ap.error(f"--train-episodes {' '.join(map(str, sizes))}: one or two different sizes, each at least 2 episodes")
    bench = Bench(args)
    path = bench.out / "paper_cost.json"
    rows = {r["stage"]: r for r in (json.loads(path.read_text())["rows"] if path.exists() else [])}
    for stage in (s for s in STAGES if s in args.stages):
        print(f"{stage}:", flush=True)
        rows.update((r["stage"], r) for r in (bench.train(stage) if stage in ("pretrain", "bc") else
                                              getattr(bench, stage)()))
    result = {"scale": args.scale, "device": args.device, "overrides": bench.base,
              "rows": [rows[s] for s in ROWS if s in rows]}
    result["total_s"] = sum(r["projected_s"] for r in result["rows"])
    for r in result["rows"]:
        r["share"] = r["projected_s"] / result["total_s"] if result["total_s"] > 0 else 0.0
    path.write_text(json.dumps(result, indent=2, default=str))
    path.with_suffix(".md").write_text(markdown(result))
    print(markdown(result))
    for r in result["rows"]:
        if r["stage"] in ("demonstrations", "eval") and r["rate_s"] > 0:
            print(f"{r['stage']}: {3600 * r['processes'] / r['rate_s']:,.0f} episodes an hour in {r['processes']} "
                  "process(es)")
    print(f"wrote {path} and {path.with_suffix('.md')}")
    return result


if __name__ == "__main__":
    main()
