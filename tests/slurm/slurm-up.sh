#!/usr/bin/env bash
# Bring up a real single-node SLURM cluster on this machine, without systemd (Debian 12, root):
# munge, MariaDB + slurmdbd (accounting, so `sacct` works), slurmctld, slurmd.
# Installs the Debian packages itself when they are missing (apt-get update first).
# Idempotent: daemons already running are left alone. Tear down with slurm-down.sh.
#
#   sudo tests/slurm/slurm-up.sh            # env: SLURM_ACCOUNT (default nemo), DBPASS
set -euo pipefail
SLURM_ACCOUNT="${SLURM_ACCOUNT:-nemo}"
DBPASS="${DBPASS:-nemo-slurm-ci}"
STATE=/run/nemo-slurm            # our PID files live here (slurm-down.sh reads them)
export DEBIAN_FRONTEND=noninteractive
t0=$(date +%s)
log() { echo "[slurm-up +$(( $(date +%s) - t0 ))s] $*"; }
wait_for() {  # wait_for SECONDS CMD...: retry CMD every 0.25 s
  local n=$(( $1 * 4 )); shift
  for _ in $(seq 1 "$n"); do "$@" >/dev/null 2>&1 && return 0; sleep 0.25; done
  echo "slurm-up: timeout waiting for: $*" >&2; return 1
}
[ "$(id -u)" = 0 ] || { echo "slurm-up: must run as root (installs packages, starts daemons)" >&2; exit 2; }

pkgs=(munge slurmctld slurmd slurm-client slurmdbd mariadb-server)
missing=()
for p in "${pkgs[@]}"; do dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "ok installed" || missing+=("$p"); done
if [ "${#missing[@]}" -gt 0 ]; then
  log "apt-get install ${missing[*]}"
  apt-get update -q >/dev/null
  # package scripts try to start services; without systemd that is refused, which is fine
  apt-get install -y -q --no-install-recommends -o DPkg::Lock::Timeout=600 "${missing[@]}" >/dev/null
fi
install -d -m 0755 "$STATE"

log "munge"
if [ ! -s /etc/munge/munge.key ]; then
  mungekey --create --force 2>/dev/null || dd if=/dev/urandom of=/etc/munge/munge.key bs=1 count=1024 status=none
fi
chown munge:munge /etc/munge/munge.key; chmod 400 /etc/munge/munge.key
install -d -o munge -g munge -m 0755 /run/munge      # systemd's tmpfiles would create it
if ! munge -n 2>/dev/null | unmunge >/dev/null 2>&1; then
  su -s /bin/sh munge -c "/usr/sbin/munged --pid-file=/run/munge/munged.pid"
fi
wait_for 20 sh -c 'munge -n | unmunge'
ln -sf /run/munge/munged.pid "$STATE/munged.pid"

log "slurm.conf"
install -d -o slurm -g slurm /var/lib/slurm/slurmctld /var/lib/slurm/slurmd /var/log/slurm
NCPU=$(nproc)
MEM_MB=$(( $(awk '/MemTotal/ {print int($2 / 1024)}' /proc/meminfo) * 8 / 10 ))
cat > /etc/slurm/slurm.conf <<CONF
# written by NEMO tests/slurm/slurm-up.sh: one node (this machine), accounting via slurmdbd
ClusterName=nemo
SlurmctldHost=localhost
AuthType=auth/munge
CredType=cred/munge
SlurmUser=slurm
SlurmdUser=root
SlurmctldPort=6817
SlurmdPort=6818
StateSaveLocation=/var/lib/slurm/slurmctld
SlurmdSpoolDir=/var/lib/slurm/slurmd
SlurmctldPidFile=$STATE/slurmctld.pid
SlurmdPidFile=$STATE/slurmd.pid
SlurmctldLogFile=/var/log/slurm/slurmctld.log
SlurmdLogFile=/var/log/slurm/slurmd.log
ReturnToService=2
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
MpiDefault=none
SchedulerType=sched/backfill
SelectType=select/cons_tres
SelectTypeParameters=CR_Core
JobCompType=jobcomp/none
AccountingStorageType=accounting_storage/slurmdbd
AccountingStorageHost=localhost
AccountingStoragePort=6819
AccountingStoreFlags=job_comment
JobAcctGatherType=jobacct_gather/linux
JobAcctGatherFrequency=30
SlurmctldTimeout=30
SlurmdTimeout=30
InactiveLimit=0
MinJobAge=300
KillWait=5
Waittime=0
NodeName=localhost NodeAddr=127.0.0.1 CPUs=$NCPU RealMemory=$MEM_MB State=UNKNOWN
PartitionName=debug Nodes=localhost Default=YES MaxTime=INFINITE State=UP
CONF

log "mariadb"
install -d -o mysql -g mysql /run/mysqld
[ -d /var/lib/mysql/mysql ] || mariadb-install-db --user=mysql --datadir=/var/lib/mysql >/dev/null
if ! mariadb -e 'select 1' >/dev/null 2>&1; then
  nohup /usr/sbin/mariadbd --user=mysql --pid-file=/run/mysqld/mysqld.pid \
    --socket=/run/mysqld/mysqld.sock --bind-address=127.0.0.1 >/var/log/slurm/mariadb.log 2>&1 &
fi
wait_for 60 mariadb -e 'select 1'
ln -sf /run/mysqld/mysqld.pid "$STATE/mysqld.pid"
mariadb -e "CREATE DATABASE IF NOT EXISTS slurm_acct_db;
  CREATE USER IF NOT EXISTS 'slurm'@'localhost' IDENTIFIED BY '${DBPASS}';
  ALTER USER 'slurm'@'localhost' IDENTIFIED BY '${DBPASS}';
  GRANT ALL ON slurm_acct_db.* TO 'slurm'@'localhost'; FLUSH PRIVILEGES;"

log "slurmdbd"
cat > /etc/slurm/slurmdbd.conf <<CONF
AuthType=auth/munge
DbdHost=localhost
DbdPort=6819
SlurmUser=slurm
LogFile=/var/log/slurm/slurmdbd.log
PidFile=$STATE/slurmdbd.pid
StorageType=accounting_storage/mysql
StorageHost=localhost
StoragePort=3306
StorageLoc=slurm_acct_db
StorageUser=slurm
StoragePass=${DBPASS}
CONF
chown slurm:slurm /etc/slurm/slurmdbd.conf; chmod 600 /etc/slurm/slurmdbd.conf  # slurmdbd insists
pgrep -F "$STATE/slurmdbd.pid" >/dev/null 2>&1 || /usr/sbin/slurmdbd
wait_for 60 sacctmgr -n list cluster

log "slurmctld + slurmd"
pgrep -F "$STATE/slurmctld.pid" >/dev/null 2>&1 || /usr/sbin/slurmctld
wait_for 60 scontrol ping
pgrep -F "$STATE/slurmd.pid" >/dev/null 2>&1 || /usr/sbin/slurmd -N localhost  # node name != hostname
scontrol update nodename=localhost state=resume >/dev/null 2>&1 || true
wait_for 60 sh -c 'sinfo -h -N -o %T | grep -Eqx "idle|mixed|allocated"'
wait_for 30 sh -c 'sacctmgr -n -P list cluster format=cluster | grep -qx nemo'  # slurmctld registers
sacctmgr -i add account "$SLURM_ACCOUNT" Description=nemo-ci Organization=nemo >/dev/null 2>&1 || true
sacctmgr -i add user "$(id -un)" Account="$SLURM_ACCOUNT" DefaultAccount="$SLURM_ACCOUNT" >/dev/null 2>&1 || true

log "smoke test"
jid=$(sbatch --parsable -o /dev/null --wrap 'hostname')
wait_for 60 sh -c "sacct -n -X -j $jid -o State | grep -q COMPLETED"
sinfo
log "SLURM up: cluster nemo, partition debug, account $SLURM_ACCOUNT"
