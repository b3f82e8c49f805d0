#!/usr/bin/env bash
# Slow CI step: bring up a real single-node SLURM cluster (munge, MariaDB + slurmdbd, slurmctld,
# slurmd; installed with apt-get if missing, started without systemd), run the default workflow
# through profiles/slurm, check with sacct that every job ran under SLURM and that the summaries
# equal a local run's, and tear the cluster down again. Needs root.
#
#   bash tests/slurm/run_slurm_test.sh            # from anywhere; VENV=path/to/venv optional
set -euo pipefail
ROOT=$(cd "$(dirname "$0")/../.." && pwd)
cd "$ROOT"
VENV=${VENV:-$ROOT/.venv}
t0=$(date +%s)
if ! "$VENV/bin/python" -c "import snakemake_executor_plugin_slurm" 2>/dev/null; then
  "$VENV/bin/python" -m pip install --quiet -e "$ROOT[slurm]"   # the pinned plugin from pyproject
fi
if scontrol ping >/dev/null 2>&1; then
  echo "[slurm-test] SLURM already running: using it, not tearing it down"
else
  trap 'bash "$ROOT/tests/slurm/slurm-down.sh"' EXIT
  bash "$ROOT/tests/slurm/slurm-up.sh"
fi
echo "[slurm-test] cluster ready after $(( $(date +%s) - t0 )) s"
"$VENV/bin/python" -m pytest -m slow -p no:cacheprovider -s -q \
  "$ROOT/tests/test_workflow.py::test_slurm_profile_runs_under_slurm_and_matches_local"
echo "[slurm-test] passed in $(( $(date +%s) - t0 )) s"
