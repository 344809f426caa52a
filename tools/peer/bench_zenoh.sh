#!/usr/bin/env bash
# zenoh next to iceoryx2 on one host: `gprflow-bench ipc` with a zenoh partner in a second
# network namespace, joined to the first by a veth pair (10.77.50.1/30 <-> 10.77.50.2/30).
# The driver, its iceoryx2 and Unix socket partner, and the driver's listening zenoh session
# run in the first namespace; the zenoh partner connects from the second over TCP. The
# report shows the zenoh rows ("zenoh tcp, 2 netns") next to the iceoryx2, socket and memcpy
# ones of the same run. Both namespaces are deleted on exit. Needs root (ip netns).
#
# usage: tools/peer/bench_zenoh.sh [gprflow-bench ipc options: --quick, --spin, --iterations N,
#                                   --messages N, --touch-stride B, --json FILE]
set -euo pipefail
cd "$(dirname "$0")/../.."
if [ "$(id -u)" != 0 ] || ! command -v ip >/dev/null; then
    echo "$0: needs root and iproute2 for the network namespaces (tools/scripts/ensure-netns-tools.sh)" >&2
    exit 1
fi
export CARGO_TARGET_DIR=${CARGO_TARGET_DIR:-target}
cargo build --release -p gprflow-bench
bench=$(realpath "$CARGO_TARGET_DIR/release/gprflow-bench")

# interface names have at most 15 characters: gzb + pid (up to 7 digits) + d/p
driver_ns=gfbz$$d
partner_ns=gfbz$$p
driver_if=gzb$$d
partner_if=gzb$$p
driver_addr=10.77.50.1
partner_addr=10.77.50.2
endpoint=tcp/$driver_addr:7447

cleanup() {
    # deleting a namespace deletes its end of the veth pair, and so the pair
    ip netns del "$driver_ns" 2>/dev/null || true
    ip netns del "$partner_ns" 2>/dev/null || true
}
trap cleanup EXIT
trap 'exit 130' INT TERM

ip netns add "$driver_ns"
ip netns add "$partner_ns"
ip link add "$driver_if" type veth peer name "$partner_if"
for spec in "$driver_ns $driver_if $driver_addr" "$partner_ns $partner_if $partner_addr"; do
    read -r ns dev addr <<<"$spec"
    ip link set "$dev" netns "$ns"
    ip -n "$ns" addr add "$addr/30" dev "$dev"
    ip -n "$ns" link set "$dev" up
    ip -n "$ns" link set lo up
done

echo "== gprflow-bench ipc: driver in netns $driver_ns ($driver_addr), zenoh partner in $partner_ns ($partner_addr), veth" >&2
ip netns exec "$driver_ns" "$bench" ipc \
    --zenoh-listen "$endpoint" --zenoh-connect "$endpoint" --zenoh-partner-netns "$partner_ns" "$@"
