"""One Table 1 from several evaluation artifacts of the same protocol (docs/evaluation.md, "Combining runs").

A paper-scale evaluation is ~6,000 episodes; on a lent GPU it is run in pieces (the scripted policies and the
policies trained so far on one machine, the rest later), each piece an ``eval/<name>/vNNN`` artifact.  The pieces
form one table only if they ran the same episodes: the same scenes, simulator, reward, planner and observation.
``combine`` checks that from the manifests (every config key but the ones that say *which* policies ran and how
the table is reported), refuses a run present in two pieces, copies the episodes into one directory and writes the
report there, with the per-seed rows of the learned policies beside the pooled ones (``results_seeds.md``).

A piece need not hold its table's reference: the evaluation stage refuses ``eval.reference`` outside
``eval.policies``, so a piece of learned policies only is run with one of them as its reference; pieces that differ
in the reference are combined with ``reference=`` (checked against the combined runs).
"""
from __future__ import annotations

import json
import shutil
from pathlib import Path

from topocut.data.store import write_json_atomic
from topocut.eval.report import (
    DISPLAY,
    RUNS_FILE,
    load_episodes,
    rows_to_table,
    split_run,
    summarize,
    table1_markdown,
    write_report,
)
from topocut.utils.progress import flatten

# Keys that say which policies ran and how the run was spread, not what an episode is
NOT_PROTOCOL = ("eval.policies", "eval.checkpoints", "eval.train_seeds", "eval.gifs", "eval.name", "eval.jobs",
                "eval.policy_kwargs")
# Keys that say how the table is reported (which run normalises R̂, per task or per split, the Δ columns' baseline):
# they change no episode, so pieces may differ in them; the combined table takes them from the reference's piece
REPORTING = ("eval.reference", "eval.normalize_by", "eval.compare_to")
SOURCES_FILE = "sources.json"


def protocol(manifest: dict) -> dict:
    """The manifest's config, flattened, without the keys of NOT_PROTOCOL and REPORTING (and anything under them)."""
    flat = flatten(manifest.get("config", {}), sep=".")
    skip = NOT_PROTOCOL + REPORTING
    return {k: v for k, v in flat.items() if not any(k == n or k.startswith(n + ".") for n in skip)}


def _read(source: Path) -> tuple[dict, dict]:
    mpath = source / "manifest.json"
    if not mpath.is_file():
        raise ValueError(f"{source}: no manifest.json; pass committed evaluation artifacts (eval/<name>/vNNN)")
    if not any(source.glob("episodes/*/*.json")):
        raise ValueError(f"{source}: no episodes/<run>/*.json")
    runs = json.loads((source / RUNS_FILE).read_text()) if (source / RUNS_FILE).exists() else {}
    return json.loads(mpath.read_text()), runs


def _reporting(manifest: dict) -> dict:
    flat = flatten(manifest.get("config", {}), sep=".")
    return {"reference": flat.get("eval.reference", "oracle"), "normalize_by": flat.get("eval.normalize_by", "task"),
            "compare_to": flat.get("eval.compare_to") or None}


def _pick(reports: list[dict], key: str, given):
    """``given``, else the value of ``key`` all pieces share (ValueError naming them when they differ)."""
    if given is not None:
        return given
    values = {r[key] for r in reports}
    if len(values) > 1:
        raise ValueError(f"the pieces differ in eval.{key} ({', '.join(sorted(map(str, values)))}); "
                         f"pass {key}= one of them (experiments/table1.py --{key.replace('_', '-')})")
    return values.pop()


def combine(sources: list, out_dir, console: bool = False, reference: str | None = None,
            normalize_by: str | None = None, compare_to: str | None = None) -> dict:
    """Episodes of ``sources`` (evaluation artifact directories) into ``out_dir`` and its report.

    ``reference`` / ``normalize_by`` / ``compare_to``: how the table is reported; by default the pieces' own
    (which must then agree; a piece of learned policies only is run with one of them as its reference).
    Raises ValueError naming the first protocol key on which two sources differ, a run both hold, or a reference
    no piece ran.
    """
    sources = [Path(s) for s in sources]
    if len(sources) < 1:
        raise ValueError("no evaluation artifacts given")
    out_dir = Path(out_dir)
    first, runs, origin, reports = None, {}, {}, []
    for src in sources:
        manifest, src_runs = _read(src)
        reports.append(_reporting(manifest))
        proto = protocol(manifest)
        if first is None:
            first = (src, proto)
        else:
            ref_src, ref = first
            for key in sorted(set(ref) | set(proto)):
                if ref.get(key) != proto.get(key):
                    raise ValueError(f"{src}: protocol key {key!r} is {proto.get(key)!r}, but {ref!r} in {ref_src}; "
                                     "only runs of the same protocol form one table")
        for run_dir in sorted(p for p in (src / "episodes").iterdir() if p.is_dir()):
            if run_dir.name in origin:
                raise ValueError(f"run {run_dir.name!r} is in both {origin[run_dir.name]} and {src}; pass one of them")
            origin[run_dir.name] = src
            runs[run_dir.name] = src_runs.get(run_dir.name, {})
    policies = {m.get("policy") or split_run(r)[0] for r, m in runs.items()}  # runs: every run in origin
    reference, normalize_by = _pick(reports, "reference", reference), _pick(reports, "normalize_by", normalize_by)
    for key, value in (("reference", reference), ("compare_to", compare_to)):
        if value is not None and value not in policies:
            raise ValueError(f"{key} {value!r} is not among the combined policies ({', '.join(sorted(policies))})")
    if compare_to is None and len({r["compare_to"] for r in reports}) == 1:
        compare_to = reports[0]["compare_to"]  # the pieces' own, when they agree and it ran (else: the reference)
        compare_to = compare_to if compare_to in policies else None
    tmp = out_dir.with_name(out_dir.name + ".partial")
    shutil.rmtree(tmp, ignore_errors=True)
    for run, src in origin.items():
        shutil.copytree(src / "episodes" / run, tmp / "episodes" / run)
    write_json_atomic(tmp / RUNS_FILE, runs)
    write_json_atomic(tmp / SOURCES_FILE, {str(s): sorted(r for r, o in origin.items() if o == s) for s in sources})
    report = write_report(tmp, reference=reference, normalize_by=normalize_by, console=console, compare_to=compare_to)
    write_seed_table(tmp, reference, normalize_by)
    shutil.rmtree(out_dir, ignore_errors=True)
    tmp.rename(out_dir)  # the finished directory appears at once; an interrupted combine leaves only .partial
    files = {k: out_dir / report[k].name for k in ("csv", "objects_csv", "md", "png")}  # report wrote them in tmp
    return {**files, "seeds_md": out_dir / "results_seeds.md", "rows": report["rows"], "runs": sorted(origin)}


def write_seed_table(out_dir, reference: str = "oracle", normalize_by: str = "task") -> Path:
    """results_seeds.md: Table 1 with one row per training seed of each learned policy (the pooled table
    averages them), every seed over the same episodes, normalised by the same reference."""
    episodes = load_episodes(out_dir)
    for e in episodes:
        if e["train_seed"] is not None:
            e["policy"] = f"{DISPLAY.get(e['policy'], e['policy'])}, seed {e['train_seed']}"  # no "@s": not pooled
            e["train_seed"] = None
    rows = summarize(episodes, reference, normalize_by, levels=("cell",))
    text = table1_markdown(rows_to_table(rows, reference), reference, title="Per training seed",
                           note="Each learned policy's checkpoints one row a seed; mean [95% bootstrap interval].")
    path = Path(out_dir) / "results_seeds.md"
    path.write_text(text)
    return path
