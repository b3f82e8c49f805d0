#!/usr/bin/env bash
# Stop the daemons started by slurm-up.sh, by PID file, in reverse order of start.
STATE=/run/nemo-slurm
for name in slurmd slurmctld slurmdbd mysqld munged; do
  pf="$STATE/$name.pid"
  [ -e "$pf" ] || continue
  pid=$(cat "$pf" 2>/dev/null || true)
  if [ -n "$pid" ] && kill -0 "$pid" 2>/dev/null; then
    kill "$pid"
    for _ in $(seq 1 80); do kill -0 "$pid" 2>/dev/null || break; sleep 0.25; done
    if kill -0 "$pid" 2>/dev/null; then echo "slurm-down: force-killing $name ($pid)"; kill -9 "$pid"; fi
    echo "slurm-down: stopped $name ($pid)"
  fi
  rm -f "$pf" "$(readlink -f "$pf" 2>/dev/null)"   # stale PID files confuse the next start
done
