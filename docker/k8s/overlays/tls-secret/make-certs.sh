#!/usr/bin/env bash
# The files overlays/tls-secret makes the radserve-tls Secret from, in this directory: a CA (ca.crt;
# its key ca.key stays here, out of the cluster) and the servers' certificate (tls.crt, tls.key),
# ECDSA P-256, valid for a year, for each pod's name under the headless Service (short and in
# full). Usage: make-certs.sh [REPLICAS (3)] [NAMESPACE (radserve)]
set -euo pipefail
cd "$(dirname "$0")"
replicas=${1:-3} namespace=${2:-radserve}
names=()
for ((i = 0; i < replicas; i++)); do
    names+=("DNS:radserve-$i.radserve" "DNS:radserve-$i.radserve.$namespace.svc"
            "DNS:radserve-$i.radserve.$namespace.svc.cluster.local")
done
sans=$(IFS=,; echo "${names[*]}")
umask 077
openssl req -x509 -new -newkey ec -pkeyopt ec_paramgen_curve:P-256 -nodes -days 3650 \
    -subj "/CN=radserve-ca" -keyout ca.key -out ca.crt \
    -addext "basicConstraints=critical,CA:TRUE" -addext "keyUsage=critical,keyCertSign,cRLSign" 2> /dev/null
openssl req -new -newkey ec -pkeyopt ec_paramgen_curve:P-256 -nodes -subj "/CN=radserve" \
    -keyout tls.key -out tls.csr 2> /dev/null
openssl x509 -req -in tls.csr -CA ca.crt -CAkey ca.key -CAcreateserial -days 365 -out tls.crt \
    -extfile <(printf 'subjectAltName=%s\nextendedKeyUsage=serverAuth\nkeyUsage=critical,digitalSignature\n' "$sans") 2> /dev/null
rm -f tls.csr ca.srl
echo "make-certs.sh: ca.crt, tls.crt, tls.key for ${#names[@]} names (ca.key: keep it, out of the cluster)"
