#!/usr/bin/env bash
# A one-node SLURM cluster on this machine, every file of it in one folder: munge with its own key
# and socket, slurmctld and slurmd on free ports, state, spool and logs. What tests/test_slurm.py
# submits `launcher: slurm` recipes to; also a way to try a cluster recipe on a workstation.
#
#   tools/slurm/single_node.sh start DIR   # prints `export SLURM_CONF=DIR/slurm.conf`
#   tools/slurm/single_node.sh stop DIR
#
# Needs root (slurmd starts jobs as their users) and Debian's packages:
#   apt-get install -y slurm-wlm munge
# Exit code 3: SLURM cannot run here (not installed, or not root); the message says why.
set -euo pipefail

usage() { echo "usage: $0 start|stop DIR" >&2; exit 2; }
[[ $# -eq 2 ]] || usage
action=$1
dir=$(mkdir -p "$2" && cd "$2" && pwd)

stop() {
    # The jobs first: slurmd leaves running jobs alone when it stops (a restart must not kill
    # them), and a job left so outlives the cluster. Waited for up to 20 s (KillWait is 10 s).
    local pid jobs
    if [[ -f "$dir/slurmctld.pid" ]] && kill -0 "$(cat "$dir/slurmctld.pid")" 2>/dev/null; then
        jobs=$(SLURM_CONF="$dir/slurm.conf" squeue -h -o %A 2>/dev/null || true)
        if [[ -n "$jobs" ]]; then
            # shellcheck disable=SC2086  # one job id per word
            SLURM_CONF="$dir/slurm.conf" scancel $jobs 2>/dev/null || true
            for _ in $(seq 200); do
                [[ -z "$(SLURM_CONF="$dir/slurm.conf" squeue -h -o %A 2>/dev/null)" ]] && break
                sleep 0.1
            done
        fi
    fi
    # Then one daemon at a time, slurmd first: a job step ending during the stop reports to
    # slurmctld through munge, and with munged gone first it hangs on, keeping slurmd alive with it.
    for name in slurmd slurmctld munged; do
        pid=$(cat "$dir/$name.pid" 2>/dev/null || true)
        if [[ -n "$pid" ]]; then
            kill "$pid" 2>/dev/null || true
            for _ in $(seq 50); do  # wait until it is gone (ports, sockets freed)
                kill -0 "$pid" 2>/dev/null || break
                sleep 0.1
            done
            if kill -0 "$pid" 2>/dev/null; then kill -KILL "$pid" || true; fi  # still there after 5 s
        fi
        rm -f "$dir/$name.pid"
    done
}

case "$action" in
stop) stop; exit 0 ;;
start) ;;
*) usage ;;
esac

for tool in munged slurmctld slurmd sbatch scontrol; do
    if ! command -v "$tool" >/dev/null; then
        echo "SLURM is not installed here ($tool is missing): apt-get install -y slurm-wlm munge" >&2
        exit 3
    fi
done
if [[ $(id -u) -ne 0 ]]; then
    echo "a SLURM node needs root (slurmd starts jobs as their users); this is uid $(id -u)" >&2
    exit 3
fi

stop  # a cluster left running in DIR by an earlier start
mkdir -p "$dir/state" "$dir/spool" "$dir/munge"
chmod 700 "$dir/munge"

# munge: its own key, socket and files, beside any munged the machine runs.
dd if=/dev/urandom of="$dir/munge/munge.key" bs=1024 count=1 status=none
chmod 400 "$dir/munge/munge.key"
munged --force --key-file="$dir/munge/munge.key" --socket="$dir/munge/socket" \
    --pid-file="$dir/munged.pid" --log-file="$dir/munged.log" --seed-file="$dir/munge/seed"

free_port() {
    python3 -c 'import socket; s = socket.socket(); s.bind(("127.0.0.1", 0)); print(s.getsockname()[1])'
}
node=$(hostname -s)
cpus=$(nproc)
memory=$(( $(awk '/MemTotal/ {print $2}' /proc/meminfo) / 1024 * 3 / 4 ))  # MiB, 3/4 of it

# proctrack/linuxproc and task/none: no cgroup setup needed (containers often lack it). Without
# accounting (slurmdbd needs a database) `sacct` does not answer; submitit then reads a job's end
# from its result file. CR_CPU: jobs share the node by CPUs.
cat >"$dir/slurm.conf" <<EOF
ClusterName=capvector-test
SlurmctldHost=$node(127.0.0.1)
SlurmctldPort=$(free_port)
SlurmdPort=$(free_port)
SlurmUser=root
SlurmdUser=root
AuthType=auth/munge
CredType=cred/munge
AuthInfo=socket=$dir/munge/socket
StateSaveLocation=$dir/state
SlurmdSpoolDir=$dir/spool/%n
SlurmctldPidFile=$dir/slurmctld.pid
SlurmdPidFile=$dir/slurmd.pid
SlurmctldLogFile=$dir/slurmctld.log
SlurmdLogFile=$dir/slurmd.log
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
MpiDefault=none
SchedulerType=sched/backfill
SelectType=select/cons_tres
SelectTypeParameters=CR_CPU
ReturnToService=2
AccountingStorageType=accounting_storage/none
JobAcctGatherType=jobacct_gather/none
JobCompType=jobcomp/none
SlurmctldTimeout=30
SlurmdTimeout=30
InactiveLimit=0
MinJobAge=300
KillWait=10
NodeName=$node NodeAddr=127.0.0.1 CPUs=$cpus RealMemory=$memory State=UNKNOWN
PartitionName=debug Nodes=ALL Default=YES MaxTime=INFINITE State=UP
EOF

export SLURM_CONF="$dir/slurm.conf"
slurmctld -f "$SLURM_CONF"
slurmd -f "$SLURM_CONF" -N "$node"

for _ in $(seq 100); do  # the node registers within a few seconds
    state=$(sinfo -h -N -o %t 2>/dev/null | head -1 || true)
    if [[ "$state" == idle* ]]; then
        echo "export SLURM_CONF=$SLURM_CONF"
        exit 0
    fi
    sleep 0.2
done
echo "the SLURM node did not come up (state: ${state:-none}); logs:" >&2
tail -n 20 "$dir/slurmctld.log" "$dir/slurmd.log" >&2 || true
stop
exit 1
