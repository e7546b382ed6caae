#!/usr/bin/env bash
# Install smartedge on an edge board (a Jetson, or any Linux with systemd and Python >= 3.10):
# a venv in /opt/smartedge with only the `edge` extra, the system user `smartedge`,
# /etc/smartedge (site file, zenoh client config, settings), and one enabled
# smartedge-edge-agent@<camera>.service per camera id. Safe to re-run (updates code, configs and
# units; keeps edited settings files). Walkthrough: docs/deployment.md.
set -euo pipefail
PROG="install-edge.sh"
# shellcheck source=deploy/install-common.sh
. "$(dirname "${BASH_SOURCE[0]}")/install-common.sh"

usage() {
  cat <<USAGE
Usage: sudo $PROG --site SITE.yaml --backend-host HOST [options] CAMERA_ID...

Install smartedge[edge] and one edge-agent service per CAMERA_ID (ids of the site file).

Required:
  --site FILE            site file; installed as $ETC/site.yaml
  --backend-host HOST    name or address of the backend host running the Zenoh router

Options:
  --tls DIR              Zenoh over TLS (mTLS): DIR holds ca.crt, client.crt, client.key
                         (installed to $ETC/tls; uses deploy/zenoh/client-tls.json5), or, made
                         by \`smartedge certs\`, ca.crt and edge-<camera>.crt/.key for each
                         CAMERA_ID: each agent then connects with its own certificate
  --with FILE            another file the site file refers to (calibration_file), copied next
                         to it; repeatable
  --source camera|sim    SMARTEDGE_SOURCE for a new smartedge.env (default: camera)
  --device CAMERA=URI    the camera's OpenCV input (V4L2 index or path, RTSP/HTTP URL, video
                         file): writes $ETC/edge-agent@CAMERA.env with
                         SMARTEDGE_EDGE_AGENT_ARGS=--device URI; repeatable; with one
                         CAMERA_ID, --device URI is enough. For a RealSense or an image folder,
                         edit that file (docs/deployment.md)
  --jetson auto|yes|no   a Jetson (default auto: if /etc/nv_tegra_release): the GPU drop-in,
                         a venv that sees JetPack's system packages (--system-site-packages),
                         and JetPack's OpenCV (with GStreamer: CSI cameras) in place of
                         opencv-python-headless when the system python3 has it (numpy kept <2,
                         which that OpenCV is built against)
  --ort-wheel SPEC       replace the CPU-only onnxruntime with this GPU build (CUDA, TensorRT):
                         a wheel file, URL or requirement, e.g. NVIDIA's onnxruntime-gpu for
                         JetPack 6 (docs/deployment.md); give it again on every re-run
  --ort-index URL        extra pip index to find --ort-wheel in
  --package SPEC         wheel file or source directory to pip install with [edge]
                         (default: the checkout this script is in)
  --python PY            interpreter that creates the venv (default: python3)
  --skip-pip             do not create or update the venv in $PREFIX
  --skip-apt             do not install missing Debian packages
  --no-start             enable the units, do not (re)start them
  --root DIR             install under DIR instead of / (staging, tests): no apt, useradd,
                         chown or systemctl
  --dry-run              print every step, change nothing
  -h, --help             this help

Example:
  sudo deploy/install-edge.sh --site lab.yaml --backend-host backend.lab \
      --device cam_sw=/dev/video0 --device cam_se=/dev/video2 cam_sw cam_se
USAGE
}

# jetson_venv: /opt/smartedge sees JetPack's system site-packages (OpenCV with GStreamer,
# TensorRT's python): a new venv is made with --system-site-packages, an existing one switched.
jetson_venv() {
  local venv cfg
  venv="$(staged "$PREFIX")"
  if [ "$SKIP_PIP" = 1 ]; then log "skip (--skip-pip): venv $venv --system-site-packages"; return 0; fi
  if [ ! -x "$venv/bin/python" ]; then
    run "$PYTHON_BIN" -m venv "$venv" --system-site-packages
    return 0
  fi
  cfg="$venv/pyvenv.cfg"
  if [ -f "$cfg" ] && grep -q '^include-system-site-packages = false' "$cfg"; then
    run sed -i 's/^include-system-site-packages = false/include-system-site-packages = true/' "$cfg"
  fi
}

# jetson_opencv: when the system python3's OpenCV has GStreamer (JetPack's does), the venv uses
# it: opencv-python-headless (no GStreamer) goes, numpy stays 1.x (that OpenCV is built
# against numpy 1.x and cannot load under numpy 2).
jetson_opencv() {
  local venv
  venv="$(staged "$PREFIX")"
  if [ "$SKIP_PIP" = 1 ]; then log "skip (--skip-pip): JetPack OpenCV in place of opencv-python-headless"; return 0; fi
  if [ "$DRY_RUN" = 1 ]; then
    log "would: if the system OpenCV has GStreamer: $venv/bin/python -m pip uninstall -y opencv-python-headless; pip install 'numpy>=1.24,<2'"
    return 0
  fi
  if "$PYTHON_BIN" -c 'import re, sys, cv2; sys.exit(0 if re.search(r"GStreamer:\s*YES", cv2.getBuildInformation()) else 1)' 2>/dev/null; then
    run "$venv/bin/python" -m pip install --quiet "numpy>=1.24,<2"
    run "$venv/bin/python" -m pip uninstall --quiet -y opencv-python-headless
  else
    log "WARNING: $PYTHON_BIN has no OpenCV with GStreamer (JetPack: apt install nvidia-opencv);"
    log "  the venv keeps opencv-python-headless: no CSI cameras (--device csi://N) on this board"
  fi
}

# gpu_onnxruntime: the GPU build of onnxruntime (--ort-wheel) replaces the CPU-only one; both
# install the same 'onnxruntime' package, so both distributions go first.
gpu_onnxruntime() {
  local venv
  venv="$(staged "$PREFIX")"
  if [ "$SKIP_PIP" = 1 ]; then log "skip (--skip-pip): pip install $ORT_WHEEL"; return 0; fi
  run "$venv/bin/python" -m pip uninstall --quiet -y onnxruntime onnxruntime-gpu
  if [ -n "$ORT_INDEX" ]; then
    run "$venv/bin/python" -m pip install --quiet --extra-index-url "$ORT_INDEX" "$ORT_WHEEL"
  else
    run "$venv/bin/python" -m pip install --quiet "$ORT_WHEEL"
  fi
}

# report_runtime: what the installed venv offers the edge agent (execution providers,
# GStreamer), so a board that would run on the CPU says so now.
report_runtime() {
  local py
  py="$(staged "$PREFIX")/bin/python"
  if [ "$DRY_RUN" = 1 ] || [ "$SKIP_PIP" = 1 ] || [ ! -x "$py" ]; then return 0; fi
  "$py" - <<'PY' || log "WARNING: onnxruntime or OpenCV does not import in $PREFIX"
import re
import cv2
import onnxruntime as ort
have = ort.get_available_providers()
gst = re.search(r"GStreamer:\s*(\S+)", cv2.getBuildInformation())
print(f"install-edge.sh: onnxruntime {ort.__version__} providers {', '.join(have)}; "
      f"OpenCV {cv2.__version__} GStreamer {gst.group(1) if gst else '?'}")
if "TensorrtExecutionProvider" not in have:
    print("install-edge.sh: no TensorRT provider: the networks run on "
          + ("CUDA" if "CUDAExecutionProvider" in have else "the CPU")
          + " (GPU: --ort-wheel, docs/deployment.md)")
PY
}

SITE=""
BACKEND_HOST=""
TLS_DIR=""
SOURCE=camera
JETSON=auto
ORT_WHEEL=""
ORT_INDEX=""
EXTRA_FILES=()
DEVICES=()
CAMERAS=()
while [ $# -gt 0 ]; do
  if common_option "$@"; then shift "$SHIFT_BY"; continue; fi
  case "$1" in
    -h | --help) usage; exit 0 ;;
    --site) SITE="${2:?--site needs a file}"; shift 2 ;;
    --backend-host) BACKEND_HOST="${2:?--backend-host needs a host}"; shift 2 ;;
    --tls) TLS_DIR="${2:?--tls needs a directory}"; shift 2 ;;
    --with) EXTRA_FILES+=("${2:?--with needs a file}"); shift 2 ;;
    --source) SOURCE="${2:?--source needs camera or sim}"; shift 2 ;;
    --device) DEVICES+=("${2:?--device needs CAMERA=URI}"); shift 2 ;;
    --jetson) JETSON="${2:?--jetson needs auto, yes or no}"; shift 2 ;;
    --ort-wheel) ORT_WHEEL="${2:?--ort-wheel needs a wheel file, URL or requirement}"; shift 2 ;;
    --ort-index) ORT_INDEX="${2:?--ort-index needs a URL}"; shift 2 ;;
    -*) usage >&2; die "unknown option $1" ;;
    *) CAMERAS+=("$1"); shift ;;
  esac
done

[ -n "$SITE" ] || { usage >&2; die "--site is required"; }
[ -f "$SITE" ] || die "$SITE: no such file"
[ -n "$BACKEND_HOST" ] || { usage >&2; die "--backend-host is required"; }
[[ "$BACKEND_HOST" =~ ^[A-Za-z0-9._:-]+$ ]] || die "--backend-host $BACKEND_HOST: not a host name or address"
[ ${#CAMERAS[@]} -gt 0 ] || { usage >&2; die "give at least one CAMERA_ID"; }
for cam in "${CAMERAS[@]}"; do
  [[ "$cam" =~ ^[A-Za-z0-9_.-]+$ ]] || die "camera id $cam: only [A-Za-z0-9_.-] allowed"
done
case "$SOURCE" in camera | sim) ;; *) die "--source $SOURCE: expected camera or sim" ;; esac
# --device CAMERA=URI (or URI alone for a single camera) → DEVICE_OF[CAMERA]=URI
declare -A DEVICE_OF=()
for spec in ${DEVICES[@]+"${DEVICES[@]}"}; do
  if [[ "$spec" == *=* && "${spec%%=*}" =~ ^[A-Za-z0-9_.-]+$ ]]; then
    cam="${spec%%=*}" uri="${spec#*=}"
  elif [ ${#CAMERAS[@]} -eq 1 ]; then
    cam="${CAMERAS[0]}" uri="$spec"
  else
    die "--device $spec: write CAMERA=URI when installing several cameras"
  fi
  in_list=0
  for c in "${CAMERAS[@]}"; do [ "$c" = "$cam" ] && in_list=1; done
  [ "$in_list" = 1 ] || die "--device $spec: camera $cam is not among the cameras installed (${CAMERAS[*]})"
  [ -n "$uri" ] || die "--device $spec: empty URI"
  [[ "$uri" =~ ^[A-Za-z0-9_.:/@%?\&=+~,-]+$ ]] || \
    die "--device $spec: the URI may not contain spaces, quotes, \$ or backslashes"
  [ -z "${DEVICE_OF[$cam]+x}" ] || die "--device: camera $cam given twice"
  DEVICE_OF[$cam]="$uri"
done
case "$JETSON" in
  auto) if [ -f /etc/nv_tegra_release ]; then JETSON=yes; else JETSON=no; fi ;;
  yes | no) ;;
  *) die "--jetson $JETSON: expected auto, yes or no" ;;
esac
# --tls: one certificate per camera (edge-<camera>, from `smartedge certs`) when DIR has them
# all, else the board's client.crt
TLS_PER_CAMERA=0
if [ -n "$TLS_DIR" ]; then
  TLS_PER_CAMERA=1
  for cam in "${CAMERAS[@]}"; do
    [ -f "$TLS_DIR/edge-$cam.crt" ] && [ -f "$TLS_DIR/edge-$cam.key" ] || TLS_PER_CAMERA=0
  done
  tls_files=(ca.crt client.crt client.key)
  [ "$TLS_PER_CAMERA" = 0 ] || tls_files=(ca.crt)
  for f in "${tls_files[@]}"; do
    [ -f "$TLS_DIR/$f" ] || die "--tls: $TLS_DIR/$f missing (or edge-<camera>.crt/.key for every camera)"
  done
fi
default_package
normalize_root
ensure_root_privileges
[ "$DRY_RUN" = 1 ] && log "dry run: nothing is changed"
log "edge board: cameras ${CAMERAS[*]}, router tcp/tls on $BACKEND_HOST:7447, package ${PACKAGE}[edge]"

# 1. system packages and user
ensure_apt python3-venv
ensure_user

# 2. python environment: only the edge extra (no casadi, gtsam, open3d, rerun on a board)
if [ "$JETSON" = yes ]; then jetson_venv; fi
had_gpu_ort=0
if [ -z "$ORT_WHEEL" ] && [ -x "$(staged "$PREFIX")/bin/python" ] && \
   "$(staged "$PREFIX")/bin/python" -m pip show onnxruntime-gpu >/dev/null 2>&1; then
  had_gpu_ort=1
fi
ensure_venv edge
if [ "$JETSON" = yes ]; then jetson_opencv; fi
if [ -n "$ORT_WHEEL" ]; then
  gpu_onnxruntime
elif [ "$had_gpu_ort" = 1 ]; then
  log "WARNING: onnxruntime-gpu was installed; pip just put the CPU-only onnxruntime over it."
  log "  Re-run with --ort-wheel SPEC (the same GPU wheel) to get CUDA/TensorRT back."
fi

check_site "$SITE" cameras "${CAMERAS[@]}"

# 3. configuration
install_dir 0750 "$ETC"
install_file 0640 "$SITE" "$ETC/site.yaml"
for f in ${EXTRA_FILES[@]+"${EXTRA_FILES[@]}"}; do install_file 0640 "$f" "$ETC/$(basename "$f")"; done
if [ -n "$TLS_DIR" ]; then
  install_dir 0750 "$ETC/tls"
  install_file 0644 "$TLS_DIR/ca.crt" "$ETC/tls/ca.crt"
  if [ "$TLS_PER_CAMERA" = 0 ]; then
    install_file 0644 "$TLS_DIR/client.crt" "$ETC/tls/client.crt"
    install_file 0640 "$TLS_DIR/client.key" "$ETC/tls/client.key"
  fi
  install_rendered 0640 "$DEPLOY_DIR/zenoh/client-tls.json5" "$ETC/zenoh-client.json5" \
    "s/BACKEND_HOST/$BACKEND_HOST/g"
else
  install_rendered 0640 "$DEPLOY_DIR/zenoh/client.json5" "$ETC/zenoh-client.json5" \
    "s/BACKEND_HOST/$BACKEND_HOST/g"
fi
install_if_missing 0640 "$DEPLOY_DIR/smartedge.env.example" "$ETC/smartedge.env" \
  "s/^SMARTEDGE_SOURCE=.*/SMARTEDGE_SOURCE=$SOURCE/"

# the camera inputs: one env file per camera given with --device
for cam in "${CAMERAS[@]}"; do
  env_file="$ETC/edge-agent@$cam.env"
  if [ -n "${DEVICE_OF[$cam]+x}" ]; then
    tmp_env="$(mktemp)"
    printf '%s\n' "# camera $cam: written by install-edge.sh --device (re-running with --device rewrites it)" \
      "SMARTEDGE_EDGE_AGENT_ARGS=--device ${DEVICE_OF[$cam]}" > "$tmp_env"
    install_rendered 0640 "$tmp_env" "$env_file"
    rm -f "$tmp_env"
  elif [ "$SOURCE" = camera ] && [ ! -e "$(staged "$env_file")" ]; then
    log "WARNING: camera $cam has no input yet: its agent exits with status 78 until you set"
    log "  SMARTEDGE_EDGE_AGENT_ARGS=--device URI (or --images DIR, --realsense) in $env_file"
    log "  or re-run with --device $cam=URI"
  fi
done

# 4. systemd units
system_dir "$UNIT_DIR"
install_system_file "$DEPLOY_DIR/systemd/smartedge-edge-agent@.service" \
  "$UNIT_DIR/smartedge-edge-agent@.service"
if [ "$JETSON" = yes ]; then
  run install -d -m 0755 "$(staged "$UNIT_DIR/smartedge-edge-agent@.service.d")"
  install_system_file "$DEPLOY_DIR/systemd/jetson-gpu.conf" \
    "$UNIT_DIR/smartedge-edge-agent@.service.d/jetson-gpu.conf"
else
  remove_file "$UNIT_DIR/smartedge-edge-agent@.service.d/jetson-gpu.conf"
fi
units=()
for cam in "${CAMERAS[@]}"; do
  # With its own certificate, an agent connects as identity edge-<camera>: its client config
  # and a drop-in pointing ZENOH_CONFIG at it.
  if [ "$TLS_PER_CAMERA" = 1 ]; then
    install_identity "smartedge-edge-agent@$cam" "edge-$cam" "$BACKEND_HOST"
  else
    remove_identity "smartedge-edge-agent@$cam" "edge-$cam"
  fi
  units+=("smartedge-edge-agent@$cam.service")
done
units_start "${units[@]}"
report_runtime

log "done. Check with:"
log "  systemctl status 'smartedge-edge-agent@*'    journalctl -u 'smartedge-edge-agent@*' -f"
