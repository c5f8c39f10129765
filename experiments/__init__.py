"""The paper's experiments: figure-, table- and sweep-making built on the library (topocut/), which they import and
which never imports them.

A module with a ``main`` is a command line, run from the repository root as ``python experiments/<name>.py``; the
others hold experiment bodies those command lines (and tests, as ``experiments.<name>``) import, or what
several command lines share (reference_cli.py: the reference checks' ``--json``).
"""
