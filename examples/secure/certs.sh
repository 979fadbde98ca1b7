#!/bin/sh
# A private CA and certificates for a secure artrack deployment (EC P-256, PEM), with openssl.
#
#   sh examples/secure/certs.sh DIR ROUTER_ADDRESS [CLIENT_NAME...]
#
# DIR/ca.pem, ca.key          the CA: ca.pem goes to every host, ca.key stays offline
# DIR/router.pem, router.key  the router's certificate, valid for ROUTER_ADDRESS (an IP or a DNS name)
# DIR/NAME.pem, NAME.key      one client certificate per NAME (its common name, for mutual TLS and acl.toml)
set -eu
dir=$1
router=$2
shift 2
days=${DAYS:-365}
mkdir -p "$dir"
cd "$dir"
umask 077
key() { openssl req -newkey ec -pkeyopt ec_paramgen_curve:prime256v1 -nodes "$@" 2>/dev/null; }
sign() {  # sign NAME COMMON_NAME EXTENSIONS (v3: webpki refuses v1 certificates)
    key -keyout "$1.key" -out "$1.csr" -subj "/CN=$2"
    printf '%s\n' "$3" > "$1.ext"
    openssl x509 -req -in "$1.csr" -CA ca.pem -CAkey ca.key -CAcreateserial -days "$days" \
        -out "$1.pem" -extfile "$1.ext" 2>/dev/null
    rm "$1.csr" "$1.ext"
}
key -x509 -keyout ca.key -out ca.pem -days "$days" -subj "/CN=artrack CA"
case $router in
    *[!0-9.]*) san="DNS:$router" ;;
    *) san="IP:$router" ;;
esac
sign router "$router" "extendedKeyUsage=serverAuth,clientAuth
subjectAltName=$san"
for name in "$@"; do
    sign "$name" "$name" "extendedKeyUsage=clientAuth"
done
chmod 644 ./*.pem
