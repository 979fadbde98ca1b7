#!/bin/sh
# The hardened router: TLS only, every session logs in, access roles from acl.toml.
# Run from a folder holding pki/ (certs.sh), users.txt (mode 600) and acl.toml.
exec artrack router --listen tls/0.0.0.0:7447 \
    --tls-cert pki/router.pem --tls-key pki/router.key --tls-ca pki/ca.pem \
    --users users.txt --acl acl.toml "$@"
