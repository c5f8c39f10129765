"""Rich progress bars on a terminal; one log line per step when output goes to a file or a CI log."""
from __future__ import annotations

import logging
import time
from contextlib import contextmanager

from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn


@contextmanager
def progress_bar(description: str, total: int, enabled: bool = True):
    """Yield an ``advance(n=1, **fields)`` callable backed by a rich progress bar."""
    if not enabled:
        yield lambda n=1, **kw: None
        return
    from rich.console import Console

    if not Console().is_terminal:  # a bar redrawn in place would show nothing until the end (redirected output)
        log, done, t0 = logging.getLogger("topocut.progress"), [0], time.perf_counter()

        def advance_log(n: int = 1, info: str = "") -> None:
            done[0] += n
            log.info("%s %d/%d (%.0f s)%s", description, done[0], total, time.perf_counter() - t0,
                     f": {info}" if info else "")

        yield advance_log
        return
    columns = (TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(),
               TimeElapsedColumn(), TimeRemainingColumn(), TextColumn("{task.fields[info]}"))
    with Progress(*columns, transient=False) as prog:
        task = prog.add_task(description, total=total, info="")

        def advance(n: int = 1, info: str = "") -> None:
            prog.update(task, advance=n, info=info)

        yield advance


def flatten(d: dict, sep: str = "/", prefix: str = "") -> dict:
    """Nested dicts as one level, keys joined with ``sep`` ({"a": {"b": 1}} -> {"a/b": 1}); empty dicts stay
    values."""
    out = {}
    for k, v in d.items():
        if isinstance(v, dict) and v:
            out.update(flatten(v, sep, f"{prefix}{k}{sep}"))
        else:
            out[f"{prefix}{k}"] = v
    return out


LOG_WIDTH = 240  # columns of a table printed to a file or a CI log: rich's default there (80) wraps Table 1


def console():
    """A rich Console as wide as the terminal, or LOG_WIDTH columns when the output is not a terminal (a log file,
    a CI log), where rich would wrap every table at 80 columns."""
    from rich.console import Console

    c = Console()
    return c if c.is_terminal else Console(width=LOG_WIDTH)


def print_summary(title: str, summary: dict) -> None:
    """A two-column rich table of a stage's summary (nested dicts flattened with '/')."""
    from rich.table import Table

    flat = flatten(summary)
    out = console()
    table = Table(title=title, show_header=True, header_style="bold")
    # A key is never cut short (rich shrank it to fit a long path beside it: "val/cluster_err_re…", a name no doc
    # could be searched for); the value folds onto further lines instead.  Only where even the keys leave no room
    # for a value (a very narrow terminal) does the key fold too, still whole.
    longest = max((len(k) for k in flat), default=3)
    if longest + 20 <= out.width:
        table.add_column("key", no_wrap=True, min_width=longest)
    else:
        table.add_column("key", overflow="fold")
    table.add_column("value", overflow="fold")
    for k, v in flat.items():
        table.add_row(k, f"{v:.4g}" if isinstance(v, float) else str(v))
    out.print(table)
