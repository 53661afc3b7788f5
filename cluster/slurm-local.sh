#!/usr/bin/env bash
# A single-node SLURM cluster on this machine, for testing the workflow's cluster path
# (profiles/slurm + snakemake-executor-plugin-slurm) without systemd or a database.
#
#   cluster/slurm-local.sh start    install SLURM and munge if missing (Debian packages),
#                                    write the configs into the state folder, start
#                                    munged, slurmctld and slurmd, wait for the node
#   cluster/slurm-local.sh stop     cancel this cluster's jobs, stop the daemons by PID
#   cluster/slurm-local.sh status   daemons and node state
#   cluster/slurm-local.sh env      the line to eval so that sbatch/squeue find the cluster
#
# Every file lives in the state folder ($DEPTHGT_SLURM_STATE, default
# ${TMPDIR:-/tmp}/depthgt-slurm): slurm.conf, munge key and socket, spool, logs, PID
# files. Clients (sbatch, squeue, the executor plugin) find the cluster through
# SLURM_CONF=$STATE/slurm.conf (`eval "$(cluster/slurm-local.sh env)"`); the one file
# outside is the link /etc/slurm/slurm.conf -> $STATE/slurm.conf, for the job steps
# (see link_system_conf), removed by `stop`. One such cluster per machine at a time.
#
# Settings (environment): DEPTHGT_SLURMCTLD_PORT (6817), DEPTHGT_SLURMD_PORT (6818),
# DEPTHGT_SLURM_GPUS (default: the number of /dev/nvidia<N> devices): GPUs the node
# offers as gres/gpu; where there are fewer device files than GPUs asked for, the node
# declares the missing ones with empty placeholder device files, which lets a `--gpus`
# request be scheduled and inspected on a machine without a GPU (such a job gets the
# placeholder, not a GPU).
#
# Configuration choices: proctrack/linuxproc and task/none (no cgroups, no systemd),
# accounting_storage/none (no slurmdbd: `sacct` cannot answer, so the executor plugin
# polls with `squeue`; MinJobAge keeps finished jobs visible to squeue and scontrol for an
# hour: the tests read their records long after the runs that start with the session),
# jobcomp/filetxt (one line per finished job in $STATE/jobcomp.txt), select/cons_tres
# with CR_CPU_Memory (cores and memory are consumable: a job's --mem is enforced at
# scheduling). Daemons run as the calling user; installing needs root (apt-get).
# Exit status: 0 ok, 2 usage, 3 SLURM cannot be installed or set up here (not root, no
# apt-get, another SLURM configuration in /etc/slurm), 4 a daemon did not come up (the
# daemons it started are stopped again; logs in $STATE/log).
set -euo pipefail

STATE="${DEPTHGT_SLURM_STATE:-${TMPDIR:-/tmp}/depthgt-slurm}"
CTLD_PORT="${DEPTHGT_SLURMCTLD_PORT:-6817}"
SLURMD_PORT="${DEPTHGT_SLURMD_PORT:-6818}"
PACKAGES=(slurmctld slurmd slurm-client munge)
PATH="$PATH:/usr/sbin:/sbin"
NODE="$(hostname -s)"

log() { echo "slurm-local: $*" >&2; }
die() { local code=$1; shift; log "$*"; exit "$code"; }

have_slurm() {
    command -v slurmctld >/dev/null && command -v slurmd >/dev/null && command -v sbatch >/dev/null \
        && command -v squeue >/dev/null && command -v munged >/dev/null
}

install_slurm() {
    have_slurm && return 0
    [ "$(id -u)" = 0 ] || die 3 "SLURM is not installed and installing it needs root (apt-get install ${PACKAGES[*]})"
    command -v apt-get >/dev/null || die 3 "SLURM is not installed and apt-get is not available"
    log "installing ${PACKAGES[*]}"
    export DEBIAN_FRONTEND=noninteractive
    # Refresh the package lists once, only when the packages are not known yet (or the
    # cached lists point at files the mirror no longer has).
    local apt=(apt-get -o DPkg::Lock::Timeout=300)  # wait for another apt run to finish
    if ! "${apt[@]}" install -y --no-install-recommends "${PACKAGES[@]}" >"$STATE/apt.log" 2>&1; then
        "${apt[@]}" update >>"$STATE/apt.log" 2>&1 || die 3 "apt-get update failed (see $STATE/apt.log)"
        "${apt[@]}" install -y --no-install-recommends "${PACKAGES[@]}" >>"$STATE/apt.log" 2>&1 \
            || die 3 "apt-get install ${PACKAGES[*]} failed (see $STATE/apt.log)"
    fi
    have_slurm || die 3 "SLURM packages installed but their commands are missing (see $STATE/apt.log)"
}

HEADER="# Written by cluster/slurm-local.sh"
SYSTEM_CONF=/etc/slurm/slurm.conf

link_system_conf() {
    # The executor plugin's job step starts the job with a nested `srun` whose
    # environment has every SLURM_* variable removed, SLURM_CONF included: inside a job,
    # SLURM's commands find this cluster only at the default path. Link it there; a
    # file there that is not such a link (to a live or a removed state folder) belongs
    # to another SLURM installation and is left alone.
    if [ -L "$SYSTEM_CONF" ]; then
        local target
        target="$(readlink "$SYSTEM_CONF")"
        if [ -e "$target" ] && [[ "$(head -n1 "$target")" != "$HEADER"* ]]; then
            die 3 "$SYSTEM_CONF links to $target, another SLURM configuration; not replacing it"
        fi
    elif [ -e "$SYSTEM_CONF" ]; then
        die 3 "$SYSTEM_CONF belongs to another SLURM installation; not replacing it"
    fi
    if ! { mkdir -p "$(dirname "$SYSTEM_CONF")" && ln -sfn "$STATE/slurm.conf" "$SYSTEM_CONF"; }; then
        die 3 "cannot link $SYSTEM_CONF to $STATE/slurm.conf (needs root)"
    fi
}

unlink_system_conf() {
    if [ -L "$SYSTEM_CONF" ] && [ "$(readlink "$SYSTEM_CONF")" = "$STATE/slurm.conf" ]; then
        rm -f "$SYSTEM_CONF"
    fi
}

pid_alive() { [ -s "$1" ] && kill -0 "$(cat "$1")" 2>/dev/null; }

gpu_devices() { compgen -G '/dev/nvidia[0-9]*' | sort -V || true; }

write_configs() {
    mkdir -p "$STATE"/{munge,ctld,spool,log,run}
    chmod 755 "$STATE/munge"  # clients reach the socket; the key itself is 0400
    if [ ! -s "$STATE/munge/munge.key" ]; then
        # munge's key is 1024 random bytes readable by its owner only
        head -c 1024 /dev/urandom >"$STATE/munge/munge.key"
        chmod 400 "$STATE/munge/munge.key"
    fi
    local cpus mem_mb devices gpus i gres_node="" gres_types=""
    cpus="$(nproc)"
    # leave 1 GiB to the system; RealMemory bounds what jobs may request (--mem)
    mem_mb="$(awk '/^MemTotal:/ {m = int($2 / 1024) - 1024; print (m > 512 ? m : 512)}' /proc/meminfo)"
    mapfile -t devices < <(gpu_devices)
    gpus="${DEPTHGT_SLURM_GPUS:-${#devices[@]}}"
    : >"$STATE/gres.conf"
    if [ "$gpus" -gt 0 ]; then
        gres_types="GresTypes=gpu"
        gres_node="Gres=gpu:$gpus"
        if [ "${#devices[@]}" -lt "$gpus" ]; then
            # SLURM drops GPUs without a device file: empty placeholder files stand in
            mkdir -p "$STATE/placeholder-gpus"
            devices=()
            for ((i = 0; i < gpus; i++)); do
                : >"$STATE/placeholder-gpus/nvidia$i"
                devices+=("$STATE/placeholder-gpus/nvidia$i")
            done
        fi
        printf "NodeName=$NODE Name=gpu File=%s\n" "${devices[@]:0:$gpus}" >"$STATE/gres.conf"
    fi
    cat >"$STATE/slurm.conf" <<EOF
$HEADER: a single-node test cluster without systemd or slurmdbd.
ClusterName=depthgt
SlurmctldHost=$NODE(127.0.0.1)
SlurmctldPort=$CTLD_PORT
SlurmdPort=$SLURMD_PORT
SlurmUser=$(id -un)
SlurmdUser=$(id -un)
AuthType=auth/munge
CredType=cred/munge
AuthInfo=socket=$STATE/munge/munge.socket
StateSaveLocation=$STATE/ctld
SlurmdSpoolDir=$STATE/spool
SlurmctldPidFile=$STATE/run/slurmctld.pid
SlurmdPidFile=$STATE/run/slurmd.pid
SlurmctldLogFile=$STATE/log/slurmctld.log
SlurmdLogFile=$STATE/log/slurmd.log
SlurmctldDebug=info
SlurmdDebug=info
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
JobAcctGatherType=jobacct_gather/none
AccountingStorageType=accounting_storage/none
JobCompType=jobcomp/filetxt
JobCompLoc=$STATE/jobcomp.txt
SchedulerType=sched/backfill
SelectType=select/cons_tres
SelectTypeParameters=CR_CPU_Memory
MpiDefault=none
ReturnToService=2
MinJobAge=3600
MailProg=/bin/true
PlugStackConfig=$STATE/plugstack.conf
$gres_types
NodeName=$NODE NodeAddr=127.0.0.1 CPUs=$cpus RealMemory=$mem_mb $gres_node State=UNKNOWN
PartitionName=debug Nodes=$NODE Default=YES MaxTime=INFINITE State=UP
EOF
    # gres.conf and plugstack.conf are read from slurm.conf's folder; the empty
    # plugstack keeps the packaged /etc/slurm/plugstack.conf.d out of this cluster
    : >"$STATE/plugstack.conf"
}

wait_for() {  # wait_for SECONDS DESCRIPTION COMMAND...
    local secs=$1 what=$2; shift 2
    local i
    for ((i = 0; i < secs * 5; i++)); do
        "$@" >/dev/null 2>&1 && return 0
        sleep 0.2
    done
    die 4 "$what did not come up within ${secs}s (logs in $STATE/log)"
}

node_ready() {
    local state
    state="$(sinfo -h -n "$NODE" -o %t 2>/dev/null)" || return 1
    [[ "$state" == idle* || "$state" == mix* || "$state" == alloc* ]]
}

start() {
    mkdir -p "$STATE"
    install_slurm
    if pid_alive "$STATE/run/slurmctld.pid" && pid_alive "$STATE/run/slurmd.pid"; then
        log "already running (state in $STATE)"
        return 0
    fi
    write_configs
    link_system_conf
    export SLURM_CONF="$STATE/slurm.conf"
    trap 'log "start failed, stopping what was started"; stop' EXIT
    pid_alive "$STATE/run/munged.pid" || munged --force \
        --key-file="$STATE/munge/munge.key" --socket="$STATE/munge/munge.socket" \
        --pid-file="$STATE/run/munged.pid" --log-file="$STATE/log/munged.log" \
        --seed-file="$STATE/munge/munged.seed"
    wait_for 20 munged munge -n --socket="$STATE/munge/munge.socket"
    # -c: start with a clean job state (a previous cluster in this folder is forgotten,
    # its job ids start again at 1, and so does the job completion record)
    : >"$STATE/jobcomp.txt"
    pid_alive "$STATE/run/slurmctld.pid" || slurmctld -c -f "$SLURM_CONF"
    wait_for 30 slurmctld scontrol ping
    pid_alive "$STATE/run/slurmd.pid" || slurmd -f "$SLURM_CONF" -N "$NODE"
    wait_for 60 "node $NODE" node_ready
    trap - EXIT
    log "running: $(sinfo -h -o '%P %D %t %c cpus %m MB %G')"
    log "clients need: export SLURM_CONF=$SLURM_CONF"
}

stop_pid() {  # stop_pid NAME PIDFILE: TERM, wait up to 10 s, then KILL
    local name=$1 file=$2 pid i
    [ -s "$file" ] || return 0
    pid="$(cat "$file")"
    if kill -0 "$pid" 2>/dev/null; then
        kill "$pid" 2>/dev/null || true
        for ((i = 0; i < 50; i++)); do kill -0 "$pid" 2>/dev/null || break; sleep 0.2; done
        if kill -0 "$pid" 2>/dev/null; then
            log "$name ($pid) ignored TERM, sending KILL"
            kill -9 "$pid" 2>/dev/null || true
        fi
    fi
    rm -f "$file"
}

stop() {
    export SLURM_CONF="$STATE/slurm.conf"
    if [ -f "$SLURM_CONF" ] && pid_alive "$STATE/run/slurmctld.pid"; then
        # cancel this cluster's jobs so that no job step outlives slurmd
        scancel --full --quiet --partition=debug 2>/dev/null || true
        local i
        for ((i = 0; i < 50; i++)); do
            [ -z "$(squeue -h -t running,completing -o %i 2>/dev/null)" ] && break
            sleep 0.2
        done
    fi
    stop_pid slurmd "$STATE/run/slurmd.pid"
    stop_pid slurmctld "$STATE/run/slurmctld.pid"
    stop_pid munged "$STATE/run/munged.pid"
    unlink_system_conf
    log "stopped (state and logs kept in $STATE)"
}

status() {
    local name rc=0
    for name in munged slurmctld slurmd; do
        if pid_alive "$STATE/run/$name.pid"; then
            echo "$name running (pid $(cat "$STATE/run/$name.pid"))"
        else
            echo "$name not running"; rc=1
        fi
    done
    [ "$rc" = 0 ] && SLURM_CONF="$STATE/slurm.conf" sinfo -N -o '%N %P %t %c %m %G'
    return "$rc"
}

case "${1:-}" in
    start) start ;;
    stop) stop ;;
    status) status ;;
    env) echo "export SLURM_CONF=$STATE/slurm.conf" ;;
    *) die 2 "usage: $0 start|stop|status|env   (state folder: $STATE)" ;;
esac
