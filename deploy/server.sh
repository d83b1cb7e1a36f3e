#!/usr/bin/env bash
# Start a local Prefect server on 127.0.0.1, create the process work pool, deploy deploy/prefect.yaml, start a
# worker, and print the dashboard URL. `deploy/server-stop.sh` stops what this started (pid files).
#
# Settings (environment): BAT3R_PREFECT_PORT (default 4200), BAT3R_WORK_POOL (default bat3r, the pool named in
# deploy/prefect.yaml), PREFECT_HOME (default <project>/runs/.prefect), PY (default <project>/.venv/bin/python).
set -euo pipefail
set -m  # background jobs get their own process group: the worker then stops on a signal, and stop kills the group

ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$ROOT"
PY="${PY:-$ROOT/.venv/bin/python}"
PORT="${BAT3R_PREFECT_PORT:-4200}"
POOL="${BAT3R_WORK_POOL:-bat3r}"
export PREFECT_HOME="${PREFECT_HOME:-$ROOT/runs/.prefect}"
export PREFECT_SERVER_ANALYTICS_ENABLED=false
export PREFECT_SERVER_API_HOST=127.0.0.1
export PREFECT_SERVER_API_PORT="$PORT"
export PREFECT_API_URL="http://127.0.0.1:$PORT/api"
export PREFECT_WORKER_QUERY_SECONDS="${PREFECT_WORKER_QUERY_SECONDS:-5}"
STATE="$PREFECT_HOME/bat3r-server"
mkdir -p "$STATE"
prefect() { "$PY" -m prefect "$@"; }

alive() { [[ -f "$1" ]] && kill -0 "$(cat "$1")" 2>/dev/null; }

if alive "$STATE/server.pid"; then
    echo "a server started by this script is already running (pid $(cat "$STATE/server.pid")); stop it with deploy/server-stop.sh"
else
    prefect server start >"$STATE/server.log" 2>&1 &
    echo $! >"$STATE/server.pid"
    echo "server: pid $(cat "$STATE/server.pid"), log $STATE/server.log"
fi

for _ in $(seq 1 120); do
    if "$PY" -c "import urllib.request,sys; urllib.request.urlopen('$PREFECT_API_URL/health', timeout=2)" 2>/dev/null; then
        break
    fi
    if ! alive "$STATE/server.pid"; then
        echo "the server exited; last lines of $STATE/server.log:" >&2
        tail -n 30 "$STATE/server.log" >&2
        exit 1
    fi
    sleep 1
done
"$PY" -c "import urllib.request; urllib.request.urlopen('$PREFECT_API_URL/health', timeout=5)" \
    || { echo "the server did not become healthy at $PREFECT_API_URL" >&2; exit 1; }

if ! prefect work-pool inspect "$POOL" >/dev/null 2>&1; then
    prefect work-pool create "$POOL" --type process >/dev/null
fi
# One GPU task per GPU across every flow run of this server: a tag concurrency limit on the GPU tasks' tag.
if command -v nvidia-smi >/dev/null 2>&1; then
    NGPU="$(nvidia-smi -L 2>/dev/null | grep -c '^GPU' || true)"
    if [[ "${NGPU:-0}" -gt 0 ]]; then
        prefect concurrency-limit create bat3r-gpu "$NGPU" >/dev/null && echo "tag limit bat3r-gpu = $NGPU"
    fi
fi
prefect --no-prompt deploy --all --prefect-file deploy/prefect.yaml >"$STATE/deploy.log" 2>&1 \
    || { cat "$STATE/deploy.log" >&2; exit 1; }
grep -o "Deployment '[^']*' successfully created[^.]*" "$STATE/deploy.log" || true

if alive "$STATE/worker.pid"; then
    echo "worker already running (pid $(cat "$STATE/worker.pid"))"
else
    prefect worker start --pool "$POOL" --type process >"$STATE/worker.log" 2>&1 &
    echo $! >"$STATE/worker.pid"
    echo "worker: pid $(cat "$STATE/worker.pid"), log $STATE/worker.log"
fi

echo "Prefect dashboard: http://127.0.0.1:$PORT"
echo "API: export PREFECT_API_URL=$PREFECT_API_URL   then e.g.: prefect deployment run bootstrap/toy --watch"
