#!/usr/bin/env bash
# Makes a certificate authority and one certificate per host for the zenoh bridge's mutual
# TLS (a graph's `hosts.NAME.zenoh.tls`). Each host's certificate has the host name as its
# common name (what `allow:` lists) and the given addresses as subject names (what the other
# hosts connect to).
#   tools/scripts/make-certs.sh DIR robot=10.0.0.1 base=10.0.0.2,base.local
# writes DIR/ca.pem, DIR/ca.key and DIR/NAME.pem, DIR/NAME.key for each host. Test use: the
# keys are unencrypted and the CA signs for 30 days.
set -euo pipefail
if [ $# -lt 2 ]; then
    echo "usage: $0 DIR NAME=ADDRESS[,ADDRESS...] ..." >&2
    exit 2
fi
command -v openssl >/dev/null || { echo "$0: needs openssl (apt-get install -y openssl)" >&2; exit 2; }
dir=$1
shift
mkdir -p "$dir"
openssl req -x509 -newkey rsa:2048 -nodes -days 30 -subj "/CN=gprflow test CA" \
    -keyout "$dir/ca.key" -out "$dir/ca.pem" 2>/dev/null
for spec in "$@"; do
    name=${spec%%=*}
    addresses=${spec#*=}
    san=""
    IFS=',' read -ra list <<<"$addresses"
    for a in "${list[@]}"; do
        if [[ $a =~ ^[0-9.]+$ || $a == *:* ]]; then san+="IP:$a,"; else san+="DNS:$a,"; fi
    done
    openssl req -newkey rsa:2048 -nodes -subj "/CN=$name" \
        -keyout "$dir/$name.key" -out "$dir/$name.csr" 2>/dev/null
    printf 'subjectAltName=%s\nbasicConstraints=CA:FALSE\nkeyUsage=digitalSignature,keyEncipherment\nextendedKeyUsage=serverAuth,clientAuth\n' \
        "${san%,}" >"$dir/$name.ext"
    openssl x509 -req -in "$dir/$name.csr" -CA "$dir/ca.pem" -CAkey "$dir/ca.key" -CAcreateserial \
        -days 30 -extfile "$dir/$name.ext" -out "$dir/$name.pem" 2>/dev/null
    rm -f "$dir/$name.csr" "$dir/$name.ext"
done
rm -f "$dir/ca.srl"
