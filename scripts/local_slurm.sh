#!/usr/bin/env bash
# A one-node Slurm cluster on this machine, for trying `aaute benchmark --launcher slurm` and for the
# tests marked `slurm`. Debian/Ubuntu packages (slurm-wlm, munge), localhost only, no accounting.
#
#   scripts/local_slurm.sh up       install if missing (root, apt-get), configure, start, wait until idle
#   scripts/local_slurm.sh status   the daemons and `sinfo`
#   scripts/local_slurm.sh down     stop the daemons (configuration and packages stay)
#
# `up` is idempotent: on a running, healthy cluster it does nothing. The cluster is named `aaute`, which the
# tests check before submitting anything (they never submit to another cluster unless AAUTE_SLURM_TESTS=1).
# Sized from the machine: CPUs from nproc, RealMemory 90% of `free`'s total. Logs: /var/log/slurm/.
set -euo pipefail

CLUSTER=aaute
CONF_DIR=/etc/slurm
CONF=$CONF_DIR/slurm.conf
STATE=/var/spool/slurmctld
SPOOL=/var/spool/slurmd
LOGS=/var/log/slurm
NODE=$(hostname -s)
TIMEOUT_S=${LOCAL_SLURM_TIMEOUT_S:-120}

say() { echo "local_slurm: $*"; }
die() { echo "local_slurm: $*" >&2; exit 2; }

healthy() {
    command -v sinfo >/dev/null 2>&1 || return 1
    [ "$(scontrol show config 2>/dev/null | awk '$1 == "ClusterName" {print $3}')" = "$CLUSTER" ] || return 1
    sinfo -h -n "$NODE" -o '%T' 2>/dev/null | grep -Eq '^(idle|mixed|allocated)$'
}

install() {
    if command -v slurmctld >/dev/null 2>&1 && command -v munged >/dev/null 2>&1; then
        return
    fi
    [ "$(id -u)" = 0 ] || die "slurm-wlm and munge are not installed; run as root (apt-get) or install them"
    command -v apt-get >/dev/null 2>&1 || die "slurm-wlm and munge are not installed and there is no apt-get"
    say "installing slurm-wlm and munge (apt-get)"
    export DEBIAN_FRONTEND=noninteractive
    apt-get update -qq
    apt-get install -y -qq --no-install-recommends slurm-wlm munge >/dev/null
}

munge_key() {
    local key=/etc/munge/munge.key
    if [ ! -s "$key" ]; then
        mkdir -p /etc/munge
        dd if=/dev/urandom of="$key" bs=1 count=1024 status=none
    fi
    chown munge:munge "$key" 2>/dev/null || true
    chmod 0400 "$key"
    mkdir -p /run/munge /var/lib/munge /var/log/munge
    chown -R munge:munge /run/munge /var/lib/munge /var/log/munge /etc/munge 2>/dev/null || true
}

write_conf() {
    local cpus memory
    cpus=$(nproc)
    memory=$(free -m | awk '/^Mem:/ {printf "%d", $2 * 0.9}')
    mkdir -p "$CONF_DIR" "$STATE" "$SPOOL" "$LOGS"
    cat >"$CONF.tmp" <<EOF
# written by scripts/local_slurm.sh: a one-node cluster on localhost, no accounting
ClusterName=$CLUSTER
SlurmctldHost=$NODE(127.0.0.1)
SlurmUser=root
SlurmdUser=root
AuthType=auth/munge
StateSaveLocation=$STATE
SlurmdSpoolDir=$SPOOL
SlurmctldPidFile=/run/slurmctld.pid
SlurmdPidFile=/run/slurmd.pid
SlurmctldLogFile=$LOGS/slurmctld.log
SlurmdLogFile=$LOGS/slurmd.log
MpiDefault=none
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
SelectType=select/cons_tres
SelectTypeParameters=CR_CPU
SchedulerType=sched/backfill
ReturnToService=2
AccountingStorageType=accounting_storage/none
JobAcctGatherType=jobacct_gather/none
JobCompType=jobcomp/none
# a killed job is gone quickly; finished jobs stay visible to squeue for 10 minutes (there is no sacct)
KillWait=5
MinJobAge=600
SlurmdTimeout=60
NodeName=$NODE NodeAddr=127.0.0.1 CPUs=$cpus RealMemory=$memory State=UNKNOWN
PartitionName=debug Nodes=$NODE Default=YES MaxTime=INFINITE State=UP
EOF
    if [ -f "$CONF" ] && cmp -s "$CONF" "$CONF.tmp"; then
        rm -f "$CONF.tmp"
    else
        mv "$CONF.tmp" "$CONF"
    fi
    # cgroup.conf is read by some plugins even when unused; keep it trivial
    [ -f "$CONF_DIR/cgroup.conf" ] || echo "CgroupPlugin=autodetect" >"$CONF_DIR/cgroup.conf"
}

running() { pgrep -x "$1" >/dev/null 2>&1; }

start() {
    if ! running munged; then
        if [ "$(id -u)" = 0 ] && id munge >/dev/null 2>&1; then
            runuser -u munge -- /usr/sbin/munged
        else
            /usr/sbin/munged
        fi
    fi
    running slurmctld || slurmctld
    running slurmd || slurmd
}

wait_idle() {
    local waited=0
    while ! healthy; do
        if [ "$waited" -ge "$TIMEOUT_S" ]; then
            sinfo -N -l 2>&1 || true
            die "the node did not become idle within ${TIMEOUT_S} s (logs: $LOGS)"
        fi
        # a node left DOWN or DRAINED by an earlier run is resumed
        if sinfo -h -n "$NODE" -o '%T' 2>/dev/null | grep -Eq 'down|drain'; then
            scontrol update NodeName="$NODE" State=RESUME >/dev/null 2>&1 || true
        fi
        sleep 1
        waited=$((waited + 1))
    done
}

up() {
    local start_s=$SECONDS
    if healthy; then
        say "cluster $CLUSTER already up (node $NODE idle)"
        return
    fi
    install
    munge_key
    write_conf
    start
    wait_idle
    say "cluster $CLUSTER up in $((SECONDS - start_s)) s: node $NODE, $(nproc) CPUs"
}

down() {
    # by the daemons' own pid files, so nothing else on the machine is touched
    local pidfile pid
    for pidfile in /run/slurmd.pid /run/slurmctld.pid /run/munge/munged.pid; do
        [ -s "$pidfile" ] || continue
        pid=$(cat "$pidfile")
        kill "$pid" 2>/dev/null || continue
        for _ in $(seq 40); do kill -0 "$pid" 2>/dev/null || break; sleep 0.25; done
    done
    say "stopped"
}

status() {
    for daemon in munged slurmctld slurmd; do
        if running "$daemon"; then echo "$daemon: running"; else echo "$daemon: stopped"; fi
    done
    if healthy; then sinfo; exit 0; fi
    exit 1
}

case "${1:-}" in
    up) up ;;
    down) down ;;
    status) status ;;
    *) echo "usage: $0 up|down|status" >&2; exit 2 ;;
esac
