#!/usr/bin/env bash
# A Docker engine and Compose v2 on this machine, for `make image` and the compose test
# (tests/integration/test_compose.py); nothing to do where an engine already answers.
#
#   deploy/docker/engine.sh up     # install what is missing, start dockerd if none answers
#   deploy/docker/engine.sh down   # stop the dockerd that `up` started (if it did), and put
#                                  # back the iptables rules and links it found
# Installs (root, Debian 12): docker.io (dockerd 20.10) and debootstrap from the system's
# sources, and the Compose v2 plugin binary from Debian 13's docker-compose package (Debian
# 12 has only Compose v1, which rejects the compose file's top-level `name:`), fetched with a
# source list of its own, never added to the system's; the plugin goes to
# ~/.docker/cli-plugins. The engine's data: AESOP_DOCKER_ROOT (default /var/lib/aesop-docker).
set -euo pipefail
state=${AESOP_DOCKER_STATE:-/run/aesop-docker}
root=${AESOP_DOCKER_ROOT:-/var/lib/aesop-docker}
sudo=$([ "$(id -u)" = 0 ] || echo sudo)

answers() { docker info >/dev/null 2>&1; }

install_missing() {
    local missing=()
    command -v dockerd >/dev/null || missing+=(docker.io)
    command -v debootstrap >/dev/null || missing+=(debootstrap)
    command -v iptables-save >/dev/null || missing+=(iptables)
    if [ ${#missing[@]} -gt 0 ]; then
        $sudo apt-get update -q
        $sudo env DEBIAN_FRONTEND=noninteractive apt-get install -y -q "${missing[@]}"
    fi
    if ! docker compose version >/dev/null 2>&1; then
        local tmp
        tmp=$(mktemp -d)
        mkdir -p "$tmp/lists/partial" "$tmp/cache/archives/partial"
        echo "deb http://deb.debian.org/debian trixie main" > "$tmp/sources.list"
        local opts=(-o "Dir::Etc::SourceList=$tmp/sources.list" -o Dir::Etc::SourceParts=/dev/null
                    -o "Dir::State::Lists=$tmp/lists" -o "Dir::Cache=$tmp/cache"
                    -o APT::Sandbox::User=root)
        apt-get "${opts[@]}" update -q >/dev/null
        (cd "$tmp" && apt-get "${opts[@]}" download docker-compose >/dev/null)
        dpkg -x "$tmp"/docker-compose_*.deb "$tmp/root"
        mkdir -p ~/.docker/cli-plugins
        install -m 0755 "$tmp/root/usr/libexec/docker/cli-plugins/docker-compose" \
            ~/.docker/cli-plugins/docker-compose
        rm -rf "$tmp"
    fi
    docker compose version
}

up() {
    install_missing
    if answers; then
        echo "engine.sh: an engine answers: $(docker info --format '{{.ServerVersion}}')"
        return
    fi
    $sudo mkdir -p "$state" "$root"
    # what the engine will change, to put back on `down`
    $sudo iptables-save > "$state/iptables"
    $sudo ip6tables-save > "$state/ip6tables" 2>/dev/null || true
    cat /proc/sys/net/ipv4/ip_forward > "$state/ip_forward"
    $sudo sh -c "nohup dockerd --data-root '$root' --pidfile '$state/dockerd.pid' \
        > '$state/dockerd.log' 2>&1 &"
    for _ in $(seq 60); do answers && break; sleep 1; done
    answers || { echo "engine.sh: dockerd did not answer in 60 s: $state/dockerd.log" >&2; exit 1; }
    touch "$state/started"
    echo "engine.sh: started dockerd $(docker info --format '{{.ServerVersion}}') ($root)"
}

down() {
    if [ ! -e "$state/started" ]; then
        echo "engine.sh: the engine was not started here: left running"
        return
    fi
    local pid
    pid=$(cat "$state/dockerd.pid" 2>/dev/null || true)
    if [ -n "$pid" ] && kill -0 "$pid" 2>/dev/null; then
        $sudo kill -TERM "$pid"  # dockerd stops its containers and its containerd
        for _ in $(seq 60); do kill -0 "$pid" 2>/dev/null || break; sleep 1; done
    fi
    $sudo iptables-restore < "$state/iptables"
    [ ! -s "$state/ip6tables" ] || $sudo ip6tables-restore < "$state/ip6tables" || true
    $sudo sh -c "cat '$state/ip_forward' > /proc/sys/net/ipv4/ip_forward"
    for link in $(ip -o link show type bridge | awk -F': ' '{print $2}' | grep -E '^(docker0|br-)'); do
        $sudo ip link delete "$link" || true
    done
    $sudo rm -f "$state/started"
    echo "engine.sh: dockerd stopped, iptables and links as they were"
}

case ${1:-} in
    up) up ;;
    down) down ;;
    *) echo "usage: $0 up|down" >&2; exit 2 ;;
esac
