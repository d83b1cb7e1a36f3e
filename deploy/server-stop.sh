#!/usr/bin/env bash
# Stop the worker and the server that deploy/server.sh started (their process groups, from the pid files).
set -uo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
export PREFECT_HOME="${PREFECT_HOME:-$ROOT/runs/.prefect}"
STATE="$PREFECT_HOME/bat3r-server"

stop() {  # $1: name, $2: pid file
    local pidfile="$2" pid
    [[ -f "$pidfile" ]] || { echo "$1: not started by deploy/server.sh"; return 0; }
    pid="$(cat "$pidfile")"
    if kill -0 "$pid" 2>/dev/null; then
        kill -INT -- "-$pid" 2>/dev/null || kill -INT "$pid" 2>/dev/null
        for _ in $(seq 1 40); do kill -0 "$pid" 2>/dev/null || break; sleep 0.5; done
        if kill -0 "$pid" 2>/dev/null; then
            kill -KILL -- "-$pid" 2>/dev/null || kill -KILL "$pid" 2>/dev/null
        fi
        echo "$1: stopped (pid $pid)"
    else
        echo "$1: was not running"
    fi
    rm -f "$pidfile"
}

stop worker "$STATE/worker.pid"
stop server "$STATE/server.pid"
