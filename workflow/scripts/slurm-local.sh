#!/usr/bin/env bash
# A single-node SLURM on loopback, for testing the workflow's SLURM profile on one machine
# (Debian/Ubuntu, run as root; no systemd needed). Not for production clusters.
#
#   workflow/scripts/slurm-local.sh start    install slurm-wlm + munge if missing, start
#                                            munged, slurmctld, slurmd; wait until the node is idle
#   workflow/scripts/slurm-local.sh stop     stop the daemons this script started (by pid file)
#   workflow/scripts/slurm-local.sh status   exit 0 when the node answers
# Exit status 2: a daemon did not come up (its log is named); 3: SLURM cannot be set up here
# (not root, no apt-get, installation failed, or /etc/slurm/slurm.conf belongs to a real SLURM).
#
# Accounting: none (AccountingStorageType=accounting_storage/none, MinJobAge=300). Snakemake's
# SLURM plugin then needs `--slurm-status-command squeue` (sacct has no database to ask).
# State, spool, logs and pid files live in $DICER_SLURM_DIR (default /tmp/dicer-slurm);
# /etc/slurm/slurm.conf is a symlink to its slurm.conf (SLURM's job steps read only that path).
set -euo pipefail

DIR=${DICER_SLURM_DIR:-/tmp/dicer-slurm}
CONF=/etc/slurm/slurm.conf
PARTITION=${DICER_SLURM_PARTITION:-debug}
# CPUs the node offers (default: the machine's); more than the machine has lets more small,
# mostly start-up-bound jobs run at once (the test asks for 4)
CPUS=${DICER_SLURM_CPUS:-$(nproc)}

die() { echo "error: slurm-local: $*" >&2; exit 2; }
# exit status 3: SLURM cannot be set up on this machine at all (not root, nothing to install with)
cannot() { echo "error: slurm-local: $*" >&2; exit 3; }

install_packages() {
    command -v slurmctld >/dev/null && command -v slurmd >/dev/null && command -v munged >/dev/null && return
    command -v apt-get >/dev/null || cannot "slurm-wlm and munge are not installed and there is no apt-get; install them by hand"
    echo "slurm-local: installing slurm-wlm munge (apt-get)" >&2
    export DEBIAN_FRONTEND=noninteractive
    apt-get install -y -qq slurm-wlm munge >/dev/null 2>&1 \
        || { apt-get update -qq >/dev/null 2>&1 && apt-get install -y -qq slurm-wlm munge >/dev/null; } \
        || cannot "apt-get install slurm-wlm munge failed; install them by hand"
}

alive() { [ -s "$1" ] && kill -0 "$(cat "$1")" 2>/dev/null; }

write_conf() {
    local host cpus mem
    host=$(hostname -s)
    cpus=$CPUS
    mem=$(awk '/^MemTotal:/ {printf "%d", $2 / 1024 * 0.9}' /proc/meminfo)
    mkdir -p "$DIR/state" "$DIR/spool" "$DIR/log"
    cat > "$DIR/slurm.conf" <<CONF
# written by workflow/scripts/slurm-local.sh: one node on loopback, no accounting
ClusterName=dicer-local
SlurmctldHost=$host(127.0.0.1)
SlurmUser=root
SlurmdUser=root
AuthType=auth/munge
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
SelectType=select/cons_tres
SelectTypeParameters=CR_Core_Memory
JobAcctGatherType=jobacct_gather/linux
AccountingStorageType=accounting_storage/none
MinJobAge=300
ReturnToService=2
SlurmdParameters=config_overrides
SchedulerType=sched/backfill
StateSaveLocation=$DIR/state
SlurmdSpoolDir=$DIR/spool
SlurmctldPidFile=$DIR/slurmctld.pid
SlurmdPidFile=$DIR/slurmd.pid
SlurmctldLogFile=$DIR/log/slurmctld.log
SlurmdLogFile=$DIR/log/slurmd.log
SlurmctldPort=6817
SlurmdPort=6818
NodeName=$host NodeAddr=127.0.0.1 CPUs=$cpus RealMemory=$mem State=UNKNOWN
PartitionName=$PARTITION Nodes=$host Default=YES MaxTime=INFINITE State=UP
CONF
    mkdir -p /etc/slurm
    if [ -e "$CONF" ] || [ -L "$CONF" ]; then
        [ "$(readlink "$CONF" || true)" = "$DIR/slurm.conf" ] \
            || cannot "$CONF exists and is not this script's; refusing to replace a real SLURM configuration"
    else
        ln -s "$DIR/slurm.conf" "$CONF"
    fi
}

start_munge() {
    alive "$DIR/munge/munged.pid" && return
    mkdir -p /run/munge
    chown munge:munge /run/munge
    chmod 0755 /run/munge
    [ -s /etc/munge/munge.key ] || { mungekey --create >/dev/null 2>&1 || create-munge-key >/dev/null 2>&1; chown munge:munge /etc/munge/munge.key; }
    # munged runs as user munge: its pid and log files in a folder of its own
    mkdir -p "$DIR/munge"
    chown munge:munge "$DIR/munge"
    chmod 0700 "$DIR/munge"
    su -s /bin/sh munge -c "munged --pid-file=$DIR/munge/munged.pid --log-file=$DIR/munge/munged.log" \
        || die "munged did not start; see $DIR/munge/munged.log"
}

start() {
    [ "$(id -u)" = 0 ] || cannot "needs root (installs packages, writes /etc/slurm, runs the daemons as root)"
    install_packages
    mkdir -p "$DIR"
    write_conf
    start_munge
    # -c: a fresh controller forgets the jobs of an earlier start
    alive "$DIR/slurmctld.pid" || slurmctld -c -f "$DIR/slurm.conf"
    alive "$DIR/slurmd.pid" || slurmd -f "$DIR/slurm.conf"
    for _ in $(seq 60); do
        if sinfo -h -o '%t' 2>/dev/null | grep -qx 'idle\|mix\|alloc'; then
            echo "slurm-local: node $(hostname -s) up, partition $PARTITION, state in $DIR" >&2
            return 0
        fi
        sleep 0.5
    done
    scontrol update NodeName="$(hostname -s)" State=RESUME >/dev/null 2>&1 || true
    sinfo -h -o '%t' 2>/dev/null | grep -qx 'idle\|mix\|alloc' && return 0
    die "the node did not become idle within 30 s; see $DIR/log/slurmctld.log and slurmd.log"
}

stop_one() {
    local pidfile=$1 pid
    [ -s "$pidfile" ] || return 0
    pid=$(cat "$pidfile")
    if kill -0 "$pid" 2>/dev/null; then
        kill "$pid"
        for _ in $(seq 50); do kill -0 "$pid" 2>/dev/null || break; sleep 0.2; done
        kill -0 "$pid" 2>/dev/null && kill -9 "$pid"
    fi
    rm -f "$pidfile"
}

stop() {
    stop_one "$DIR/slurmd.pid"
    stop_one "$DIR/slurmctld.pid"
    stop_one "$DIR/munge/munged.pid"
    if [ "$(readlink "$CONF" 2>/dev/null || true)" = "$DIR/slurm.conf" ]; then
        rm -f "$CONF"
    fi
    echo "slurm-local: stopped" >&2
}

case "${1:-}" in
    start) start ;;
    stop) stop ;;
    status) sinfo -h -o '%t' 2>/dev/null | grep -qx 'idle\|mix\|alloc' ;;
    *) echo "usage: $0 start|stop|status" >&2; exit 2 ;;
esac
