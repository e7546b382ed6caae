#!/usr/bin/env bash
# Install smartedge on the backend host: a venv in /opt/smartedge with the `backend` and `bridge`
# extras (plus libusb-1.0-0, which open3d needs at import), the system user `smartedge`,
# /etc/smartedge (site file, zenoh router and client configs, settings), the site's Zenoh router
# (`smartedge router` by default; zenohd or the backend's own session when asked),
# smartedge-backend.service, smartedge-mapper.service
# (the semantic map), smartedge-viewer.service
# (Rerun drawing of the site; optional, --no-viewer) and one smartedge-robot-bridge@<robot>.service
# per robot id. Safe to re-run. Walkthrough: docs/deployment.md.
set -euo pipefail
PROG="install-backend.sh"
# shellcheck source=deploy/install-common.sh
. "$(dirname "${BASH_SOURCE[0]}")/install-common.sh"

usage() {
  cat <<USAGE
Usage: sudo $PROG --site SITE.yaml [options] [ROBOT_ID...]

Install smartedge[backend,bridge], the Zenoh router, the backend service, the viewer service
(draws the site into Rerun) and one robot-bridge service per ROBOT_ID (ids of the site file's
robots section).

Required:
  --site FILE              site file; installed as $ETC/site.yaml

Options:
  --router smartedge|zenohd|backend|external
                           who is the site's Zenoh router (default: smartedge, or zenohd when
                           --zenohd PATH is given):
                             smartedge smartedge-router.service runs \`smartedge router\`
                                       with $ETC/zenoh-router.json5: from the
                                       smartedge package itself, nothing else to install
                                       (the backend can restart without dropping the edge
                                       boards' links)
                             zenohd    smartedge-zenohd.service runs zenohd with the same
                                       config (zenohd installed separately, see
                                       docs/deployment.md)
                             backend   the backend's own session is the router (no router unit)
                             external  a router elsewhere (--router-host); nothing here
  --zenohd PATH            zenohd executable for --router zenohd (default: zenohd on PATH)
  --router-host HOST       router the local services connect to (default 127.0.0.1)
  --tls DIR                Zenoh over TLS (mTLS): DIR holds ca.crt, router.crt, router.key and,
                           for the local services, client.crt, client.key (see docs). A DIR made
                           by \`smartedge certs\` (backend.crt, bridge-<robot>.crt,
                           router-acl.json5) installs the router config with access control
                           and gives each robot bridge its own certificate
  --adapter ros2|sim       SMARTEDGE_ADAPTER for a new smartedge.env (default: ros2)
  --rerun SINK             the viewer's Rerun sink, SMARTEDGE_RERUN for a new smartedge.env
                           (save:PATH.rrd, serve, connect:URL; default: a recording under
                           $STATE/recordings)
  --no-viewer              do not install smartedge-viewer.service (one installed by an earlier
                           run is stopped, disabled and removed)
  --with FILE              another file the site file refers to; repeatable
  --package SPEC           wheel file or source directory to pip install with [backend,bridge]
                           (default: the checkout this script is in)
  --python PY              interpreter that creates the venv (default: python3)
  --skip-pip               do not create or update the venv in $PREFIX
  --skip-apt               do not install missing Debian packages
  --no-start               enable the units, do not (re)start them
  --root DIR               install under DIR instead of / (staging, tests): no apt, useradd,
                           chown or systemctl
  --dry-run                print every step, change nothing
  -h, --help               this help

Example:
  sudo deploy/install-backend.sh --site lab.yaml hsr1
USAGE
}

SITE=""
ROUTER=""
ZENOHD=""
ROUTER_HOST=127.0.0.1
TLS_DIR=""
ADAPTER=ros2
RERUN=""
VIEWER=1
EXTRA_FILES=()
ROBOTS=()
while [ $# -gt 0 ]; do
  if common_option "$@"; then shift "$SHIFT_BY"; continue; fi
  case "$1" in
    -h | --help) usage; exit 0 ;;
    --site) SITE="${2:?--site needs a file}"; shift 2 ;;
    --router) ROUTER="${2:?--router needs smartedge, zenohd, backend or external}"; shift 2 ;;
    --zenohd) ZENOHD="${2:?--zenohd needs a path}"; shift 2 ;;
    --router-host) ROUTER_HOST="${2:?--router-host needs a host}"; shift 2 ;;
    --tls) TLS_DIR="${2:?--tls needs a directory}"; shift 2 ;;
    --adapter) ADAPTER="${2:?--adapter needs ros2 or sim}"; shift 2 ;;
    --rerun) RERUN="${2:?--rerun needs a sink}"; shift 2 ;;
    --no-viewer) VIEWER=0; shift ;;
    --with) EXTRA_FILES+=("${2:?--with needs a file}"); shift 2 ;;
    -*) usage >&2; die "unknown option $1" ;;
    *) ROBOTS+=("$1"); shift ;;
  esac
done

[ -n "$SITE" ] || { usage >&2; die "--site is required"; }
[ -f "$SITE" ] || die "$SITE: no such file"
[[ "$ROUTER_HOST" =~ ^[A-Za-z0-9._:-]+$ ]] || die "--router-host $ROUTER_HOST: not a host name or address"
for robot in ${ROBOTS[@]+"${ROBOTS[@]}"}; do
  [[ "$robot" =~ ^[A-Za-z0-9_.-]+$ ]] || die "robot id $robot: only [A-Za-z0-9_.-] allowed"
done
case "$ADAPTER" in ros2 | sim) ;; *) die "--adapter $ADAPTER: expected ros2 or sim" ;; esac
# The router and why (printed below): zenohd only when asked for, since `smartedge router` comes
# with the package this script installs and zenohd is in no package registry a lab has by default.
if [ -z "$ROUTER" ]; then
  if [ -n "$ZENOHD" ]; then ROUTER=zenohd; router_why="--zenohd $ZENOHD given"
  else ROUTER=smartedge; router_why="the default; zenohd not requested"; fi
else
  router_why="--router $ROUTER"
fi
case "$ROUTER" in
  zenohd)
    [ -n "$ZENOHD" ] || ZENOHD="$(command -v zenohd || true)"
    [ -n "$ZENOHD" ] || die "--router zenohd: zenohd not found (install it, see docs/deployment.md, or give --zenohd PATH; --router smartedge needs nothing else)"
    [ -x "$ZENOHD" ] || die "--zenohd $ZENOHD: not an executable file"
    ;;
  smartedge | backend | external)
    [ -z "$ZENOHD" ] || die "--zenohd goes with --router zenohd, not --router $ROUTER"
    ;;
  *) die "--router $ROUTER: expected smartedge, zenohd, backend or external" ;;
esac
case "$ROUTER" in
  smartedge) router_note="smartedge-router.service (smartedge router, from the smartedge package; $router_why)" ;;
  zenohd) router_note="smartedge-zenohd.service (zenohd $ZENOHD; $router_why)" ;;
  backend) router_note="the backend's own session, smartedge-backend.service with zenoh-router.json5 ($router_why)" ;;
  external) router_note="external, at $ROUTER_HOST; none runs here ($router_why)" ;;
esac
[ "$ROUTER" = external ] || [ "$ROUTER_HOST" = 127.0.0.1 ] \
  || die "--router-host only goes with --router external"
[ "$VIEWER" = 1 ] || [ -z "$RERUN" ] || die "--rerun configures the viewer: not with --no-viewer"
TLS_CLIENT=client
TLS_ACL=0
if [ -n "$TLS_DIR" ]; then
  # From `smartedge certs`: the identity `backend` and the generated router config with access
  # control, under which each robot bridge needs its own identity (bridge-<robot>).
  [ -f "$TLS_DIR/backend.crt" ] && TLS_CLIENT=backend
  [ -f "$TLS_DIR/router-acl.json5" ] && TLS_ACL=1
  for f in ca.crt router.crt router.key "$TLS_CLIENT.crt" "$TLS_CLIENT.key"; do
    [ -f "$TLS_DIR/$f" ] || die "--tls: $TLS_DIR/$f missing"
  done
  if [ "$TLS_ACL" = 1 ]; then
    for robot in ${ROBOTS[@]+"${ROBOTS[@]}"}; do
      for f in "bridge-$robot.crt" "bridge-$robot.key"; do
        [ -f "$TLS_DIR/$f" ] || die "--tls: $TLS_DIR/$f missing: router-acl.json5 lets robot $robot's bridge in only with its own certificate (smartedge certs --site SITE --out $TLS_DIR)"
      done
    done
  fi
fi
default_package
normalize_root
ensure_root_privileges
[ "$DRY_RUN" = 1 ] && log "dry run: nothing is changed"
viewer_note=""
[ "$VIEWER" = 1 ] || viewer_note=", no viewer"
log "backend host: router $ROUTER, robots ${ROBOTS[*]:-none}$viewer_note, package $PACKAGE[backend,bridge]"
log "router: $router_note"

# 1. system packages (open3d needs libusb-1.0 at import time; gcc compiles the pose solver's
#    kernels once, docs/deployment.md) and user
ensure_apt python3-venv libusb-1.0-0 libgomp1 gcc
ensure_user

# 2. python environment
ensure_venv backend,bridge

check_site "$SITE" robots ${ROBOTS[@]+"${ROBOTS[@]}"}

# 3. configuration
install_dir 0750 "$ETC"
install_file 0640 "$SITE" "$ETC/site.yaml"
for f in ${EXTRA_FILES[@]+"${EXTRA_FILES[@]}"}; do install_file 0640 "$f" "$ETC/$(basename "$f")"; done
if [ -n "$TLS_DIR" ]; then
  install_dir 0750 "$ETC/tls"
  install_file 0644 "$TLS_DIR/ca.crt" "$ETC/tls/ca.crt"
  install_file 0644 "$TLS_DIR/router.crt" "$ETC/tls/router.crt"
  install_file 0640 "$TLS_DIR/router.key" "$ETC/tls/router.key"
  install_file 0644 "$TLS_DIR/$TLS_CLIENT.crt" "$ETC/tls/client.crt"
  install_file 0640 "$TLS_DIR/$TLS_CLIENT.key" "$ETC/tls/client.key"
  router_template=router-tls.json5
  client_template=client-tls.json5
else
  router_template=router.json5
  client_template=client.json5
fi
if [ "$ROUTER" != external ] && [ "$TLS_ACL" = 1 ]; then
  log "router config: $TLS_DIR/router-acl.json5 (TLS with access control by certificate name)"
  install_rendered 0640 "$TLS_DIR/router-acl.json5" "$ETC/zenoh-router.json5"
elif [ "$ROUTER" != external ]; then
  install_rendered 0640 "$DEPLOY_DIR/zenoh/$router_template" "$ETC/zenoh-router.json5"
else
  remove_file "$ETC/zenoh-router.json5"
fi
# The local services (viewer, robot bridges; the backend unless it is the router) are clients too.
install_rendered 0640 "$DEPLOY_DIR/zenoh/$client_template" "$ETC/zenoh-client.json5" \
  "s/BACKEND_HOST/$ROUTER_HOST/g"
env_edits=("s/^SMARTEDGE_ADAPTER=.*/SMARTEDGE_ADAPTER=$ADAPTER/")
[ -z "$RERUN" ] || env_edits+=("s|^SMARTEDGE_RERUN=.*|SMARTEDGE_RERUN=$RERUN|")
install_if_missing 0640 "$DEPLOY_DIR/smartedge.env.example" "$ETC/smartedge.env" "${env_edits[@]}"

# 4. systemd units
system_dir "$UNIT_DIR"
dropin="$UNIT_DIR/smartedge-backend.service.d"
units=()
# One router unit at most: the one chosen is installed, the other is stopped, disabled and
# removed (both would listen on port 7447).
zenohd_path_dropin="$UNIT_DIR/smartedge-zenohd.service.d/zenohd-path.conf"
if [ "$ROUTER" = smartedge ]; then
  install_system_file "$DEPLOY_DIR/systemd/smartedge-router.service" "$UNIT_DIR/smartedge-router.service"
  units+=(smartedge-router.service)
else
  remove_unit smartedge-router.service
fi
if [ "$ROUTER" = zenohd ]; then
  install_system_file "$DEPLOY_DIR/systemd/smartedge-zenohd.service" "$UNIT_DIR/smartedge-zenohd.service"
  if [ "$ZENOHD" != /usr/bin/zenohd ]; then
    run install -d -m 0755 "$(staged "$UNIT_DIR/smartedge-zenohd.service.d")"
    tmp="$(mktemp)"
    printf '[Service]\nExecStart=\nExecStart=%s -c ${ZENOHD_CONFIG}\n' "$ZENOHD" > "$tmp"
    install_system_file "$tmp" "$zenohd_path_dropin"
    rm -f "$tmp"
  else
    remove_file "$zenohd_path_dropin"
  fi
  units+=(smartedge-zenohd.service)
else
  remove_unit smartedge-zenohd.service
  remove_file "$zenohd_path_dropin"
fi
install_system_file "$DEPLOY_DIR/systemd/smartedge-backend.service" "$UNIT_DIR/smartedge-backend.service"
if [ "$ROUTER" = backend ]; then
  # The backend's own session listens on tcp/0.0.0.0:7447 (or tls/) as the router.
  run install -d -m 0755 "$(staged "$dropin")"
  tmp="$(mktemp)"
  printf '[Service]\nEnvironment=ZENOH_CONFIG=%s/zenoh-router.json5\n' "$ETC" > "$tmp"
  install_system_file "$tmp" "$dropin/zenoh-router.conf"
  rm -f "$tmp"
else
  remove_file "$dropin/zenoh-router.conf"
fi
units+=(smartedge-backend.service)
# The mapper: the semantic map, a unit of its own so that ICP never delays a pose estimate.
install_system_file "$DEPLOY_DIR/systemd/smartedge-mapper.service" "$UNIT_DIR/smartedge-mapper.service"
units+=(smartedge-mapper.service)
# The viewer: a unit of its own, so that it can fail or be left out without touching the backend.
if [ "$VIEWER" = 1 ]; then
  install_system_file "$DEPLOY_DIR/systemd/smartedge-viewer.service" "$UNIT_DIR/smartedge-viewer.service"
  units+=(smartedge-viewer.service)
else
  remove_unit smartedge-viewer.service
fi
install_system_file "$DEPLOY_DIR/systemd/smartedge-robot-bridge@.service" \
  "$UNIT_DIR/smartedge-robot-bridge@.service"
for robot in ${ROBOTS[@]+"${ROBOTS[@]}"}; do
  # With its own certificate (smartedge certs), a bridge connects as identity bridge-<robot>: its
  # client config and a drop-in pointing ZENOH_CONFIG at it.
  if [ -n "$TLS_DIR" ] && [ -f "$TLS_DIR/bridge-$robot.crt" ] && [ -f "$TLS_DIR/bridge-$robot.key" ]; then
    install_identity "smartedge-robot-bridge@$robot" "bridge-$robot" "$ROUTER_HOST"
  else
    remove_identity "smartedge-robot-bridge@$robot" "bridge-$robot"
  fi
  units+=("smartedge-robot-bridge@$robot.service")
done
units_start "${units[@]}"

log "done. Check with:"
log "  systemctl status 'smartedge-*'    journalctl -u smartedge-backend -f"
log "  mapper: journalctl -u smartedge-mapper (map kept in /var/lib/smartedge/semantic_map.npz)"
log "router: $router_note"
[ "$ROUTER" != smartedge ] || log "  router: journalctl -u smartedge-router"
[ "$ROUTER" != zenohd ] || log "  zenohd: journalctl -u smartedge-zenohd"
[ "$VIEWER" = 0 ] || log "  viewer: journalctl -u smartedge-viewer (Rerun sink: SMARTEDGE_RERUN)"
