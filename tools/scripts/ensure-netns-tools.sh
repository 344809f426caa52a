#!/usr/bin/env bash
# The distributed tests (tests/distributed.rs) run each host in a network namespace of its
# own (`ip netns`, as root) and make TLS certificates with openssl: installs iproute2 and
# openssl from Debian's packages where they are missing.
set -euo pipefail
missing=()
command -v ip >/dev/null || missing+=(iproute2)
command -v openssl >/dev/null || missing+=(openssl)
if [ ${#missing[@]} -gt 0 ]; then
    if [ "$(id -u)" != 0 ]; then
        echo "$0: needs ${missing[*]} (and root for the network namespaces)" >&2
        exit 1
    fi
    apt-get update -qq
    DEBIAN_FRONTEND=noninteractive apt-get install -y -qq "${missing[@]}" >/dev/null
fi
