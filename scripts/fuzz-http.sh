#!/usr/bin/env bash
# OpenAPI-driven fuzzing of the HTTP API with schemathesis (PyPI): starts `posematch serve` on a
# throw-away template directory (embedded default weights), lets schemathesis generate valid
# and invalid requests for every operation in /openapi.json, and fails on any 5xx answer, any
# status the document does not list, and any answer outside the document's schemas.
#
#   scripts/fuzz-http.sh [path/to/posematch] [max examples per operation, default 200]
#
# .ci/run runs it after `cargo test` (which builds target/debug/posematch). Needs python3 with
# schemathesis (`python3 -m pip install schemathesis`).
set -euo pipefail
cd "$(dirname "$0")/.."
binary="${1:-target/debug/posematch}"
examples="${2:-200}"
work="$(mktemp -d)"
port="$(python3 -c 'import socket; s = socket.socket(); s.bind(("127.0.0.1", 0)); print(s.getsockname()[1])')"
"$binary" serve --listen 127.0.0.1:0 --http-listen "127.0.0.1:$port" \
  --template-dir "$work/templates" 2>"$work/server.log" &
server=$!
cleanup() {
  kill "$server" 2>/dev/null || true
  wait "$server" 2>/dev/null || true
  rm -rf "$work"
}
trap cleanup EXIT
# Ready once the API answers (the model loads after the ports are bound).
for _ in $(seq 1 600); do
  if python3 -c "import urllib.request, sys; urllib.request.urlopen('http://127.0.0.1:$port/v1/templates', timeout=2)" 2>/dev/null; then
    break
  fi
  if ! kill -0 "$server" 2>/dev/null; then
    echo "posematch serve ended before it was ready:" >&2
    cat "$work/server.log" >&2
    exit 1
  fi
  sleep 0.2
done
# scripts/fuzz_hooks.py: generated requests go without a grpc-timeout header (a deadline that
# passes is a 504 by design, not a fault).
PYTHONPATH="scripts${PYTHONPATH:+:$PYTHONPATH}" SCHEMATHESIS_HOOKS=fuzz_hooks \
schemathesis run "http://127.0.0.1:$port/openapi.json" \
  --checks not_a_server_error,status_code_conformance,content_type_conformance,response_schema_conformance \
  --max-examples "$examples" --seed 7 --workers 1 --request-timeout 60 --generation-database none \
  --phases examples,coverage,fuzzing,stateful --no-color
if ! kill -0 "$server" 2>/dev/null; then
  echo "posematch serve did not survive the fuzzing:" >&2
  tail -50 "$work/server.log" >&2
  exit 1
fi
echo "fuzzing found no 5xx and no answer outside the document"
