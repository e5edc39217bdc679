#!/usr/bin/env bash
# Make a throw-away CA and a server certificate for TLS tests and local trials (never for production).
# Usage: scripts/make-test-certs.sh DIR [HOSTNAME]
#   DIR/ca.pem ca.key       the test certificate authority (clients trust ca.pem: --tls-ca)
#   DIR/server.pem server.key  certificate for HOSTNAME (default localhost) and 127.0.0.1 (--tls-cert/--tls-key)
set -euo pipefail
dir=${1:?usage: make-test-certs.sh DIR [HOSTNAME]}
host=${2:-localhost}
mkdir -p "$dir"
cd "$dir"
openssl ecparam -name prime256v1 -genkey -noout -out ca.key
openssl req -x509 -new -key ca.key -sha256 -days 30 -subj "/CN=hybridloc test CA" -out ca.pem
openssl ecparam -name prime256v1 -genkey -noout -out server.key
openssl req -new -key server.key -subj "/CN=$host" -out server.csr
printf "subjectAltName=DNS:%s,IP:127.0.0.1\nbasicConstraints=CA:FALSE\nkeyUsage=digitalSignature,keyEncipherment\nextendedKeyUsage=serverAuth\n" "$host" > server.ext
openssl x509 -req -in server.csr -CA ca.pem -CAkey ca.key -CAcreateserial -days 30 -sha256 -extfile server.ext -out server.pem
rm -f server.csr server.ext ca.srl
echo "test CA and server certificate for $host in $dir"
