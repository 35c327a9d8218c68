#!/usr/bin/env bash
# Make a private CA and the certificates for TLS between an overtake router and its clients.
#
#   scripts/make-certs.sh DIR [HOST ...]
#
# DIR/ca.pem                      the CA certificate: every process gets it (--tls-root-ca)
# DIR/ca.key                      the CA's key: keep it off the machines, it signs certificates
# DIR/router.pem, router.key      the router's certificate for HOST ... (the names and addresses
#                                 clients connect to; default: localhost 127.0.0.1)
# DIR/client.pem, client.key      a client certificate, for mutual TLS (--tls-mtls)
#
# Elliptic-curve keys (P-256), valid for 365 days (OVERTAKE_CERT_DAYS). tests/e2e/test_deploy_tls.py
# runs this script; docs/remote-hosts.md shows how the files are used.
set -euo pipefail

if [[ $# -lt 1 ]]; then
    echo "usage: $0 DIR [HOST ...]" >&2
    exit 2
fi
dir=$1
shift
hosts=("$@")
if [[ ${#hosts[@]} -eq 0 ]]; then
    hosts=(localhost 127.0.0.1)
fi
days=${OVERTAKE_CERT_DAYS:-365}
mkdir -p "$dir"
cd "$dir"
umask 077   # the keys are readable by their owner only

# subjectAltName: the router's certificate must name every host or address clients dial
# (Zenoh checks it unless told --no-tls-verify-name).
san=""
for host in "${hosts[@]}"; do
    if [[ $host =~ ^[0-9.]+$ || $host == *:* ]]; then
        san+="IP:$host,"
    else
        san+="DNS:$host,"
    fi
done
san=${san%,}

openssl req -x509 -newkey ec -pkeyopt ec_paramgen_curve:prime256v1 -nodes \
    -keyout ca.key -out ca.pem -days "$days" -subj "/CN=overtake CA" \
    -addext "basicConstraints=critical,CA:TRUE" \
    -addext "keyUsage=critical,keyCertSign,cRLSign" 2>/dev/null

sign() {  # sign NAME CN EXTENDED_KEY_USAGE [SAN]
    local name=$1 cn=$2 usage=$3 alt=${4:-}
    openssl req -newkey ec -pkeyopt ec_paramgen_curve:prime256v1 -nodes \
        -keyout "$name.key" -out "$name.csr" -subj "/CN=$cn" 2>/dev/null
    {
        echo "basicConstraints=critical,CA:FALSE"
        echo "keyUsage=critical,digitalSignature"
        echo "extendedKeyUsage=$usage"
        if [[ -n $alt ]]; then echo "subjectAltName=$alt"; fi
    } > "$name.ext"
    openssl x509 -req -in "$name.csr" -CA ca.pem -CAkey ca.key -CAcreateserial \
        -out "$name.pem" -days "$days" -extfile "$name.ext" 2>/dev/null
    rm -f "$name.csr" "$name.ext"
}

# serverAuth and clientAuth: a router also connects out to other routers with its identity.
sign router "${hosts[0]}" serverAuth,clientAuth "$san"
sign client "overtake client" clientAuth
rm -f ca.srl
chmod 644 ca.pem router.pem client.pem
echo "made $dir/ca.pem, router.pem (for ${hosts[*]}), client.pem and their keys"
