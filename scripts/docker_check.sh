#!/usr/bin/env bash
# Build threedq's Docker image on a Debian machine that reaches no container registry, and run it.
#
#   sudo bash scripts/docker_check.sh            # from the repository root; about 10-15 min on 2 cores
#
# What it does, in order (a maintainer's check before a release; not part of the tests or CI):
#   1. installs Debian's docker.io and mmdebstrap if they are missing;
#   2. starts its own dockerd (own socket, pid file and data root; no bridge, no iptables rules, so there is no
#      network change to undo) and stops it by its pid on exit, whatever happens;
#   3. makes a local base image (Debian bookworm minbase + python3 + venv, `docker import`), with this host's CA
#      bundle in it where the host has one (HTTPS may be intercepted: pip inside the build must trust what the host
#      trusts), unless that image exists already;
#   4. serves torch (the wheel this host's `pip download torch==$TORCH_VERSION` takes, and its dependencies) as a
#      package index on the host's loopback, and builds the project's image with `--network host`;
#   5. runs, inside the image with no network: `threedq --help`, the tests' fast subset (`-m "not slow"`) and a
#      short training (`threedq em --rounds 1` with a few steps on a small generated dataset);
#   6. prints the build time, the image size and the run's numbers, and writes them to $OUT/docker_check.json.
#
# Nothing machine-specific is in this file: the Debian mirror is read from the host's apt sources, the CA bundle
# from the host's usual place (or $HOST_CA_BUNDLE), the torch wheel from the host's pip configuration.
# Environment (all optional): TORCH_VERSION (2.13.0), BASE_IMAGE (threedq-base:bookworm, made here if missing),
# REBUILD_BASE=1, DEBIAN_MIRROR, HOST_CA_BUNDLE, DOCKER_DATA_ROOT (/var/lib/threedq-docker), OUT (a new temp dir),
# SKIP_TESTS=1, EM_STEPS (20), PORT (8765).
set -euo pipefail

cd "$(dirname "$0")/.."
REPO=$PWD
TORCH_VERSION=${TORCH_VERSION:-2.13.0}
BASE_IMAGE=${BASE_IMAGE:-threedq-base:bookworm}
IMAGE=${IMAGE:-threedq:cpu}
DATA_ROOT=${DOCKER_DATA_ROOT:-/var/lib/threedq-docker}
OUT=${OUT:-$(mktemp -d /tmp/threedq-docker-check.XXXXXX)}
PORT=${PORT:-8765}
EM_STEPS=${EM_STEPS:-20}
mkdir -p "$OUT"
RUN_DIR=$(mktemp -d /tmp/threedq-dockerd.XXXXXX)
SOCK=$RUN_DIR/docker.sock
export DOCKER_HOST=unix://$SOCK
log() { printf '[docker_check %(%H:%M:%S)T] %s\n' -1 "$*"; }

[ "$(id -u)" = 0 ] || { echo "docker_check.sh: run as root (it starts dockerd)" >&2; exit 2; }
command -v apt-get >/dev/null || { echo "docker_check.sh: needs a Debian-like host (apt-get)" >&2; exit 2; }

# ---- 1. the engine and the base-image maker -------------------------------------------------------------------
if ! command -v dockerd >/dev/null || ! command -v mmdebstrap >/dev/null; then
    log "installing docker.io and mmdebstrap from the Debian mirror"
    apt-get update -q >/dev/null
    DEBIAN_FRONTEND=noninteractive apt-get install -y -q docker.io mmdebstrap >/dev/null
fi
DOCKER=/usr/bin/docker; [ -x "$DOCKER" ] || DOCKER=$(command -v docker)

# ---- 2. our own dockerd, stopped by its pid on exit ----------------------------------------------------------
SERVER_PID=""
DOCKERD_PID=""
had_docker0=0; ip link show docker0 >/dev/null 2>&1 && had_docker0=1
cleanup() {
    local rc=$?
    [ -n "$SERVER_PID" ] && kill "$SERVER_PID" 2>/dev/null || true
    if [ -n "$DOCKERD_PID" ]; then
        log "stopping dockerd (pid $DOCKERD_PID)"
        kill "$DOCKERD_PID" 2>/dev/null || true
        for _ in $(seq 60); do kill -0 "$DOCKERD_PID" 2>/dev/null || break; sleep 1; done
        kill -9 "$DOCKERD_PID" 2>/dev/null || true
    fi
    # dockerd ran without a bridge and without iptables; remove a docker0 only if it appeared during this run
    if [ "$had_docker0" = 0 ] && ip link show docker0 >/dev/null 2>&1; then ip link delete docker0 || true; fi
    # dockerd leaves its network namespace mounted under its exec root: unmount what lies under our folder
    awk -v d="$RUN_DIR" 'index($2, d) == 1 {print $2}' /proc/mounts | sort -r | while read -r m; do
        umount "$m" 2>/dev/null || umount -l "$m" 2>/dev/null || true
    done
    rm -rf "$RUN_DIR"
    exit $rc
}
trap cleanup EXIT INT TERM
log "starting dockerd (data root $DATA_ROOT, socket $SOCK)"
mkdir -p "$DATA_ROOT"
dockerd --host "$DOCKER_HOST" --pidfile "$RUN_DIR/dockerd.pid" --exec-root "$RUN_DIR/exec" --data-root "$DATA_ROOT" \
    --bridge none --iptables=false --ip6tables=false --ip-forward=false --ip-masq=false \
    >"$OUT/dockerd.log" 2>&1 &
DOCKERD_PID=$!
for _ in $(seq 60); do "$DOCKER" info >/dev/null 2>&1 && break; sleep 1; done
"$DOCKER" info >/dev/null 2>&1 || { echo "dockerd did not start; its log: $OUT/dockerd.log" >&2; tail -20 "$OUT/dockerd.log" >&2; exit 1; }

# ---- 3. a local base image -----------------------------------------------------------------------------------
host_mirror() {
    local m=""
    if [ -f /etc/apt/sources.list.d/debian.sources ]; then
        m=$(awk '/^URIs:/ {print $2; exit}' /etc/apt/sources.list.d/debian.sources)
    fi
    if [ -z "$m" ] && [ -f /etc/apt/sources.list ]; then
        m=$(awk '$1 == "deb" {for (i = 2; i <= NF; i++) if ($i ~ /^https?:/) {print $i; exit}}' /etc/apt/sources.list)
    fi
    echo "${m:-http://deb.debian.org/debian}"
}
if [ "${REBUILD_BASE:-0}" = 1 ] || ! "$DOCKER" image inspect "$BASE_IMAGE" >/dev/null 2>&1; then
    MIRROR=${DEBIAN_MIRROR:-$(host_mirror)}
    CA=${HOST_CA_BUNDLE:-}
    for c in /etc/ssl/certs/ca-certificates.crt /etc/pki/tls/certs/ca-bundle.crt; do
        [ -z "$CA" ] && [ -f "$c" ] && CA=$c
    done
    log "making $BASE_IMAGE with mmdebstrap from $MIRROR${CA:+ (CA bundle: $CA)}"
    hooks=()
    changes=(--change 'CMD ["/bin/bash"]' --change 'ENV LANG=C.UTF-8')
    if [ -n "$CA" ]; then
        cp "$CA" "$RUN_DIR/host-ca.crt"
        hooks+=(--customize-hook="mkdir -p \"\$1/etc/ssl/host\" && cp '$RUN_DIR/host-ca.crt' \"\$1/etc/ssl/host/ca-bundle.crt\"")
        changes+=(--change 'ENV PIP_CERT=/etc/ssl/host/ca-bundle.crt SSL_CERT_FILE=/etc/ssl/host/ca-bundle.crt REQUESTS_CA_BUNDLE=/etc/ssl/host/ca-bundle.crt')
    fi
    t0=$(date +%s)
    mmdebstrap --quiet --variant=minbase --include=python3,python3-venv,ca-certificates \
        "${hooks[@]}" bookworm "$RUN_DIR/rootfs.tar" "$MIRROR"
    "$DOCKER" import "${changes[@]}" "$RUN_DIR/rootfs.tar" "$BASE_IMAGE" >/dev/null
    rm -f "$RUN_DIR/rootfs.tar"
    log "base image made in $(( $(date +%s) - t0 )) s"
fi

# ---- 4. torch on a loopback index, and the build ------------------------------------------------------------
log "collecting torch==$TORCH_VERSION and its dependencies as this host's pip takes them"
WHEELS=$RUN_DIR/wheels
python3 -m pip download -q --only-binary=:all: -d "$WHEELS" "torch==$TORCH_VERSION" 2>&1 \
    | grep -v "^WARNING: Location" || true  # (a host's file:// index that lacks a project warns; harmless)
ls "$WHEELS"/torch-"$TORCH_VERSION"*.whl >/dev/null || { echo "pip download found no torch==$TORCH_VERSION" >&2; exit 1; }
python3 - "$WHEELS" "$RUN_DIR/index" <<'PY'
import os, re, sys
from pathlib import Path
wheels, index = Path(sys.argv[1]), Path(sys.argv[2])
for f in sorted(wheels.iterdir()):
    name = re.sub(r"[-_.]+", "-", f.name.split("-")[0]).lower()   # PEP 503 normalised project name
    (index / name).mkdir(parents=True, exist_ok=True)
    os.symlink(f, index / name / f.name)
PY
python3 -m http.server "$PORT" --bind 127.0.0.1 --directory "$RUN_DIR/index" >"$OUT/index_server.log" 2>&1 &
SERVER_PID=$!
sleep 1
log "building $IMAGE (base $BASE_IMAGE)"
t0=$(date +%s)
"$DOCKER" build --network host --build-arg "BASE_IMAGE=$BASE_IMAGE" --build-arg "TORCH_VERSION=$TORCH_VERSION" \
    --build-arg "TORCH_INDEX=http://127.0.0.1:$PORT/" -t "$IMAGE" "$REPO" >"$OUT/build.log" 2>&1 \
    || { tail -40 "$OUT/build.log" >&2; echo "build failed; the log: $OUT/build.log" >&2; exit 1; }
BUILD_S=$(( $(date +%s) - t0 ))
kill "$SERVER_PID" 2>/dev/null || true; SERVER_PID=""
SIZE_B=$("$DOCKER" image inspect -f '{{.Size}}' "$IMAGE")
log "built in $BUILD_S s, $(( SIZE_B / 1024 / 1024 )) MiB"

# ---- 5. the image at work, without a network ---------------------------------------------------------------
run() { "$DOCKER" run --rm --network none "$@"; }
log "threedq --help in the image"
run "$IMAGE" --help >"$OUT/help.txt"
TESTS_S=-1; TESTS_LINE="skipped"
if [ "${SKIP_TESTS:-0}" != 1 ]; then
    log "the tests' fast subset in the image (pytest -m 'not slow')"
    t0=$(date +%s)
    run --entrypoint pytest "$IMAGE" -q -m "not slow" -p no:cacheprovider >"$OUT/tests.log" 2>&1 \
        || { tail -40 "$OUT/tests.log" >&2; echo "tests failed in the image; the log: $OUT/tests.log" >&2; exit 1; }
    TESTS_S=$(( $(date +%s) - t0 ))
    TESTS_LINE=$(tail -1 "$OUT/tests.log")
    log "tests: $TESTS_LINE"
fi
log "a short training: threedq em --rounds 1 ($EM_STEPS steps a stage, 40 scenes of 64 x 64)"
mkdir -p "$OUT/work"
cat >"$OUT/work/short.yaml" <<YAML
model:
  init_args:
    grid_resolution: [32, 32, 16]
data:
  init_args:
    data_dir: data/short
    num_scenes: 40
    split_fractions: [0.6, 0.1, 0.3]
    image_size: [64, 64]
    num_views: 4
trainer:
  max_steps: $EM_STEPS
  log_every_n_steps: 5
  limit_val_batches: 1
  enable_model_summary: false
YAML
t0=$(date +%s)
# the data module generates the 40 scenes on first use, inside the container (the offline EGL renderer)
run -v "$OUT/work:/work" "$IMAGE" em --rounds 1 --extra_configs short.yaml --work_dir runs/em >"$OUT/em.log" 2>&1 \
    || { tail -40 "$OUT/em.log" >&2; echo "the short training failed; the log: $OUT/em.log" >&2; exit 1; }
EM_S=$(( $(date +%s) - t0 ))

# ---- 6. the figures --------------------------------------------------------------------------------------------
python3 - "$OUT" "$BUILD_S" "$SIZE_B" "$TESTS_S" "$TESTS_LINE" "$EM_S" "$IMAGE" "$BASE_IMAGE" "$TORCH_VERSION" <<'PY'
import json, platform, subprocess, sys
from pathlib import Path
out, build_s, size_b, tests_s, tests_line, em_s, image, base, torch_v = sys.argv[1:]
metrics = json.loads((Path(out) / "work" / "runs" / "em" / "metrics.json").read_text())
cpu = next((l.split(":", 1)[1].strip() for l in open("/proc/cpuinfo") if l.startswith("model name")), platform.machine())
commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True).stdout.strip()
summary = {"image": image, "base_image": base, "torch": torch_v, "commit": commit, "cpu": cpu,
           "build_s": int(build_s), "image_size_mib": round(int(size_b) / 2**20),
           "tests_s": int(tests_s), "tests": tests_line, "em_rounds_1_s": int(em_s),
           "em_table3": metrics.get("table3")}
(Path(out) / "docker_check.json").write_text(json.dumps({**summary, "metrics": metrics}, indent=1, default=str))
print("| what | value |\n|---|---|")
for k, v in summary.items():
    if k != "em_table3":
        print(f"| {k} | {v} |")
print("\nthe short training (threedq em --rounds 1 in the image), Table 3:")
for row in metrics.get("table3") or []:
    print("  " + ", ".join(f"{k} {v:.3f}" if isinstance(v, float) else f"{k} {v}" for k, v in row.items()
                           if isinstance(v, (int, float))))
for line in (Path(out) / "em.log").read_text().splitlines():
    if line.startswith("[em] round") or line.startswith("[em] precision"):
        print("  " + line)
PY
log "done: $OUT/docker_check.json (logs beside it)"
