#!/usr/bin/env bash
# A real single-node Slurm cluster on this machine, from Debian's packages, to try the
# workflow's Slurm path (profiles/slurm) and to test it.
#
#   scripts/slurm-single-node.sh install   # root: apt-get install munge slurmctld slurmd slurm-client
#   scripts/slurm-single-node.sh config    # root: writes slurm.conf only
#   scripts/slurm-single-node.sh start     # root: slurm.conf, munged, slurmctld, slurmd; waits for the node
#   scripts/slurm-single-node.sh status    # the node and the queue
#   scripts/slurm-single-node.sh stop      # root: stops the three daemons, nothing else
#
# One node named after this host (all its CPUs, its memory less 1 GiB), one partition
# `main`, accounting off (sacct is not used: the Slurm profile queries squeue, and finished
# jobs stay visible for MinJobAge = 30 min). The configuration is written to
# /etc/slurm/slurm.conf (or $SLURM_CONF) with a marker line; a slurm.conf without that marker belongs to
# somebody else and is never overwritten. State, spool and daemon logs are kept in
# KNOCKGS_SLURM_STATE (default /var/lib/knockgs-slurm).
#
# Exit status: 0 done; 2 refused (not root, packages missing, a foreign slurm.conf, a
# daemon that did not come up: the line printed says which and where its log is).
set -euo pipefail

CONF=${SLURM_CONF:-/etc/slurm/slurm.conf}  # Slurm's own variable: daemons and commands read it too
MARKER="# knockgs single-node cluster (scripts/slurm-single-node.sh)"
STATE=${KNOCKGS_SLURM_STATE:-/var/lib/knockgs-slurm}
PACKAGES=(munge slurmctld slurmd slurm-client)

refuse() { echo "slurm-single-node: $*" >&2; exit 2; }

need_root() {
    [ "$(id -u)" -eq 0 ] || refuse "'$1' needs root (it $2): run it as root, e.g. with sudo"
}

missing_commands() {
    local c missing=()
    for c in munged slurmctld slurmd sbatch squeue scontrol sinfo; do
        command -v "$c" >/dev/null 2>&1 || [ -x "/usr/sbin/$c" ] || missing+=("$c")
    done
    echo "${missing[@]:-}"
}

install() {
    need_root install "installs Debian packages"
    if [ -z "$(missing_commands)" ]; then
        echo "slurm-single-node: munge and Slurm are installed"
        return 0
    fi
    command -v apt-get >/dev/null 2>&1 || refuse "no apt-get: install ${PACKAGES[*]} with this system's package manager"
    export DEBIAN_FRONTEND=noninteractive
    apt-get update -q >/dev/null || refuse "apt-get update failed: no package index, cannot install ${PACKAGES[*]}"
    apt-get install -y -q "${PACKAGES[@]}" >/dev/null || refuse "apt-get install ${PACKAGES[*]} failed"
    echo "slurm-single-node: installed ${PACKAGES[*]}"
}

write_conf() {
    local node cpus mem
    if [ -e "$CONF" ] && ! grep -qxF "$MARKER" "$CONF"; then
        refuse "$CONF exists and was not written by this script: not overwriting it (stop that cluster, or move the file)"
    fi
    [ -x /usr/sbin/slurmd ] || refuse "slurmd is not installed: run '$0 install' as root first"
    node=$(hostname -s)
    cpus=$(nproc)
    # the node's memory as slurmd measures it, less 1 GiB for the daemons and the workflow's own process
    mem=$(/usr/sbin/slurmd -C | sed -n 's/.*RealMemory=\([0-9]*\).*/\1/p')
    [ -n "$mem" ] || refuse "slurmd -C did not report the node's memory"
    mem=$((mem > 2048 ? mem - 1024 : mem))
    mkdir -p "$(dirname "$CONF")" "$STATE"/{ctld,spool,log,run}
    chmod 755 "$STATE"
    local tmp
    tmp=$(mktemp "$CONF.XXXXXX")
    trap 'rm -f "$tmp"' EXIT  # a failed write leaves the old slurm.conf and no temporary file
    cat >"$tmp" <<EOF
$MARKER
ClusterName=knockgs
SlurmctldHost=$node(127.0.0.1)
SlurmUser=root
SlurmdUser=root
AuthType=auth/munge
CredType=cred/munge
MpiDefault=none
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
JobAcctGatherType=jobacct_gather/none
AccountingStorageType=accounting_storage/none
JobCompType=jobcomp/none
SchedulerType=sched/backfill
SelectType=select/cons_tres
SelectTypeParameters=CR_Core_Memory
ReturnToService=2
MinJobAge=1800
KillWait=10
StateSaveLocation=$STATE/ctld
SlurmdSpoolDir=$STATE/spool
SlurmctldPidFile=$STATE/run/slurmctld.pid
SlurmdPidFile=$STATE/run/slurmd.pid
SlurmctldLogFile=$STATE/log/slurmctld.log
SlurmdLogFile=$STATE/log/slurmd.log
NodeName=$node NodeAddr=127.0.0.1 CPUs=$cpus RealMemory=$mem State=UNKNOWN
PartitionName=main Nodes=ALL Default=YES MaxTime=INFINITE State=UP
EOF
    chmod 644 "$tmp"
    mv -f "$tmp" "$CONF"
    trap - EXIT
}

start_munge() {
    if pgrep -x munged >/dev/null 2>&1; then
        return 0
    fi
    if [ ! -s /etc/munge/munge.key ]; then
        if command -v mungekey >/dev/null 2>&1; then mungekey --create --keyfile=/etc/munge/munge.key; \
        else dd if=/dev/urandom of=/etc/munge/munge.key bs=1 count=128 status=none; fi
        chown munge:munge /etc/munge/munge.key && chmod 400 /etc/munge/munge.key
    fi
    mkdir -p /run/munge /var/log/munge /var/lib/munge
    chown munge:munge /run/munge /var/log/munge /var/lib/munge
    runuser -u munge -- /usr/sbin/munged || refuse "munged did not start (see /var/log/munge/munged.log)"
}

wait_for() {  # wait_for SECONDS COMMAND...: true once COMMAND succeeds
    local end=$((SECONDS + $1)); shift
    until "$@" >/dev/null 2>&1; do
        [ "$SECONDS" -lt "$end" ] || return 1
        sleep 0.5
    done
}

node_ready() {
    local state
    state=$(sinfo -h -N -o %T 2>/dev/null | head -1)
    case "$state" in idle|mixed|allocated|completing) return 0 ;; *) return 1 ;; esac
}

start() {
    need_root start "starts munged, slurmctld and slurmd"
    [ -z "$(missing_commands)" ] || refuse "missing $(missing_commands): run '$0 install' as root first (Debian: ${PACKAGES[*]})"
    write_conf
    start_munge
    wait_for 10 munge -n || refuse "munged does not answer (see /var/log/munge/munged.log)"
    if ! pgrep -x slurmctld >/dev/null 2>&1; then
        /usr/sbin/slurmctld || refuse "slurmctld did not start (see $STATE/log/slurmctld.log)"
    fi
    wait_for 30 scontrol ping || refuse "slurmctld does not answer (see $STATE/log/slurmctld.log)"
    if ! pgrep -x slurmd >/dev/null 2>&1; then
        /usr/sbin/slurmd || refuse "slurmd did not start (see $STATE/log/slurmd.log)"
    fi
    if ! wait_for 30 node_ready; then
        scontrol update nodename="$(hostname -s)" state=resume >/dev/null 2>&1 || true
        wait_for 15 node_ready || refuse "the node is not ready: $(sinfo -h -N -o '%T %E' | head -1) (see $STATE/log/slurmd.log)"
    fi
    echo "slurm-single-node: up: node $(hostname -s), $(nproc) CPUs, partition main (sinfo: $(sinfo -h -N -o %T | head -1))"
}

stop() {
    need_root stop "stops munged, slurmctld and slurmd"
    if pgrep -x slurmctld >/dev/null 2>&1; then
        scontrol shutdown >/dev/null 2>&1 || true  # slurmctld and every slurmd, state saved
    fi
    wait_for 20 sh -c '! pgrep -x slurmctld && ! pgrep -x slurmd' || {
        pkill -x slurmd || true; pkill -x slurmctld || true
        wait_for 10 sh -c '! pgrep -x slurmctld && ! pgrep -x slurmd' || refuse "slurmctld or slurmd still runs"
    }
    if pgrep -x munged >/dev/null 2>&1; then
        pkill -x munged || true
        wait_for 10 sh -c '! pgrep -x munged' || refuse "munged still runs"
    fi
    echo "slurm-single-node: stopped"
}

status() {
    if ! command -v sinfo >/dev/null 2>&1; then echo "slurm-single-node: Slurm is not installed"; exit 1; fi
    if ! scontrol ping >/dev/null 2>&1; then echo "slurm-single-node: slurmctld is not running"; exit 1; fi
    sinfo -N -o "%N %T %c %m %P"
    squeue -o "%.8i %.9P %.10T %.10M %.40k"
}

case "${1:-}" in
    install) install ;;
    config) need_root config "writes $CONF"; write_conf; echo "slurm-single-node: wrote $CONF" ;;
    start) start ;;
    stop) stop ;;
    status) status ;;
    *) echo "usage: $0 install|config|start|stop|status" >&2; exit 2 ;;
esac
