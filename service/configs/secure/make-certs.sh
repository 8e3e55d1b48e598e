#!/bin/sh
# Make a private CA and the certificates of the secure example (docs/SECURITY.md), with openssl:
#   sh service/configs/secure/make-certs.sh certs                 # ca + service, simulator, reader
#   sh service/configs/secure/make-certs.sh certs ops=fednav-ops  # one more: certs/ops.pem, CN=fednav-ops
# A CA already in the folder (ca.pem, ca-key.pem) is reused. EC P-256 keys (PKCS#8), 365 days.
# The service certificate names 127.0.0.1 and localhost (SAN): clients verify the name they connect
# to; for another host add it to SAN below. Keep ca-key.pem offline; hand each process only its own
# key, its certificate and ca.pem.
set -eu
out=${1:?usage: make-certs.sh OUT_DIR [name=CN ...]}
shift
days=${DAYS:-365}
mkdir -p "$out"
cd "$out"
if [ ! -f ca.pem ]; then
  openssl req -x509 -newkey ec -pkeyopt ec_paramgen_curve:P-256 -nodes -days "$days" \
    -subj "/CN=fednav-ca" -keyout ca-key.pem -out ca.pem \
    -addext "basicConstraints=critical,CA:TRUE" -addext "keyUsage=critical,keyCertSign,cRLSign"
fi
leaf() {  # leaf NAME COMMON_NAME -> NAME.pem, NAME-key.pem signed by ca.pem
  openssl req -new -newkey ec -pkeyopt ec_paramgen_curve:P-256 -nodes -subj "/CN=$2" \
    -keyout "$1-key.pem" -out "$1.csr"
  printf '%s\n' "basicConstraints=critical,CA:FALSE" "keyUsage=critical,digitalSignature" \
    "extendedKeyUsage=serverAuth,clientAuth" "subjectAltName=DNS:localhost,IP:127.0.0.1" > "$1.ext"
  openssl x509 -req -in "$1.csr" -CA ca.pem -CAkey ca-key.pem -CAcreateserial -days "$days" \
    -extfile "$1.ext" -out "$1.pem"
  rm -f "$1.csr" "$1.ext"
  chmod 600 "$1-key.pem"
}
if [ $# -eq 0 ]; then
  set -- service=fednav-service simulator=fednav-simulator reader=fednav-reader
fi
for spec in "$@"; do
  leaf "${spec%%=*}" "${spec#*=}"
done
chmod 600 ca-key.pem
