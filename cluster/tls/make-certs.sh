#!/usr/bin/env bash
# Make a private certificate authority and one key + certificate per role (scheduler, worker,
# client) for a dask cluster reached over a network, plus a dask configuration file using them.
#   usage: cluster/tls/make-certs.sh [OUTPUT_DIR] [SUBJECT_ALT_NAMES]
#   e.g.   cluster/tls/make-certs.sh /etc/tubeid/tls "DNS:scheduler,DNS:localhost,IP:127.0.0.1"
# Then on every machine (scheduler, workers, the one running `tubeid run`):
#   export DASK_CONFIG=OUTPUT_DIR        # dask reads OUTPUT_DIR/dask-tls.yaml
# and use tls:// addresses (tubeid run --scheduler tls://HOST:8786). Copy OUTPUT_DIR to the other
# machines over a channel you trust; keep ca-key.pem offline (it is only needed to sign new certs).
set -euo pipefail
out="${1:-./tls-certs}"
san="${2:-DNS:localhost,IP:127.0.0.1}"
days="${TUBEID_TLS_DAYS:-365}"
mkdir -p "$out"
out="$(cd "$out" && pwd)"
umask 077
openssl req -x509 -newkey rsa:3072 -nodes -days "$days" -subj "/CN=tubeid-dask-ca" \
  -keyout "$out/ca-key.pem" -out "$out/ca.pem" 2>/dev/null
for role in scheduler worker client; do
  openssl req -newkey rsa:3072 -nodes -subj "/CN=tubeid-$role" \
    -keyout "$out/$role-key.pem" -out "$out/$role.csr" 2>/dev/null
  printf 'subjectAltName=%s\nextendedKeyUsage=serverAuth,clientAuth\n' "$san" > "$out/$role.ext"
  openssl x509 -req -in "$out/$role.csr" -CA "$out/ca.pem" -CAkey "$out/ca-key.pem" -CAcreateserial \
    -days "$days" -extfile "$out/$role.ext" -out "$out/$role.pem" 2>/dev/null
  rm -f "$out/$role.csr" "$out/$role.ext"
done
sed "s#@DIR@#$out#g" "$(dirname "$0")/dask-tls.yaml.in" > "$out/dask-tls.yaml"
echo "certificates and $out/dask-tls.yaml written; export DASK_CONFIG=$out"
