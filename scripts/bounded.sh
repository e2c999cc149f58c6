#!/usr/bin/env bash
# bounded.sh SECONDS COMMAND...: runs COMMAND; if it is still running after SECONDS, prints what every
# process under it is doing (process tree, kernel wait channel, and with gdb installed each native
# process's thread backtraces), then kills them all and exits 124.
#
# `make test` runs its test commands under this so that a test that hangs ends the run within a bound
# and says where it hung, instead of holding CI until its 90 minutes are up with nothing to read.
# coreutils' `timeout` kills without saying anything, which is why this is written out here.
set -uo pipefail
limit=$1
shift
setsid "$@" &
leader=$!
# The command's process group is its own (setsid): the kill below reaches the test binaries and the
# simulator workers they started, never make or this shell.
trap 'kill -TERM -- -"$leader" 2>/dev/null' INT TERM
waited=0
while kill -0 "$leader" 2>/dev/null && [ "$waited" -lt "$limit" ]; do
    sleep 1
    waited=$((waited + 1))
done
if ! kill -0 "$leader" 2>/dev/null; then
    wait "$leader"
    exit $?
fi
echo "bounded.sh: '$*' still running after $limit s; what each of its processes is doing:" >&2
pids=$(ps -o pid= -s "$leader" 2>/dev/null || true)
ps -o pid,ppid,stat,etime,time,wchan:24,args -s "$leader" >&2 || true
for pid in $pids; do
    exe=$(readlink "/proc/$pid/exe" 2>/dev/null) || continue
    case "$exe" in
        */make | */bash | */sh | */cargo) continue ;;
    esac
    echo "--- pid $pid ($exe): threads and their wait channels" >&2
    for task in /proc/"$pid"/task/*; do
        echo "  $(cat "$task/comm" 2>/dev/null) $(cat "$task/wchan" 2>/dev/null)" >&2
    done
    if command -v gdb > /dev/null; then
        timeout 60 gdb -batch -nx -ex "thread apply all bt 25" -p "$pid" 2>&1 \
            | grep -E '^(Thread|#)' | grep -v '/rustc/' >&2 || true
    fi
done
kill -KILL -- -"$leader" 2>/dev/null
wait "$leader" 2>/dev/null
exit 124
