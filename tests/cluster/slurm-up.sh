#!/usr/bin/env bash
# A one-node SLURM cluster on this machine, for the cluster tests (pytest -m slurm) and CI:
# munge, MariaDB + slurmdbd (job accounting), slurmctld and slurmd, from Debian's packages.
# Needs root (as CI has). Installs the packages with apt-get when they are missing.
#
#   bash tests/cluster/slurm-up.sh         # install if needed, configure, start; idempotent
#   bash tests/cluster/slurm-up.sh down    # stop the daemons it started (the setup is kept)
#
# The node is this machine as it is (its CPUs, 90 % of its memory); one partition `debug`, the
# default, no time limit; one account `physmorph` holding the user running the script.
# Everything it writes lives in $PHYSMORPH_SLURM_STATE (default /var/lib/physmorph-slurm), with
# the daemons' logs; where it cannot bring the cluster up it says why in $STATE/unavailable and
# exits 1 (the tests then skip, quoting that file).
set -uo pipefail

STATE=${PHYSMORPH_SLURM_STATE:-/var/lib/physmorph-slurm}
CLUSTER=physmorph
ACCOUNT=physmorph
PARTITION=debug
DB_PASS=physmorph-slurmdbd
mkdir -p "$STATE"

fail() {
    echo "slurm-up: $*" >&2
    echo "$*" > "$STATE/unavailable"
    exit 1
}

pid_alive() { [ -s "$1" ] && kill -0 "$(cat "$1")" 2>/dev/null; }

stop_pidfile() {  # stop the daemon whose pid file is $1 (only that process)
    if pid_alive "$1"; then
        local pid; pid=$(cat "$1")
        kill "$pid" 2>/dev/null
        for _ in $(seq 50); do kill -0 "$pid" 2>/dev/null || break; sleep 0.2; done
        kill -0 "$pid" 2>/dev/null && kill -9 "$pid" 2>/dev/null
    fi
    rm -f "$1"
}

if [ "${1:-up}" = down ]; then
    stop_pidfile "$STATE/slurmd.pid"
    stop_pidfile "$STATE/slurmctld.pid"
    stop_pidfile "$STATE/slurmdbd.pid"
    if pid_alive "$STATE/mysql/mariadb.pid"; then
        mysqladmin --socket="$STATE/mysql/mysqld.sock" shutdown 2>/dev/null || stop_pidfile "$STATE/mysql/mariadb.pid"
    fi
    stop_pidfile "$STATE/munge/munged.pid"
    echo "slurm-up: daemons stopped (start them again with: bash tests/cluster/slurm-up.sh)"
    exit 0
fi

rm -f "$STATE/unavailable"
[ "$(id -u)" = 0 ] || fail "needs root (to install Debian's slurm packages and run slurmd); run as root, as CI does"

# ---------------------------------------------------------------- packages
need=()
for pair in slurmctld:slurmctld slurmd:slurmd slurmdbd:slurmdbd munged:munge mariadbd:mariadb-server sbatch:slurm-client; do
    command -v "${pair%%:*}" >/dev/null 2>&1 || [ -x "/usr/sbin/${pair%%:*}" ] || need+=("${pair##*:}")
done
if [ ${#need[@]} -gt 0 ]; then
    command -v apt-get >/dev/null 2>&1 || fail "SLURM is not installed and there is no apt-get to install it (${need[*]})"
    echo "slurm-up: installing ${need[*]} slurm-wlm"
    export DEBIAN_FRONTEND=noninteractive
    { apt-get update -q && apt-get install -y -q --no-install-recommends "${need[@]}" slurm-wlm; } \
        > "$STATE/apt.log" 2>&1 || fail "apt-get could not install ${need[*]} (see $STATE/apt.log: $(tail -n 2 "$STATE/apt.log" | tr '\n' ' '))"
fi
export PATH="$PATH:/usr/sbin:/sbin"

HOST=$(hostname -s)
CPUS=$(nproc)
MEM_MB=$(awk '/MemTotal/ {print int($2 / 1024 * 0.9)}' /proc/meminfo)
USER_NAME=$(id -un)

# ---------------------------------------------------------------- munge
mkdir -p "$STATE/munge" /run/munge /etc/munge
chown munge:munge "$STATE/munge" /run/munge
if [ ! -s /etc/munge/munge.key ]; then
    mungekey --create --keyfile /etc/munge/munge.key >/dev/null 2>&1 \
        || dd if=/dev/urandom of=/etc/munge/munge.key bs=1 count=128 status=none
fi
chown munge:munge /etc/munge/munge.key && chmod 400 /etc/munge/munge.key
if ! pid_alive "$STATE/munge/munged.pid"; then
    runuser -u munge -- munged --pid-file="$STATE/munge/munged.pid" --log-file="$STATE/munge/munged.log" \
        --seed-file="$STATE/munge/munged.seed" --socket=/run/munge/munge.socket.2 --force \
        || fail "munged did not start (see $STATE/munge/munged.log)"
fi
for _ in $(seq 50); do munge -n </dev/null | unmunge >/dev/null 2>&1 && break; sleep 0.2; done
munge -n </dev/null | unmunge >/dev/null 2>&1 || fail "munge does not answer (see $STATE/munge/munged.log)"

# ---------------------------------------------------------------- MariaDB (slurmdbd's store)
DB=$STATE/mysql
SOCK=$DB/mysqld.sock
if ! pid_alive "$DB/mariadb.pid"; then
    mkdir -p "$DB/data"
    chown -R mysql:mysql "$DB"
    if [ ! -d "$DB/data/mysql" ]; then
        mariadb-install-db --user=mysql --datadir="$DB/data" --auth-root-authentication-method=socket \
            > "$DB/install.log" 2>&1 || fail "mariadb-install-db failed (see $DB/install.log)"
    fi
    (setsid mariadbd --user=mysql --datadir="$DB/data" --socket="$SOCK" --pid-file="$DB/mariadb.pid" \
        --skip-networking=0 --bind-address=127.0.0.1 --port=3307 --log-error="$DB/error.log" \
        --innodb-buffer-pool-size=64M </dev/null >/dev/null 2>&1 &)
fi
for _ in $(seq 100); do mariadb --socket="$SOCK" -e 'select 1' >/dev/null 2>&1 && break; sleep 0.2; done
mariadb --socket="$SOCK" -e "CREATE DATABASE IF NOT EXISTS slurm_acct_db;
    CREATE USER IF NOT EXISTS 'slurm'@'127.0.0.1' IDENTIFIED BY '$DB_PASS';
    GRANT ALL ON slurm_acct_db.* TO 'slurm'@'127.0.0.1'; FLUSH PRIVILEGES;" \
    || fail "MariaDB did not start (see $DB/error.log)"

# ---------------------------------------------------------------- configuration
mkdir -p /etc/slurm "$STATE/ctld" "$STATE/d"
cat > /etc/slurm/slurmdbd.conf <<EOF
# written by tests/cluster/slurm-up.sh
AuthType=auth/munge
DbdHost=localhost
SlurmUser=root
StorageType=accounting_storage/mysql
StorageHost=127.0.0.1
StoragePort=3307
StorageUser=slurm
StoragePass=$DB_PASS
StorageLoc=slurm_acct_db
LogFile=$STATE/slurmdbd.log
PidFile=$STATE/slurmdbd.pid
EOF
chmod 600 /etc/slurm/slurmdbd.conf

cat > /etc/slurm/slurm.conf <<EOF
# written by tests/cluster/slurm-up.sh: one node (this machine), accounting through slurmdbd
ClusterName=$CLUSTER
SlurmctldHost=$HOST
SlurmUser=root
SlurmdUser=root
AuthType=auth/munge
StateSaveLocation=$STATE/ctld
SlurmdSpoolDir=$STATE/d
SlurmctldPidFile=$STATE/slurmctld.pid
SlurmdPidFile=$STATE/slurmd.pid
SlurmctldLogFile=$STATE/slurmctld.log
SlurmdLogFile=$STATE/slurmd.log
# no cgroups in containers: plain process tracking
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
SchedulerType=sched/backfill
SelectType=select/cons_tres
SelectTypeParameters=CR_CPU_Memory
AccountingStorageType=accounting_storage/slurmdbd
AccountingStorageHost=127.0.0.1
AccountingStorageEnforce=associations
AccountingStoreFlags=job_comment
JobAcctGatherType=jobacct_gather/linux
JobAcctGatherFrequency=30
ReturnToService=2
KillWait=10
MinJobAge=300
NodeName=$HOST CPUs=$CPUS RealMemory=$MEM_MB State=UNKNOWN
PartitionName=$PARTITION Nodes=$HOST Default=YES MaxTime=INFINITE State=UP
EOF

# ---------------------------------------------------------------- daemons
if ! pid_alive "$STATE/slurmdbd.pid"; then
    slurmdbd || fail "slurmdbd did not start (see $STATE/slurmdbd.log)"
fi
for _ in $(seq 100); do sacctmgr -n list cluster >/dev/null 2>&1 && break; sleep 0.3; done
sacctmgr -n list cluster >/dev/null 2>&1 || fail "slurmdbd does not answer (see $STATE/slurmdbd.log)"
sacctmgr -n list cluster format=cluster | grep -qw "$CLUSTER" || sacctmgr -i add cluster "$CLUSTER" >/dev/null
sacctmgr -n list account format=account | grep -qw "$ACCOUNT" || sacctmgr -i add account "$ACCOUNT" Cluster="$CLUSTER" Description=physmorph Organization=physmorph >/dev/null
sacctmgr -n -P list assoc user="$USER_NAME" account="$ACCOUNT" format=account | grep -qx "$ACCOUNT" || sacctmgr -i add user "$USER_NAME" Account="$ACCOUNT" DefaultAccount="$ACCOUNT" >/dev/null

if ! pid_alive "$STATE/slurmctld.pid"; then
    slurmctld || fail "slurmctld did not start (see $STATE/slurmctld.log)"
else
    scontrol reconfigure >/dev/null 2>&1
fi
if ! pid_alive "$STATE/slurmd.pid"; then
    slurmd || fail "slurmd did not start (see $STATE/slurmd.log)"
fi
for _ in $(seq 100); do
    state=$(sinfo -h -n "$HOST" -o %T 2>/dev/null | head -n 1)
    case "$state" in idle|mixed|allocated) break ;; esac
    sleep 0.3
done
case "$state" in
    idle|mixed|allocated) ;;
    *) scontrol update nodename="$HOST" state=resume >/dev/null 2>&1; sleep 1
       state=$(sinfo -h -n "$HOST" -o %T 2>/dev/null | head -n 1) ;;
esac
case "$state" in
    idle|mixed|allocated) ;;
    *) fail "node $HOST is '${state:-unknown}', not idle (see $STATE/slurmctld.log and $STATE/slurmd.log)" ;;
esac
echo "slurm-up: cluster '$CLUSTER' up: node $HOST ($CPUS CPUs, $MEM_MB MB), partition $PARTITION, account $ACCOUNT; state in $STATE"
