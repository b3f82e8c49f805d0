"""Environment of the jobs the NEMO workflow starts (imported by workflow/rules/common.smk).

Every rule runs ``python -m nemo``. So that ``.venv/bin/snakemake`` works without activating
the virtual environment, the directory of the interpreter running Snakemake goes first on
PATH (a conda environment activated per job by ``--sdm conda`` is put in front of it again by
Snakemake, so it still wins), and the checkout holding the ``nemo`` package goes on PYTHONPATH
(conda environments do not install NEMO itself: workflow/envs/nemo.yaml).
"""

from __future__ import annotations

import os
import sys


def prepend(variable: str, path: str, environ=os.environ) -> None:
    """Put ``path`` first in the search path ``variable`` (unless it already is first)."""
    value = environ.get(variable, "")
    if not value:
        environ[variable] = path
    elif value.split(os.pathsep)[0] != path:
        environ[variable] = path + os.pathsep + value


def prepare(checkout: str, environ=os.environ) -> None:
    """Set PATH and PYTHONPATH for the jobs (inherited by every job Snakemake starts)."""
    prepend("PATH", os.path.dirname(sys.executable), environ)
    prepend("PYTHONPATH", checkout, environ)
