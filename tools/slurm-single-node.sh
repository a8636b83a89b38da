#!/usr/bin/env bash
# A single-node Slurm on this machine, to test `invaders experiment … --slurm` against a real
# scheduler (issue #102). Debian 12 or later, as root:
#
#   bash tools/slurm-single-node.sh up       # install (apt) if needed, configure, start, wait
#   bash tools/slurm-single-node.sh status   # sinfo and the queue
#   bash tools/slurm-single-node.sh down     # stop the daemons (the packages stay)
#
# One node (this host, with the CPUs and memory `slurmd -C` finds), one partition `debug`, no
# accounting. The daemons run as root and are started directly, not through systemd (containers
# often have none): munged, slurmctld, slurmd. Process tracking is `proctrack/linuxproc` and task
# binding `task/none`, which need no cgroups, so this works in a container; jobs are therefore not
# confined to their memory (`--mem` is still counted when jobs are placed). All state lives in
# $SLURM_SN_DIR (default /var/lib/slurm-single-node); `down` keeps it, `down --purge` deletes it.
# It writes /etc/slurm/slurm.conf, keeping any earlier one as slurm.conf.before-single-node.
set -euo pipefail

STATE=${SLURM_SN_DIR:-/var/lib/slurm-single-node}
CONF=/etc/slurm/slurm.conf

die() { echo "slurm-single-node: $*" >&2; exit 1; }

need_root() { [ "$(id -u)" = 0 ] || die "run as root (it installs packages and starts daemons)"; }

install_packages() {
    if command -v slurmctld >/dev/null && command -v slurmd >/dev/null \
        && command -v sbatch >/dev/null && command -v munged >/dev/null; then
        return
    fi
    command -v apt-get >/dev/null || die "no apt-get: install slurmctld, slurmd, slurm-client and munge by hand"
    echo "installing slurmctld slurmd slurm-client munge"
    apt-get update -qq
    DEBIAN_FRONTEND=noninteractive apt-get install -y -qq slurmctld slurmd slurm-client munge >/dev/null
}

write_conf() {
    local host node cpus mem
    host=$(hostname -s)
    node=$(slurmd -C | head -n 1)
    cpus=$(sed -n 's/.* CPUs=\([0-9]*\).*/\1/p' <<<"$node")
    mem=$(sed -n 's/.* RealMemory=\([0-9]*\).*/\1/p' <<<"$node")
    [ -n "$cpus" ] && [ -n "$mem" ] || die "slurmd -C gave no CPUs or RealMemory: $node"
    # Leave the system 5 % of memory, so that a node is never refused for reporting less.
    mem=$((mem * 95 / 100))
    mkdir -p "$STATE"/{ctld,d,log} /etc/slurm
    if [ -f "$CONF" ] && ! grep -q '^# written by slurm-single-node' "$CONF"; then
        cp "$CONF" "$CONF.before-single-node"
    fi
    cat >"$CONF" <<EOF
# written by slurm-single-node.sh (tools/ of invaders); 'down' leaves it
ClusterName=single
SlurmctldHost=$host
SlurmUser=root
SlurmdUser=root
AuthType=auth/munge
# A killed job's credential stays revoked this long, and a requeued job waits for it (default 120 s).
AuthInfo=cred_expire=10
StateSaveLocation=$STATE/ctld
SlurmdSpoolDir=$STATE/d
SlurmctldPidFile=$STATE/slurmctld.pid
SlurmdPidFile=$STATE/slurmd.pid
SlurmctldLogFile=$STATE/log/slurmctld.log
SlurmdLogFile=$STATE/log/slurmd.log
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
JobAcctGatherType=jobacct_gather/none
AccountingStorageType=accounting_storage/none
MpiDefault=none
SwitchType=switch/none
SchedulerType=sched/backfill
SelectType=select/cons_tres
SelectTypeParameters=CR_Core_Memory
DefMemPerCPU=1000
ReturnToService=2
JobRequeue=1
KillWait=30
MaxArraySize=10001
NodeName=$host CPUs=$cpus RealMemory=$mem State=UNKNOWN
PartitionName=debug Nodes=$host Default=YES MaxTime=INFINITE State=UP
EOF
    echo "wrote $CONF: node $host, $cpus CPUs, $mem MB"
}

running() { pgrep -x "$1" >/dev/null; }

up() {
    need_root
    install_packages
    write_conf
    mkdir -p /run/munge && chown munge:munge /run/munge
    running munged || su -s /bin/sh munge -c /usr/sbin/munged \
        || /usr/sbin/munged --force || die "munged did not start"
    running slurmctld || slurmctld || die "slurmctld did not start: see $STATE/log/slurmctld.log"
    running slurmd || slurmd || die "slurmd did not start: see $STATE/log/slurmd.log"
    for _ in $(seq 60); do
        if sinfo -h -N -o '%T' 2>/dev/null | grep -Eq '^(idle|mixed|allocated)'; then
            scontrol update nodename="$(hostname -s)" state=resume >/dev/null 2>&1 || true
            sinfo
            return
        fi
        sleep 1
    done
    sinfo || true
    die "the node did not become idle in 60 s: see $STATE/log/"
}

stop_daemon() {
    local name=$1 pid
    pid=$(pgrep -x "$name" || true)
    [ -n "$pid" ] || return 0
    kill $pid
    for _ in $(seq 30); do
        kill -0 $pid 2>/dev/null || return 0
        sleep 0.5
    done
    echo "$name did not stop in 15 s; killing it" >&2
    kill -9 $pid 2>/dev/null || true
}

down() {
    need_root
    stop_daemon slurmd
    stop_daemon slurmctld
    stop_daemon munged
    if [ "${1:-}" = --purge ]; then rm -rf "$STATE"; fi
    echo "stopped"
}

status() {
    for d in munged slurmctld slurmd; do
        if running $d; then echo "$d: running"; else echo "$d: stopped"; fi
    done
    if running slurmctld; then sinfo; squeue; fi
}

case "${1:-}" in
    up) up ;;
    down) down "${2:-}" ;;
    status) status ;;
    *) die "usage: $0 up|down [--purge]|status" ;;
esac
