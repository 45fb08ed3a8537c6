#!/usr/bin/env bash
# Make a private certificate authority and one key + certificate per role (scheduler, worker,
# client) for a dask cluster reached over a network, plus a dask configuration file using them.
#   usage: cluster/tls/make-certs.sh [OUTPUT_DIR] [SUBJECT_ALT_NAMES] [CA_DIR]
#   e.g.   cluster/tls/make-certs.sh /etc/tubeid/tls "DNS:scheduler,DNS:localhost,IP:127.0.0.1" ~/tubeid-ca
# OUTPUT_DIR (default ./tls-certs) receives what the cluster's machines need: ca.pem (the CA's
# certificate, public), <role>.pem and <role>-key.pem, and dask-tls.yaml. It never holds the CA's
# private key: that goes to CA_DIR (default OUTPUT_DIR.ca, a sibling, never inside OUTPUT_DIR), which
# is needed only to sign new certificates: keep it offline, never mount or copy it to the cluster.
# Run again with the same CA_DIR and a new OUTPUT_DIR to issue new role certificates from the same CA.
# It never overwrites or deletes a file it did not write in this run: a file of OUTPUT_DIR it would
# write (ca.pem, <role>.pem, <role>-key.pem, dask-tls.yaml, its temporary <role>.csr/.ext) that already
# exists is refused before anything is written, as is a CA_DIR holding ca.pem or ca.srl without ca-key.pem.
# A run that fails removes the files of OUTPUT_DIR it wrote (a new CA in CA_DIR is kept, and reused).
# Then on every machine (scheduler, workers, the one running `tubeid run`):
#   export DASK_CONFIG=OUTPUT_DIR        # dask reads OUTPUT_DIR/dask-tls.yaml
# and use tls:// addresses (tubeid run --scheduler tls://HOST:8786). Copy OUTPUT_DIR to the other
# machines over a channel you trust.
set -euo pipefail
umask 077                                   # every directory and file below: owner only
quiet() {                                   # run openssl; show its messages only if it fails
  local log
  if ! log="$("$@" 2>&1)"; then
    echo "make-certs.sh: $1 failed:" >&2
    echo "$log" >&2
    exit 1
  fi
}
out="${1:-./tls-certs}"
san="${2:-DNS:localhost,IP:127.0.0.1}"
out_abs="$(mkdir -p "$out" && cd "$out" && pwd -P)"
ca="${3:-$out_abs.ca}"
days="${TUBEID_TLS_DAYS:-365}"
if [ -e "$ca" ] || [ -L "$ca" ]; then        # an existing CA_DIR (or a symlink): where the key would really go
  ca_abs="$(cd "$ca" && pwd -P)"
else
  ca_abs="$(mkdir -p "$(dirname "$ca")" && cd "$(dirname "$ca")" && pwd -P)/$(basename "$ca")"  # not created yet
fi
case "$ca_abs/" in
  "$out_abs/"*)
    echo "make-certs.sh: CA_DIR $ca_abs is OUTPUT_DIR or inside it; the CA key must not go where the" \
         "cluster's files go" >&2
    exit 2 ;;
esac
case "$out_abs/" in
  "$ca_abs/"*)
    echo "make-certs.sh: OUTPUT_DIR $out_abs is inside CA_DIR $ca_abs; mounting it would not expose the CA" \
         "key, but keep them apart so that copying one never copies the other" >&2
    exit 2 ;;
esac
roles="scheduler worker client"
mine=(ca.pem dask-tls.yaml)                 # every file this script writes into OUTPUT_DIR
for role in $roles; do mine+=("$role.pem" "$role-key.pem" "$role.csr" "$role.ext"); done
if [ -e "$out_abs/ca-key.pem" ]; then
  echo "make-certs.sh: $out_abs/ca-key.pem exists (made by an earlier version of this script): move it to" \
       "CA_DIR ($ca_abs) and keep it offline, then run again" >&2
  exit 2
fi
clash=()
for name in "${mine[@]}"; do
  if [ -e "$out_abs/$name" ] || [ -L "$out_abs/$name" ]; then clash+=("$name"); fi
done
if [ ${#clash[@]} -gt 0 ]; then
  echo "make-certs.sh: OUTPUT_DIR $out_abs already holds ${clash[*]}: this script never overwrites a file;" \
       "give a new OUTPUT_DIR (with the same CA_DIR to issue more certificates from the same CA)" >&2
  exit 2
fi
if [ ! -f "$ca_abs/ca-key.pem" ]; then
  for name in ca.pem ca.srl; do
    if [ -e "$ca_abs/$name" ] || [ -L "$ca_abs/$name" ]; then
      echo "make-certs.sh: CA_DIR $ca_abs holds $name but no ca-key.pem: a new CA would overwrite it;" \
           "give the CA_DIR that holds this CA's key, or a new one" >&2
      exit 2
    fi
  done
fi
mkdir -p "$ca_abs"
written=()                                  # the files of OUTPUT_DIR this run wrote, removed if it fails
finish() {
  local status=$?
  for role in $roles; do rm -f "$out_abs/$role.csr" "$out_abs/$role.ext"; done
  if [ "$status" -ne 0 ]; then
    for name in ${written[@]+"${written[@]}"}; do rm -f "$out_abs/$name"; done
  fi
}
trap finish EXIT
if [ -f "$ca_abs/ca-key.pem" ]; then
  echo "reusing the CA in $ca_abs"
else
  quiet openssl req -x509 -newkey rsa:3072 -nodes -days "$days" -subj "/CN=tubeid-dask-ca" \
    -keyout "$ca_abs/ca-key.pem" -out "$ca_abs/ca.pem"
fi
written+=(ca.pem)
cp "$ca_abs/ca.pem" "$out_abs/ca.pem"
for role in $roles; do
  written+=("$role-key.pem" "$role.pem")
  quiet openssl req -newkey rsa:3072 -nodes -subj "/CN=tubeid-$role" \
    -keyout "$out_abs/$role-key.pem" -out "$out_abs/$role.csr"
  printf 'subjectAltName=%s\nextendedKeyUsage=serverAuth,clientAuth\n' "$san" > "$out_abs/$role.ext"
  quiet openssl x509 -req -in "$out_abs/$role.csr" -CA "$ca_abs/ca.pem" -CAkey "$ca_abs/ca-key.pem" \
    -CAserial "$ca_abs/ca.srl" -CAcreateserial -days "$days" -extfile "$out_abs/$role.ext" \
    -out "$out_abs/$role.pem"
done
written+=(dask-tls.yaml)
sed "s#@DIR@#$out_abs#g" "$(dirname "$0")/dask-tls.yaml.in" > "$out_abs/dask-tls.yaml"
echo "certificates and $out_abs/dask-tls.yaml written; export DASK_CONFIG=$out_abs"
echo "the CA key is in $ca_abs: keep it offline (needed only to issue new certificates), never in the cluster"
