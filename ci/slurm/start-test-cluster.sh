#!/usr/bin/env bash
# Starts a single-node Slurm cluster on this machine for the Slurm tests
# (issue 15): installs Slurm 22.05 and munge from the distribution if they
# are missing, writes slurm.conf and cgroup.conf for one node with every CPU
# of the machine, starts munged, slurmctld and slurmd by hand (no systemd),
# and returns once `srun true` runs a job. Idempotent: on a running cluster it
# checks `srun true` and returns. Needs root (Debian/Ubuntu, apt-get).
#
# Settings and why (measured on Debian 12, 2 cores, no systemd):
# - cgroup.conf `CgroupPlugin=cgroup/v1`: slurmd 22.05 always loads a cgroup
#   plugin and dies on autodetection in a container;
# - `ProctrackType=proctrack/pgid`: linuxproc adds about 1 s per job;
# - `TaskPlugin=task/none`;
# - `SelectType=select/cons_tres` + `CR_CPU`: with a memory-aware setting a
#   job without `--mem` takes the whole node;
# - `SchedulerParameters=bf_interval=1`: else queued array tasks wait 1-3 s;
# - `NodeAddr=127.0.0.1`; `MinJobAge=3600` keeps finished jobs visible to
#   `scontrol show job` for an hour (there is no slurmdbd here).
set -euo pipefail

CONF_DIR=/etc/slurm
LOG_DIR=/var/log/slurm
NODE=$(hostname -s)
CPUS=$(nproc)
# Memory the node offers to `--mem` requests (MiB), a little under the total.
MEM_MB=$(awk '/MemTotal/ { printf "%d", $2 / 1024 * 0.9 }' /proc/meminfo)

log() { echo "start-test-cluster: $*" >&2; }

cluster_works() {
    command -v srun >/dev/null 2>&1 && timeout 20 srun --quiet true >/dev/null 2>&1
}

if cluster_works; then
    log "cluster already running ($(sinfo -h -o '%N %T %c CPUs'))"
    exit 0
fi

if ! command -v slurmctld >/dev/null || ! command -v slurmd >/dev/null \
    || ! command -v sbatch >/dev/null || ! command -v munged >/dev/null; then
    if [ "$(id -u)" != 0 ]; then
        log "Slurm is not installed and this is not root: install slurmctld slurmd slurm-client munge"
        exit 2
    fi
    log "installing slurmctld slurmd slurm-client munge"
    export DEBIAN_FRONTEND=noninteractive
    apt-get update -q >/dev/null
    apt-get install -y -q --no-install-recommends slurmctld slurmd slurm-client munge >/dev/null
fi

mkdir -p "$CONF_DIR" "$LOG_DIR" /var/spool/slurmctld /var/spool/slurmd /run/munge /var/lib/munge /var/log/munge

cat > "$CONF_DIR/slurm.conf" <<CONF
# Written by ci/slurm/start-test-cluster.sh: a single-node test cluster.
ClusterName=scanloc-test
SlurmctldHost=$NODE(127.0.0.1)
SlurmUser=root
SlurmdUser=root
AuthType=auth/munge
StateSaveLocation=/var/spool/slurmctld
SlurmdSpoolDir=/var/spool/slurmd
SlurmctldPidFile=/run/slurmctld.pid
SlurmdPidFile=/run/slurmd.pid
SlurmctldLogFile=$LOG_DIR/slurmctld.log
SlurmdLogFile=$LOG_DIR/slurmd.log
ProctrackType=proctrack/pgid
TaskPlugin=task/none
SelectType=select/cons_tres
SelectTypeParameters=CR_CPU
SchedulerType=sched/backfill
SchedulerParameters=bf_interval=1
MinJobAge=3600
ReturnToService=2
MpiDefault=none
JobCompType=jobcomp/none
JobAcctGatherType=jobacct_gather/none
AccountingStorageType=accounting_storage/none
NodeName=$NODE NodeAddr=127.0.0.1 CPUs=$CPUS RealMemory=$MEM_MB State=UNKNOWN
PartitionName=debug Nodes=$NODE Default=YES MaxTime=INFINITE State=UP
CONF

cat > "$CONF_DIR/cgroup.conf" <<CONF
# slurmd 22.05 always loads a cgroup plugin; autodetection fails here.
CgroupPlugin=cgroup/v1
CONF

# munge: a key if the package did not make one, then the daemon as its user.
if [ ! -s /etc/munge/munge.key ]; then
    dd if=/dev/urandom of=/etc/munge/munge.key bs=1024 count=1 status=none
fi
chown -R munge:munge /etc/munge /run/munge /var/lib/munge /var/log/munge 2>/dev/null || true
chmod 0400 /etc/munge/munge.key
chmod 0755 /run/munge
if ! munge -n >/dev/null 2>&1; then
    log "starting munged"
    runuser -u munge -- /usr/sbin/munged
fi

running() { [ -s "$1" ] && kill -0 "$(cat "$1")" 2>/dev/null; }

if ! running /run/slurmctld.pid; then
    log "starting slurmctld"
    /usr/sbin/slurmctld
else
    scontrol reconfigure >/dev/null 2>&1 || true
fi
if ! running /run/slurmd.pid; then
    log "starting slurmd"
    /usr/sbin/slurmd -N "$NODE"
fi

# sinfo can say idle before slurmd has registered: only a job proves it.
for _ in $(seq 1 30); do
    if cluster_works; then
        log "cluster up ($(sinfo -h -o '%N %T %c CPUs'))"
        exit 0
    fi
    scontrol update nodename="$NODE" state=resume >/dev/null 2>&1 || true
    sleep 1
done
log "the cluster did not run a job within 30 s; logs in $LOG_DIR"
tail -n 20 "$LOG_DIR/slurmctld.log" "$LOG_DIR/slurmd.log" >&2 || true
exit 1
