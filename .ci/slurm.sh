#!/usr/bin/env bash
# A single-node SLURM cluster (Debian's slurm-wlm 22.05 and munge) for the SLURM tests of
# tests/slurm.rs, after ../shared/recipes/slurm-single-node.md.
#
#   .ci/slurm.sh start [DIR]   write DIR/slurm.conf, start munged (unless one answers),
#                              slurmctld and slurmd; wait until sinfo shows the node idle
#   .ci/slurm.sh stop  [DIR]   cancel the cluster's jobs, stop slurmd, slurmctld and the munged
#                              this script started
#   .ci/slurm.sh env   [DIR]   print the export line the clients need (SLURM_CONF)
#
# DIR (default target/slurm) holds the configuration, state, spool, logs and pid files; nothing is
# written to /etc/slurm. Clients (sbatch, squeue, scontrol, sinfo) find the cluster through
# SLURM_CONF=DIR/slurm.conf; tests/slurm.rs uses that variable, else target/slurm/slurm.conf.
# The daemons run as root (SlurmUser=root), so start and stop need root. Every wait is bounded.
set -euo pipefail

cmd=${1:-}
root=$(cd "$(dirname "$0")/.." && pwd)
dir=${2:-$root/target/slurm}
mkdir -p "$dir"
dir=$(cd "$dir" && pwd)
conf=$dir/slurm.conf

die() {
  echo "slurm.sh: $*" >&2
  exit 1
}

# Waits up to $1 seconds for the command in the remaining arguments to succeed.
wait_for() {
  local limit=$1
  shift
  local start=$SECONDS
  until "$@" >/dev/null 2>&1; do
    ((SECONDS - start < limit)) || return 1
    sleep 0.5
  done
}

alive() { [ -f "$1" ] && kill -0 "$(cat "$1")" 2>/dev/null; }

# Sends SIGTERM to the daemon of pid file $1, waits up to 20 s, then SIGKILL.
stop_pid() {
  local f=$1
  alive "$f" || {
    rm -f "$f"
    return 0
  }
  local pid
  pid=$(cat "$f")
  kill "$pid" 2>/dev/null || true
  if ! wait_for 20 bash -c "! kill -0 $pid"; then
    kill -9 "$pid" 2>/dev/null || true
  fi
  rm -f "$f"
}

munge_ok() { munge -n | unmunge; }

start() {
  [ "$(id -u)" = 0 ] || die "start needs root (slurmd runs as root)"
  for c in munged munge unmunge slurmctld slurmd sinfo; do
    command -v "$c" >/dev/null 2>&1 || die "$c not found: apt-get install -y slurm-wlm munge"
  done
  if alive "$dir/ctld.pid" && alive "$dir/d.pid"; then
    echo "slurm.sh: already running in $dir"
    return 0
  fi
  mkdir -p "$dir/state" "$dir/spool" "$dir/log"

  # munge: the key and socket of the Debian package; a munged that answers is used as it is.
  if ! munge_ok >/dev/null 2>&1; then
    [ -f /etc/munge/munge.key ] || mungekey -c
    chown munge:munge /etc/munge/munge.key
    chmod 400 /etc/munge/munge.key
    mkdir -p /run/munge /var/log/munge /var/lib/munge
    chown munge:munge /run/munge /var/log/munge /var/lib/munge
    su -s /bin/sh munge -c /usr/sbin/munged ||
      die "munged did not start (see /var/log/munge/munged.log)"
    wait_for 10 munge_ok || die "munged does not answer (munge -n | unmunge)"
    # munged writes its pid file as the munge user; a copy in DIR says this script started it.
    cp /run/munge/munged.pid "$dir/munged.pid"
  fi

  local host cpus
  host=$(hostname -s)
  cpus=$(nproc)
  cat >"$conf" <<CONF
# Written by .ci/slurm.sh: a single-node cluster on 127.0.0.1 for the SLURM tests.
ClusterName=qemd-test
SlurmctldHost=$host(127.0.0.1)
SlurmUser=root
SlurmdUser=root
AuthType=auth/munge
MpiDefault=none
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
SchedulerType=sched/backfill
SelectType=select/cons_tres
SelectTypeParameters=CR_Core
StateSaveLocation=$dir/state
SlurmdSpoolDir=$dir/spool
SlurmctldLogFile=$dir/log/ctld.log
SlurmdLogFile=$dir/log/d.log
SlurmctldPidFile=$dir/ctld.pid
SlurmdPidFile=$dir/d.pid
ReturnToService=2
# A cancelled task gets SIGTERM, then SIGKILL after KillWait seconds.
KillWait=5
# Finished jobs stay visible to squeue and scontrol for 10 minutes (there is no accounting
# database, so sacct has nothing).
MinJobAge=600
NodeName=$host NodeAddr=127.0.0.1 CPUs=$cpus State=UNKNOWN
PartitionName=main Nodes=$host Default=YES MaxTime=INFINITE State=UP
CONF
  export SLURM_CONF=$conf
  # -c: a fresh cluster, no jobs carried over from an earlier run's state.
  slurmctld -c -f "$conf" || die "slurmctld did not start (see $dir/log/ctld.log)"
  slurmd -f "$conf" || die "slurmd did not start (see $dir/log/d.log)"
  idle() { sinfo -h -o %T | grep -qx idle; }
  if ! wait_for 60 idle; then
    sinfo >&2 || true
    tail -n 20 "$dir/log/ctld.log" "$dir/log/d.log" >&2 || true
    die "the node is not idle after 60 s"
  fi
  echo "slurm.sh: cluster up in $dir (export SLURM_CONF=$conf)"
  sinfo
}

stop() {
  export SLURM_CONF=$conf
  if alive "$dir/ctld.pid"; then
    scancel --full --quiet --user "$(id -un)" 2>/dev/null || true
    # Bounded: the jobs' steps are asked to end, then the daemons go regardless.
    wait_for 15 bash -c '[ -z "$(squeue -h -o %i 2>/dev/null)" ]' || true
  fi
  stop_pid "$dir/d.pid"
  stop_pid "$dir/ctld.pid"
  # Only the munged this script started (its pid copied at start), and only if it still runs.
  if [ -f "$dir/munged.pid" ]; then
    if [ "$(cat "$dir/munged.pid")" = "$(cat /run/munge/munged.pid 2>/dev/null)" ]; then
      stop_pid "$dir/munged.pid"
    fi
    rm -f "$dir/munged.pid"
  fi
  echo "slurm.sh: stopped ($dir)"
}

case $cmd in
start) start ;;
stop) stop ;;
env) echo "export SLURM_CONF=$conf" ;;
*) die "usage: $0 start|stop|env [DIR]" ;;
esac
