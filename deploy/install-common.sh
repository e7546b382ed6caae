# Shared helpers of install-edge.sh and install-backend.sh (sourced, not run).
#
# Every step that changes the machine goes through one of these functions, so that
#   --dry-run   prints each step ("would: ...") and changes nothing, and
#   --root DIR  writes the files under DIR instead of / (staging, tests) and skips the steps
#               that act on the running system (apt, useradd, systemctl, ownership).
# Paths given to the helpers are the live paths (/etc/smartedge/...); ROOT is prepended here.
# shellcheck shell=bash

SMARTEDGE_USER=smartedge
PREFIX=/opt/smartedge
ETC=/etc/smartedge
UNIT_DIR=/etc/systemd/system
STATE=/var/lib/smartedge

DRY_RUN=0
ROOT=/
SKIP_PIP=0
SKIP_APT=0
NO_START=0
PYTHON_BIN="${PYTHON:-python3}"
PACKAGE=""
DEPLOY_DIR="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
REPO_DIR="$(dirname "$DEPLOY_DIR")"

log() { printf '%s: %s\n' "$PROG" "$*"; }
die() { printf '%s: error: %s\n' "$PROG" "$*" >&2; exit 2; }

# Live path → path on the filesystem being written (ROOT prefix).
staged() { if [ "$ROOT" = / ]; then printf '%s' "$1"; else printf '%s%s' "${ROOT%/}" "$1"; fi; }
live_system() { [ "$ROOT" = / ]; }

# quote ARG...: the words as a shell would need them typed (single quotes only where needed).
quote() {
  local out="" a
  for a in "$@"; do
    if [[ "$a" =~ ^[A-Za-z0-9_@%+=:,./-]+$ ]]; then out+="$a "; else out+="'${a//\'/\'\\\'\'}' "; fi
  done
  printf '%s' "${out% }"
}

# run CMD...: a step on the files being installed (honours --dry-run).
run() {
  if [ "$DRY_RUN" = 1 ]; then log "would: $(quote "$@")"; return 0; fi
  log "+ $(quote "$@")"
  "$@"
}

# system CMD...: a step on the running system (apt, useradd, systemctl): skipped under --root.
system() {
  if ! live_system; then log "skip (--root $ROOT): $(quote "$@")"; return 0; fi
  run "$@"
}

# Owner flags for install(1): root:smartedge on the live system, the caller's own under --root.
owner_flags() { if live_system && [ "$DRY_RUN" = 0 ]; then printf -- '-o root -g %s' "$SMARTEDGE_USER"; fi; }

# install_dir MODE DIR
install_dir() {
  # shellcheck disable=SC2046
  run install -d -m "$1" $(owner_flags) "$(staged "$2")"
}

# system_dir DIR: a standard directory of the system (/etc/systemd/system): created only when
# staging under --root, never re-owned.
system_dir() {
  if ! live_system; then run install -d -m 0755 "$(staged "$1")"; fi
}

# install_file MODE SRC DEST: copy SRC to DEST (a live path), replacing what is there.
install_file() {
  [ -f "$2" ] || die "$2: no such file"
  # shellcheck disable=SC2046
  run install -m "$1" $(owner_flags) "$2" "$(staged "$3")"
}

# install_system_file SRC DEST: a root-owned 0644 file outside /etc/smartedge (units, drop-ins).
install_system_file() {
  [ -f "$1" ] || die "$1: no such file"
  run install -m 0644 "$1" "$(staged "$2")"
}

# install_rendered MODE SRC DEST SED-EXPR...: SRC with the sed expressions applied, to DEST.
install_rendered() {
  local mode="$1" src="$2" dest="$3" tmp
  shift 3
  [ -f "$src" ] || die "$src: no such file"
  if [ "$DRY_RUN" = 1 ]; then
    log "would: render $src → $(staged "$dest") (sed $(quote "$@"))"
    return 0
  fi
  tmp="$(mktemp)"
  local args=(-e '') e
  for e in "$@"; do args+=(-e "$e"); done
  sed "${args[@]}" "$src" > "$tmp"
  # shellcheck disable=SC2046
  run install -m "$mode" $(owner_flags) "$tmp" "$(staged "$dest")"
  rm -f "$tmp"
}

# install_if_missing MODE SRC DEST SED-EXPR...: like install_rendered, but never replaces an
# existing file (the administrator's edits survive re-runs).
install_if_missing() {
  if [ -e "$(staged "$3")" ]; then log "keep existing $(staged "$3")"; return 0; fi
  install_rendered "$@"
}

# remove_file DEST: delete a file this installer manages when it is no longer wanted.
remove_file() {
  if [ -e "$(staged "$1")" ]; then run rm -f "$(staged "$1")"; fi
}

# install_identity UNIT IDENTITY ROUTER_HOST: a service instance that connects as its own
# identity (a certificate from `smartedge certs` in $TLS_DIR, CN = IDENTITY): its certificate
# and key, its client config, and a drop-in pointing the unit's ZENOH_CONFIG at that config.
install_identity() {
  local unit="$1" identity="$2" host="$3" tmp
  local dropin="$UNIT_DIR/$unit.service.d/zenoh-identity.conf"
  install_file 0644 "$TLS_DIR/$identity.crt" "$ETC/tls/$identity.crt"
  install_file 0640 "$TLS_DIR/$identity.key" "$ETC/tls/$identity.key"
  install_rendered 0640 "$DEPLOY_DIR/zenoh/client-tls.json5" "$ETC/zenoh-client-$identity.json5" \
    "s/BACKEND_HOST/$host/g" "s|/etc/smartedge/tls/client\\.|$ETC/tls/$identity.|g"
  run install -d -m 0755 "$(staged "$(dirname "$dropin")")"
  tmp="$(mktemp)"
  printf '[Service]\nEnvironment=ZENOH_CONFIG=%s/zenoh-client-%s.json5\n' "$ETC" "$identity" > "$tmp"
  install_system_file "$tmp" "$dropin"
  rm -f "$tmp"
}

# remove_identity UNIT IDENTITY: undo install_identity (the unit uses the host's client config).
remove_identity() {
  remove_file "$UNIT_DIR/$1.service.d/zenoh-identity.conf"
  remove_file "$ETC/zenoh-client-$2.json5"
}

# remove_unit UNIT: stop, disable and delete a unit this installer manages when it is no longer
# wanted (a router unit not chosen, the viewer under --no-viewer).
remove_unit() {
  system systemctl disable --now "$1" 2>/dev/null || true
  remove_file "$UNIT_DIR/$1"
}

ensure_root_privileges() {
  if live_system && [ "$DRY_RUN" = 0 ] && [ "$(id -u)" -ne 0 ]; then
    die "run as root (sudo $PROG ...), or use --dry-run / --root DIR"
  fi
}

# The dedicated system user the units run as (no login, home = state directory).
ensure_user() {
  if live_system && getent passwd "$SMARTEDGE_USER" >/dev/null 2>&1; then
    log "user $SMARTEDGE_USER exists"
    return 0
  fi
  system useradd --system --user-group --home-dir "$STATE" --no-create-home \
    --shell /usr/sbin/nologin --comment "smartedge services" "$SMARTEDGE_USER"
}

# ensure_apt PACKAGE...: install the Debian packages that are missing.
ensure_apt() {
  local missing=() p
  if ! command -v dpkg-query >/dev/null 2>&1; then
    log "not a Debian-based system: make sure these are installed: $*"
    return 0
  fi
  for p in "$@"; do
    dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q 'install ok installed' || missing+=("$p")
  done
  if [ ${#missing[@]} -eq 0 ]; then log "system packages present: $*"; return 0; fi
  if [ "$SKIP_APT" = 1 ]; then log "skip (--skip-apt): apt-get install ${missing[*]}"; return 0; fi
  system apt-get update -qq
  system env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq "${missing[@]}"
}

# ensure_venv EXTRAS: /opt/smartedge as a venv with smartedge[EXTRAS] from $PACKAGE.
ensure_venv() {
  local extras="$1" venv
  venv="$(staged "$PREFIX")"
  if [ "$SKIP_PIP" = 1 ]; then log "skip (--skip-pip): venv $venv, pip install '$PACKAGE[$extras]'"; return 0; fi
  if [ ! -x "$venv/bin/python" ]; then
    run "$PYTHON_BIN" -m venv "$venv"
  else
    log "venv $venv exists"
  fi
  run "$venv/bin/python" -m pip install --quiet --upgrade pip
  run "$venv/bin/python" -m pip install --quiet --upgrade "$PACKAGE[$extras]"
}

# default_package: this checkout when the script runs from one, else a wheel must be given.
default_package() {
  if [ -z "$PACKAGE" ]; then
    [ -f "$REPO_DIR/pyproject.toml" ] || die "--package WHEEL_OR_SOURCE_DIR is required"
    PACKAGE="$REPO_DIR"
  fi
  case "$PACKAGE" in
    *.whl | /* | ./* | ../*) [ -e "$PACKAGE" ] || die "$PACKAGE: no such file or directory" ;;
  esac
  if [ -d "$PACKAGE" ]; then PACKAGE="$(cd "$PACKAGE" && pwd)"; fi
  if [ -f "$PACKAGE" ]; then PACKAGE="$(cd "$(dirname "$PACKAGE")" && pwd)/$(basename "$PACKAGE")"; fi
}

# check_site FILE KIND ID...: validate the site file with the installed smartedge and check that
# every camera (KIND=cameras) or robot (KIND=robots) id is in it, before anything is configured.
check_site() {
  local file="$1" kind="$2" py
  shift 2
  py="$(staged "$PREFIX")/bin/python"
  if [ "$DRY_RUN" = 1 ] || [ ! -x "$py" ]; then
    log "skip site check (no installed smartedge at $(staged "$PREFIX") yet)"
    return 0
  fi
  log "checking $file and the $kind ids: $*"
  "$py" - "$file" "$kind" "$@" <<'PY' || die "site check failed: nothing configured"
import sys
from protocol.errors import SiteConfigError
from core.site import load_site
path, kind, ids = sys.argv[1], sys.argv[2], sys.argv[3:]
try:
    site = load_site(path)
except SiteConfigError as exc:
    sys.exit(f"{exc}")
known = site.cameras if kind == "cameras" else site.robots
missing = [i for i in ids if i not in known]
if missing:
    sys.exit(f"{path}: {kind} {missing} not in the site file; it has {sorted(known)}")
print(f"site {site.name!r}: {len(site.cameras)} cameras, robots {sorted(site.robots)}: ok")
PY
}

# units_start UNIT...: enable (and start or restart, unless --no-start) systemd units.
units_start() {
  system systemctl daemon-reload
  if [ "$NO_START" = 1 ]; then
    system systemctl enable "$@"
  else
    system systemctl enable "$@"
    # restart (not start): a re-run picks up new code and configuration.
    system systemctl restart "$@"
  fi
}

# Options both scripts take; returns 1 when $1 is not one of them. Sets SHIFT_BY.
common_option() {
  SHIFT_BY=1
  case "$1" in
    --dry-run) DRY_RUN=1 ;;
    --root) [ -n "${2:-}" ] || die "--root needs a directory"; ROOT="$2"; SHIFT_BY=2 ;;
    --skip-pip) SKIP_PIP=1 ;;
    --skip-apt) SKIP_APT=1 ;;
    --no-start) NO_START=1 ;;
    --python) [ -n "${2:-}" ] || die "--python needs an interpreter"; PYTHON_BIN="$2"; SHIFT_BY=2 ;;
    --package) [ -n "${2:-}" ] || die "--package needs a wheel or directory"; PACKAGE="$2"; SHIFT_BY=2 ;;
    *) return 1 ;;
  esac
  return 0
}

normalize_root() {
  if [ "$ROOT" != / ]; then
    if [ "$DRY_RUN" = 0 ]; then mkdir -p "$ROOT"; fi
    [ "$DRY_RUN" = 1 ] || ROOT="$(cd "$ROOT" && pwd)"
  fi
}
