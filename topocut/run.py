"""The one entry point: ``python -m topocut.run stage=<...> task=<...> object=<...> scale=<...>``.

Composes the config (typed schemas reject unknown keys and list valid group choices),
runs cross-field checks, seeds every backend, picks the device, opens the logger and
the artifact store, calls the stage, and always writes ``status.json`` and finishes
the logger — whatever the stage did.
"""
from __future__ import annotations

import errno
import json
import logging
import os
import sys
import tempfile
import time
import traceback
from pathlib import Path

import hydra
from hydra.core.hydra_config import HydraConfig
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf

from topocut.config import (
    ConfigError,
    check_device,
    check_known_keys,
    composition_error,
    register_configs,
    validate,
)
from topocut.data.store import (
    ArtifactBusy,
    ArtifactStore,
    CorruptArtifact,
    InvalidName,
    MissingArtifact,
    write_json_atomic,
)
from topocut.utils.context import RunContext
from topocut.utils.errors import NothingUsable
from topocut.utils.logger import RunLogger
from topocut.utils.progress import print_summary
from topocut.utils.runtime import DeviceUnavailable, resolve_device, seed_everything_all

log = logging.getLogger("topocut")
register_configs()
REPO_ROOT = Path(__file__).resolve().parent.parent
CONF_DIR = REPO_ROOT / "conf"
OUTPUTS_ENV = "TOPOCUT_OUTPUTS"
_OUTPUTS_NOTE = ""  # how a relative outputs root was resolved (absolute_outputs_root), said once by main()
# A user's mistake, not a bug: a single run prints the message (which names the key or file and what is valid)
# without a traceback and exits 2; status.json keeps the traceback.  Multirun jobs re-raise for Hydra's launcher.
USER_ERRORS = (ConfigError, MissingArtifact, CorruptArtifact, ArtifactBusy, DeviceUnavailable, InvalidName,
               NothingUsable)
# The machine's refusals the user fixes (a full disk or quota, a read-only or forbidden outputs_root), not bugs
USER_ERRNOS = (errno.ENOSPC, errno.EDQUOT, errno.EROFS, errno.EACCES, errno.EPERM)


class Terminated(KeyboardInterrupt):
    """SIGTERM (Slurm's cancel, `docker stop`, `kill`), handled as Ctrl-C is: status.json says failed, committed
    work is kept, one line is printed."""


# A library's bare `except: pass` can swallow the one Terminated a SIGTERM raises: Taichi's AST helpers
# (`is_taichi_class`, `is_matrix_class`) run thousands of times while kernels compile, and a run signalled then
# went on to finish and exit 0.  So once signalled, a timer raises it again every REDELIVER_S until it reaches
# run_stage or main (stop_redelivery).
REDELIVER_S = 1.0
_SIGNALLED = {"signum": 0}


def _raise_terminated(signum, frame) -> None:
    import signal

    if signum == signal.SIGTERM and not _SIGNALLED["signum"]:
        _SIGNALLED["signum"] = signum
        signal.signal(signal.SIGALRM, _raise_terminated)
        signal.setitimer(signal.ITIMER_REAL, REDELIVER_S, REDELIVER_S)
    if _SIGNALLED["signum"]:
        raise Terminated(f"signal {_SIGNALLED['signum']}")


def stop_redelivery() -> None:
    """The stage is ending (any exception reached run_stage or main): no more Terminated from the timer."""
    if _SIGNALLED["signum"]:
        import signal

        signal.setitimer(signal.ITIMER_REAL, 0)
        _SIGNALLED["signum"] = 0


def is_user_error(e: BaseException) -> bool:
    return isinstance(e, USER_ERRORS) or (isinstance(e, OSError) and e.errno in USER_ERRNOS)


def run_stage(cfg: DictConfig, run_dir: Path, overrides: list[str] | None = None) -> dict:
    """Run ``cfg.stage`` with status and logging around it; returns the stage's summary."""
    run_dir.mkdir(parents=True, exist_ok=True)
    started = time.time()
    status: dict = {"stage": cfg.stage.name, "status": "running", "overrides": overrides or [], "pid": os.getpid(),
                    "started": started}
    logger = None
    try:  # a run killed with SIGKILL leaves this "running" record behind: it says which run it was
        write_json_atomic(run_dir / "status.json", status)
    except OSError:  # (a full disk: the final write below warns about it once)
        pass
    try:
        validate(cfg)
        check_overrides(cfg, overrides or [])
        device = resolve_device(cfg.device)
        check_device(cfg, device)
        seed_everything_all(cfg.seed)
        store = ArtifactStore(Path(cfg.outputs_root))
        resolved = OmegaConf.to_container(cfg, resolve=True)
        logger = RunLogger(cfg.logger.kind, run_dir, name=f"{cfg.stage.name}-{cfg.task.name}",
                           config=resolved, project=cfg.logger.project, mode=cfg.logger.mode,
                           entity=cfg.logger.entity)
        ctx = RunContext(store=store, run_dir=run_dir, device=device, seed=cfg.seed, logger=logger,
                         progress=cfg.progress, config=resolved, overrides=overrides or [])
        stage = instantiate(cfg.stage.run, _convert_="object")
        summary = stage(ctx) or {}
        status.update(status="ok", summary=summary)
        if cfg.stage.name != "all":
            print_summary(f"{cfg.stage.name}: done in {time.time() - started:.1f}s", summary)
        return summary
    except BaseException as e:
        stop_redelivery()
        status.update(status="failed", error=f"{type(e).__name__}: {e}", traceback=traceback.format_exc())
        if isinstance(e, NothingUsable):
            status["failures"] = e.failures
        raise
    finally:
        status["seconds"] = round(time.time() - started, 2)
        try:
            write_json_atomic(run_dir / "status.json", status)
        except OSError as e:  # a full disk: report it, but never in place of the stage's own error
            log.warning("could not write %s (%s)", run_dir / "status.json", e)
        if logger is not None:
            logger.finish(exit_code=0 if status["status"] == "ok" else 1)


def check_overrides(cfg: DictConfig, overrides: list[str]) -> None:
    """Command-line choices a stage would silently ignore."""
    task = next((o.split("=", 1)[1] for o in overrides if o.startswith("task=")), None)
    if cfg.stage.name == "eval" and task is not None and task not in cfg.eval.tasks:
        from topocut.eval.config import TASKS

        fix = (f"set eval.tasks=[{task}]" if task in TASKS else
               f"task={task} has no evaluation protocol; eval.tasks takes {', '.join(TASKS)}")
        raise ConfigError(f"task={task}: stage=eval evaluates eval.tasks={list(cfg.eval.tasks)} and ignores `task`; "
                          f"{fix}")


def absolute_outputs_root(argv: list[str], environ) -> tuple[list[str], str]:
    """A relative outputs root (``outputs_root=<dir>``, else ``$TOPOCUT_OUTPUTS``, else the default ``outputs``) made
    absolute against the repository root, not the current directory: a stage run from another directory (docs/,
    a notebook's) otherwise wrote a second outputs tree there, and the next stage, run from the repository, found
    none of it (``latest`` is per tree).  The Makefile's ``clean-outputs`` and ``table2`` read the same path, as
    they run in the repository root.  Returns (argv with an absolute ``outputs_root=``, the note to print; "" when
    nothing was relative); ``environ`` gets an absolute TOPOCUT_OUTPUTS, which the config and every process this
    one starts (joblib workers, Lightning's DDP ranks) read."""
    argv = list(argv)
    for i in reversed(range(len(argv))):
        prefix, sep, value = argv[i].partition("outputs_root=")
        if sep and prefix in ("", "+", "++"):
            path = Path(os.path.expanduser(value))
            if "${" in value or path.is_absolute():
                return argv, ""
            argv[i] = f"{prefix}outputs_root={os.path.abspath(REPO_ROOT / path)}"
            return argv, f"outputs_root={value} is relative: taken from the repository root {REPO_ROOT}"
    value = environ.get(OUTPUTS_ENV) or ""
    path = Path(os.path.expanduser(value or "outputs"))
    if path.is_absolute():
        return argv, ""
    environ[OUTPUTS_ENV] = os.path.abspath(REPO_ROOT / path)
    return argv, (f"{OUTPUTS_ENV}={value} is relative: taken from the repository root {REPO_ROOT}" if value else "")


@hydra.main(version_base="1.3", config_path="../conf", config_name="config")
def main(cfg: DictConfig) -> None:
    from hydra.types import RunMode

    hc = HydraConfig.get()
    overrides = list(hc.overrides.task)
    single = hc.mode == RunMode.RUN
    if not single:  # a multirun job in a launcher's worker process: its own GPU of the node (topocut.utils.devices)
        from topocut.utils.devices import bind_worker

        bind_worker()
    log.info("outputs: %s%s", cfg.outputs_root, f" ({_OUTPUTS_NOTE})" if _OUTPUTS_NOTE else "")
    if single:  # SIGTERM as Ctrl-C: status.json records it, one line, committed work kept
        import signal

        signal.signal(signal.SIGTERM, _raise_terminated)
    try:
        summary = run_stage(cfg, Path(hc.runtime.output_dir), overrides)
    except Exception as e:
        if not single or not is_user_error(e):
            raise
        log.error("%s: %s", type(e).__name__, e)
        sys.exit(2)
    except KeyboardInterrupt as e:
        stop_redelivery()
        if not single:
            raise
        log.error("%s: committed work is kept; re-run the same command to resume (%s)",
                  "terminated (SIGTERM)" if isinstance(e, Terminated) else "interrupted",
                  Path(hc.runtime.output_dir) / "status.json")
        sys.exit(143 if isinstance(e, Terminated) else 130)
    finally:  # a stage that finished before a swallowed Terminated came round again has done its work
        stop_redelivery()
    log.info("summary: %s", json.dumps(summary, default=str))


# Dicts the schema leaves open: OmegaConf refuses a new key in them under Hydra's struct flag ("not in struct";
# only `++key=` adds one), so `eval.task_overrides={slice:{thickness:0.05}}` as documented failed wherever the
# scale set no such key.  Their overrides are given Hydra's add-or-override prefix.
OPEN_DICTS = ("eval.checkpoints", "eval.task_overrides", "eval.policy_kwargs", "data.task_overrides")


def open_dict_overrides(argv: list[str]) -> list[str]:
    """``argv`` with ``++`` before every plain override of (a key inside) an open dict."""
    def is_open(a: str) -> bool:
        key = a.split("=", 1)[0]
        return "=" in a and any(key == d or key.startswith(d + ".") for d in OPEN_DICTS)

    return [f"++{a}" if is_open(a) else a for a in argv]


PRINT_FLAGS = {"--cfg": 1, "-c": 1, "--package": 1, "-p": 1, "--resolve": 0}  # Hydra's printing flags: values taken


def _overrides_to_check(argv: list[str]) -> tuple[list[str] | None, bool]:
    """(the overrides preflight composes, whether Hydra only prints the config): a run's argv, or one with Hydra's
    printing flags (``--cfg job``: the same config, shown), whose overrides are checked alike.  None for Hydra's
    other modes (``-m``: a sweep's lists are not one config; ``--help``, ...), left to Hydra."""
    out, printing, i = [], False, 0
    while i < len(argv):
        flag = argv[i].split("=", 1)[0]
        if flag in PRINT_FLAGS:
            printing = True
            i += 1 + (PRINT_FLAGS[flag] if "=" not in argv[i] else 0)
            continue
        if argv[i].startswith("-"):
            return None, False
        out.append(argv[i])
        i += 1
    return out, printing


def preflight(argv: list[str]) -> None:
    """Compose the config before Hydra does, to refuse a typo'd option or key and an unwritable outputs_root as
    user errors: Hydra reports them (and fails to create the run directory) with status 1 and a traceback.
    ``--cfg job`` is checked alike (a key the task lacks is the same one-line error), without touching
    outputs_root; Hydra's other modes (``-m``, ``--help``, ...) are left to Hydra."""
    overrides, printing = _overrides_to_check(argv)
    if overrides is None:
        return
    from hydra import compose, initialize_config_dir
    from hydra.errors import HydraException
    from omegaconf.errors import OmegaConfBaseException

    try:
        with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
            cfg = compose(config_name="config", overrides=overrides)
    except (HydraException, OmegaConfBaseException) as e:
        raise composition_error(e) from e
    check_known_keys(cfg)  # +task.width=... for a task without one: Hydra adds it silently, validate would refuse it
    if printing:  # nothing runs: the outputs root is not written
        return
    root = Path(cfg.outputs_root)
    try:
        root.mkdir(parents=True, exist_ok=True)
        tempfile.TemporaryFile(dir=root).close()
    except OSError as e:
        raise ConfigError(f"outputs_root={cfg.outputs_root}: cannot write there ({e.strerror or e}); "
                          "give a writable directory (outputs_root=<dir> or TOPOCUT_OUTPUTS)") from e


if __name__ == "__main__":
    os.environ.setdefault("HYDRA_FULL_ERROR", "0")
    sys.argv[1:], _OUTPUTS_NOTE = absolute_outputs_root(open_dict_overrides(sys.argv[1:]), os.environ)
    try:
        preflight(sys.argv[1:])
    except ConfigError as e:
        print(f"ConfigError: {e}", file=sys.stderr)
        sys.exit(2)
    if "-m" in sys.argv[1:] or "--multirun" in sys.argv[1:]:  # the launcher's workers spread over the node's GPUs
        from topocut.utils.devices import share_gpus

        share_gpus()
    main()
