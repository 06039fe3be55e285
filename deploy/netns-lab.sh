#!/usr/bin/env bash
# A lab of N hosts on this one machine, for tests of what crosses a network (issue 18: workers
# and a coordinator over real TCP). Each host is a network namespace with loopback and an eth0,
# and a /dev/shm of its own; the eth0s are joined by a bridge that lives in a namespace of its own.
#
#   netns-lab.sh up N           hosts PREFIX-h1 … PREFIX-hN, host i at SUBNET.i/24, bridged in PREFIX-br.
#                               Fails if a lab of PREFIX exists (it may be someone's: down it first).
#   netns-lab.sh down           removes what up made; no lab is fine
#   netns-lab.sh exec H PROG …  runs PROG on host H (its number, or PREFIX-hI), as the process PROG
#   netns-lab.sh partition H    host H drops everything in or out of its eth0 (nftables)
#   netns-lab.sh heal H         undoes partition; a host not partitioned is fine
#   netns-lab.sh nat H          puts host H behind a NAT gateway (namespace PREFIX-nI, which takes
#                               H's address SUBNET.I on the bridge): H is 192.168.I.2 behind it, its
#                               connections out masqueraded, no connection in (a robot on a home
#                               network). nftables
#   netns-lab.sh unnat H        undoes nat; a host not behind NAT is fine
#
# Run programs with exec rather than a bare `ip netns exec`, which shares this machine's /dev/shm
# between hosts: Zenoh then finds its peer's shared memory and passes every message over 3 KiB
# through it, not over TCP. exec binds the host's own directory, /dev/shm/PREFIX-hI, on /dev/shm.
#
# Environment:
#   RETRIEVER_LAB_PREFIX  names the lab's namespaces (default rtlab): two labs of different
#                         prefixes (a test run's and a developer's) never touch each other
#   RETRIEVER_LAB_SUBNET  the hosts' /24 (default 10.200.77.0/24). Its addresses exist only inside
#                         the lab's namespaces: nothing is routed to or from this machine's networks
#
# Needs root and iproute2; partition and heal need nftables. Installs nothing.
set -euo pipefail

prog=$(basename "$0")
prefix=${RETRIEVER_LAB_PREFIX:-rtlab}
subnet=${RETRIEVER_LAB_SUBNET:-10.200.77.0/24}
table=retriever_lab  # the nftables table of a partition, in the host's own namespace

die() { echo "$prog: error: $*" >&2; exit 1; }

usage() {
    echo "usage: $prog up N | down | exec HOST PROGRAM [ARG …] | partition HOST | heal HOST | nat HOST | unnat HOST" >&2
    echo "    (RETRIEVER_LAB_PREFIX=$prefix, RETRIEVER_LAB_SUBNET=$subnet; see the top of $0)" >&2
    exit 2
}

# A lab's namespaces are PREFIX-br, PREFIX-h<i> and the NAT gateways PREFIX-n<i>: a suffix with
# no '-' after PREFIX-, so no other prefix's namespaces ever match (lab "a" never claims lab
# "a-h1"'s "a-h1-br").
lab_namespaces() { ip netns list | awk -v re="^${prefix}-(br|h[0-9]+|n[0-9]+)\$" '$1 ~ re {print $1}' | sort -V; }

host_namespace() {  # HOST as a number or a name → the namespace, which must be one of this lab's hosts
    local ns=$1
    [[ $ns =~ ^[0-9]+$ ]] && ns=$prefix-h$ns
    [[ $ns =~ ^${prefix}-h[0-9]+$ ]] && grep -qx -- "$ns" <<<"$(lab_namespaces)" \
        || die "no host '$1' in lab '$prefix' (it has: $(lab_namespaces | grep -- '-h[0-9]*$' | xargs))"
    echo "$ns"
}

up() {
    local n=$1 i h
    [[ $n =~ ^[0-9]{1,3}$ ]] && ((10#$n >= 1 && 10#$n <= 253)) \
        || die "up N: N is the number of hosts, 1 to 253; got '$n'"
    n=$((10#$n))
    [[ -z $(lab_namespaces) ]] \
        || die "a lab '$prefix' exists ($(lab_namespaces | xargs)): '$prog down' it, or set RETRIEVER_LAB_PREFIX"
    # Creating the bridge's namespace claims the prefix (it fails if it exists); from then on a
    # failure removes what this call made, so no half lab is left.
    ip netns add "$prefix-br" 2>/dev/null \
        || die "a lab '$prefix' was created at the same time; set RETRIEVER_LAB_PREFIX"
    trap 'echo "$prog: up failed; removing the lab" >&2; down' ERR
    ip -n "$prefix-br" link add br0 type bridge
    ip -n "$prefix-br" link set br0 up
    for ((i = 1; i <= n; i++)); do
        h=$prefix-h$i
        ip netns add "$h"
        ip -n "$prefix-br" link add "vb$i" type veth peer name eth0 netns "$h"
        ip -n "$prefix-br" link set "vb$i" master br0 up
        ip -n "$h" addr add "$net.$i/24" dev eth0
        ip -n "$h" link set eth0 up
        ip -n "$h" link set lo up
        mkdir -m 1777 "/dev/shm/$h"  # the host's own /dev/shm (see exec): world-writable and sticky like it
    done
    trap - ERR
    echo "lab '$prefix' is up: $n hosts, $prefix-hI at $net.I for I = 1 … $n ($prog exec I PROGRAM)"
}

down() {
    local ns pids
    for ns in $(lab_namespaces); do
        # A namespace outlives its name while a process is inside: say so, kill nothing.
        pids=$(ip netns pids "$ns" | xargs)
        [[ -z $pids ]] || echo "$prog: warning: processes $pids still run in $ns; its network lives until they exit" >&2
        ip netns del "$ns"
    done
    for d in /dev/shm/"$prefix"-h*; do
        [[ $d =~ ^/dev/shm/${prefix}-h[0-9]+$ && -d $d ]] && rm -rf -- "$d"
    done
    return 0
}

run_on() {
    local ns
    ns=$(host_namespace "$1")
    shift
    # `ip netns exec` gives PROG a mount namespace of its own (a slave of this one's): the bind
    # mount is PROG's alone, and each exec hands PROG on in the same process
    exec ip netns exec "$ns" sh -c 'mount --bind "$0" /dev/shm && exec "$@"' "/dev/shm/$ns" "$@"
}

need_nft() { command -v nft >/dev/null || die "'nft' not found: apt-get install nftables"; }

# A partition drops every packet in or out of the host's eth0, not only the lab's IPv4 subnet:
# the link-local IPv6 addresses on eth0 would otherwise still join the hosts. Loopback stays up.
partition() {
    local ns
    ns=$(host_namespace "$1")
    need_nft
    if ip netns exec "$ns" nft list table inet "$table" >/dev/null 2>&1; then
        echo "$ns is already partitioned"
        return
    fi
    ip netns exec "$ns" nft -f - <<EOF
table inet $table {
    chain input { type filter hook input priority 0; policy accept; iifname "eth0" drop; }
    chain output { type filter hook output priority 0; policy accept; oifname "eth0" drop; }
}
EOF
    echo "$ns is partitioned from the lab"
}

heal() {
    local ns
    ns=$(host_namespace "$1")
    need_nft
    if ip netns exec "$ns" nft list table inet "$table" >/dev/null 2>&1; then
        ip netns exec "$ns" nft delete table inet "$table"
        echo "$ns is healed"
    else
        echo "$ns was not partitioned"
    fi
}

# nat: the gateway takes the host's eth0 (its end of the bridge) and address; a veth joins it to
# the host, which routes everything through it. The gateway forwards the host's connections out,
# masqueraded as its own address, and only their replies in: nothing opens a connection to the host.
nat() {
    local ns i gw
    ns=$(host_namespace "$1")
    i=${ns##*-h}
    gw=$prefix-n$i
    need_nft
    if ip netns list | awk '{print $1}' | grep -qx -- "$gw"; then
        echo "$ns is already behind NAT ($gw)"
        return
    fi
    ip netns add "$gw"
    ip -n "$ns" link set eth0 netns "$gw"
    ip -n "$gw" addr add "$net.$i/24" dev eth0
    ip -n "$gw" link set eth0 up
    ip -n "$gw" link set lo up
    ip -n "$gw" link add eth1 type veth peer name eth0 netns "$ns"
    ip -n "$gw" addr add "192.168.$i.1/24" dev eth1
    ip -n "$gw" link set eth1 up
    ip -n "$ns" addr add "192.168.$i.2/24" dev eth0
    ip -n "$ns" link set eth0 up
    ip -n "$ns" route add default via "192.168.$i.1"
    ip netns exec "$gw" sysctl -qw net.ipv4.ip_forward=1
    ip netns exec "$gw" nft -f - <<EOF
table inet $table {
    chain forward { type filter hook forward priority 0; policy drop;
        iifname "eth1" oifname "eth0" accept;
        iifname "eth0" oifname "eth1" ct state established,related accept; }
    chain postrouting { type nat hook postrouting priority 100; oifname "eth0" masquerade; }
}
EOF
    echo "$ns is behind NAT: 192.168.$i.2, seen as $net.$i (gateway $gw)"
}

unnat() {
    local ns i gw
    ns=$(host_namespace "$1")
    i=${ns##*-h}
    gw=$prefix-n$i
    if ! ip netns list | awk '{print $1}' | grep -qx -- "$gw"; then
        echo "$ns was not behind NAT"
        return
    fi
    ip -n "$ns" link del eth0  # the veth to the gateway, both ends
    ip -n "$gw" link set eth0 netns "$ns"
    ip -n "$ns" addr add "$net.$i/24" dev eth0
    ip -n "$ns" link set eth0 up
    ip netns del "$gw"
    echo "$ns is on the lab's bridge again at $net.$i"
}

[[ $# -ge 1 ]] || usage
[[ $prefix =~ ^[A-Za-z0-9_-]{1,32}$ ]] || die "RETRIEVER_LAB_PREFIX='$prefix': use 1 to 32 letters, digits, '_' or '-'"
[[ $subnet =~ ^([0-9]{1,3}\.[0-9]{1,3}\.[0-9]{1,3})\.0/24$ ]] \
    || die "RETRIEVER_LAB_SUBNET='$subnet': expected a /24 such as 10.200.77.0/24"
net=${BASH_REMATCH[1]}
[[ $(id -u) -eq 0 ]] || die "network namespaces need root: sudo $0 $*"
command -v ip >/dev/null || die "'ip' not found: apt-get install iproute2"

case "$1" in
    up) [[ $# -eq 2 ]] || usage; up "$2" ;;
    down) [[ $# -eq 1 ]] || usage; down ;;
    exec) [[ $# -ge 3 ]] || usage; shift; run_on "$@" ;;
    partition) [[ $# -eq 2 ]] || usage; partition "$2" ;;
    heal) [[ $# -eq 2 ]] || usage; heal "$2" ;;
    nat) [[ $# -eq 2 ]] || usage; nat "$2" ;;
    unnat) [[ $# -eq 2 ]] || usage; unnat "$2" ;;
    *) usage ;;
esac
