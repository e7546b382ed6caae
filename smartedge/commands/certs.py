"""``smartedge certs``: the site's certificates and its router config with access control.

::

    smartedge certs --site SITE.yaml --out DIR [--router-host NAME_OR_IP ...] [--days N]

makes, in ``DIR``:

- ``ca.crt``, ``ca.key``: the site's CA (EC P-256), only when ``DIR`` has none (keep ``ca.key``
  offline once the certificates are made);
- ``router.crt``, ``router.key``: the router's certificate (CN ``router``), subjectAltName: the
  ``--router-host`` names and addresses, ``localhost`` and ``127.0.0.1``;
- ``<identity>.crt``, ``<identity>.key`` for every identity of :mod:`core.acl`
  (``edge-<camera>``, ``backend``, ``bridge-<robot>``, ``ros-<robot>``, ``viewer-<name>``), the
  certificate's CN being the identity;
- ``router-acl.json5``: the router config (``deploy/zenoh/router-tls.json5`` with the generated
  ``access_control`` block), installed by ``install-backend.sh --tls DIR``;
- ``clients/<identity>.json5``: a client config for each identity (``client-tls.json5`` with its
  certificate), e.g. for zenoh-bridge-ros2dds on the robot or a laptop's viewer.

Existing keys are kept (``--force`` makes new ones); a certificate is issued again from its
existing key when it is missing, does not verify against ``ca.crt``, names another CN, expires
within 30 days (half of ``--days`` when shorter), or (the router's) lacks a requested host.
Keys are written ``0600``. Uses the ``openssl`` command (Debian/Ubuntu package ``openssl``).
"""

from __future__ import annotations

import argparse
import ipaddress
import json
import logging
import os
import re
import secrets
import shutil
import subprocess
import sys
import tempfile
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any, Final

from core import acl
from core.site import Site, load_site
from protocol.errors import SmartedgeError
from robot_bridge.adapters.ros2 import RosConfig

log = logging.getLogger(__name__)

ROUTER_IDENTITY: Final = "router"
DEFAULT_TLS_DIR: Final = "/etc/smartedge/tls"
DEFAULT_DAYS: Final = 825
DEFAULT_CA_DAYS: Final = 3650
#: a certificate expiring sooner than this (or half its validity) is issued again
RENEW_BEFORE_S: Final = 30 * 86400
ROUTER_CONFIG_NAME: Final = "router-acl.json5"
CLIENTS_DIR: Final = "clients"
DEPLOY_ZENOH: Final = Path(__file__).resolve().parents[1] / "deploy" / "zenoh"
_EC: Final = ("-algorithm", "EC", "-pkeyopt", "ec_paramgen_curve:P-256")
_HOST_RE: Final = re.compile(r"^[A-Za-z0-9]([A-Za-z0-9.-]{0,252})$")

# used when the package runs without its checkout (deploy/ is not in the wheel): the TLS
# configs of deploy/zenoh without their comments
_FALLBACK_ROUTER: Final[dict[str, Any]] = {
    "mode": "router",
    "listen": {"endpoints": ["tls/0.0.0.0:7447"]},
    "connect": {"endpoints": []},
    "scouting": {"multicast": {"enabled": False}, "gossip": {"enabled": True}},
    "transport": {"link": {"protocols": ["tls"], "tls": {
        "root_ca_certificate": "/etc/smartedge/tls/ca.crt",
        "listen_certificate": "/etc/smartedge/tls/router.crt",
        "listen_private_key": "/etc/smartedge/tls/router.key",
        "enable_mtls": True,
        "close_link_on_expiration": True,
    }}},
}
_FALLBACK_CLIENT: Final[dict[str, Any]] = {
    "mode": "client",
    "connect": {"endpoints": ["tls/BACKEND_HOST:7447"]},
    "listen": {"endpoints": []},
    "scouting": {"multicast": {"enabled": False}},
    "transport": {"link": {"protocols": ["tls"], "tls": {
        "root_ca_certificate": "/etc/smartedge/tls/ca.crt",
        "enable_mtls": True,
        "connect_certificate": "/etc/smartedge/tls/client.crt",
        "connect_private_key": "/etc/smartedge/tls/client.key",
        "verify_name_on_connect": True,
        "close_link_on_expiration": True,
    }}},
}


class CertsError(SmartedgeError):
    """openssl is missing or failed, a file is inconsistent, or a generated config is invalid."""


def _openssl(*args: str, cwd: Path | None = None, check: bool = True
             ) -> subprocess.CompletedProcess[str]:
    exe = shutil.which("openssl")
    if exe is None:
        raise CertsError("the openssl command is not installed (Debian/Ubuntu: "
                         "sudo apt install openssl)")
    proc = subprocess.run([exe, *args], cwd=cwd, capture_output=True, text=True, timeout=60,
                          check=False)
    if check and proc.returncode != 0:
        why = (proc.stderr.strip().splitlines() or ["no message"])[-1]
        raise CertsError(f"openssl {args[0]} failed ({proc.returncode}): {why}")
    return proc


def _new_key(path: Path) -> None:
    """A new EC P-256 private key at ``path``, created 0600 before openssl writes into it."""
    if path.exists():
        path.chmod(0o600)
    else:
        os.close(os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600))
    _openssl("genpkey", *_EC, "-out", str(path))
    path.chmod(0o600)


def san_entries(hosts: Sequence[str]) -> list[str]:
    """subjectAltName entries of the router: ``DNS:`` names and ``IP:`` addresses of ``hosts``
    plus ``localhost`` and ``127.0.0.1``, without duplicates."""
    out: list[str] = []
    for host in (*hosts, "localhost", "127.0.0.1"):
        host = host.strip()
        try:
            entry = f"IP:{ipaddress.ip_address(host)}"
        except ValueError:
            if not _HOST_RE.match(host) or ".." in host:
                raise CertsError(f"--router-host {host!r}: not a host name or IP address") from None
            entry = f"DNS:{host.lower()}"
        if entry not in out:
            out.append(entry)
    return out


def _cert_sans(cert: Path) -> set[str]:
    proc = _openssl("x509", "-in", str(cert), "-noout", "-ext", "subjectAltName", check=False)
    found: set[str] = set()
    for item in re.split(r"[,\n]", proc.stdout):
        item = item.strip()
        if item.startswith("DNS:"):
            found.add(f"DNS:{item[4:].strip().lower()}")
        elif item.startswith("IP Address:"):
            found.add(f"IP:{ipaddress.ip_address(item.split(':', 1)[1].strip())}")
    return found


def _cert_problem(ca_crt: Path, key: Path, cert: Path, cn: str, days: int,
                  sans: Sequence[str] = ()) -> str | None:
    """Why ``cert`` must be issued again (``None``: it is fine). It expires too soon when less
    than 30 days are left, or half its ``days`` for shorter-lived certificates."""
    if not cert.exists():
        return "no certificate"
    if _openssl("verify", "-CAfile", str(ca_crt), str(cert), check=False).returncode != 0:
        return f"does not verify against {ca_crt.name}"
    subject = _openssl("x509", "-in", str(cert), "-noout", "-subject", "-nameopt", "RFC2253")
    if f"CN={cn}" not in subject.stdout.strip().removeprefix("subject=").split(","):
        return f"its CN is not {cn}"
    pub_cert = _openssl("x509", "-in", str(cert), "-noout", "-pubkey").stdout
    pub_key = _openssl("pkey", "-in", str(key), "-pubout").stdout
    if pub_cert.strip() != pub_key.strip():
        return f"it is not the certificate of {key.name}"
    renew_before_s = min(RENEW_BEFORE_S, days * 86400 // 2)
    if _openssl("x509", "-in", str(cert), "-noout", "-checkend", str(renew_before_s),
                check=False).returncode != 0:
        return f"it expires within {renew_before_s / 86400:g} days"
    missing = sorted(set(sans) - _cert_sans(cert))
    if missing:
        return f"subjectAltName lacks {', '.join(missing)}"
    return None


def _make_ca(out: Path, site: Site, days: int, progress: Callable[[str], None]) -> None:
    key, crt = out / "ca.key", out / "ca.crt"
    if key.exists() and crt.exists():
        progress(f"CA: using the existing {crt}")
        return
    if key.exists() or crt.exists():
        raise CertsError(f"{out}: has only one of ca.key and ca.crt; restore the other or "
                         "remove it to make a new CA (every certificate is then issued again)")
    _new_key(key)
    _openssl("req", "-x509", "-new", "-key", str(key), "-sha256", "-days", str(days),
             "-subj", f"/CN=smartedge {site.name} CA",
             "-addext", "basicConstraints=critical,CA:TRUE",
             "-addext", "keyUsage=critical,keyCertSign,cRLSign", "-out", str(crt))
    progress(f"CA: created {crt} (CN=smartedge {site.name} CA, {days} days); keep ca.key offline")


def _issue(out: Path, cn: str, days: int, extensions: str) -> None:
    with tempfile.TemporaryDirectory(prefix="smartedge-certs-") as tmp:
        csr, ext, crt = Path(tmp) / "req.csr", Path(tmp) / "req.ext", Path(tmp) / "leaf.crt"
        ext.write_text("basicConstraints=critical,CA:FALSE\n"
                       "keyUsage=critical,digitalSignature\n" + extensions)
        _openssl("req", "-new", "-key", str(out / f"{cn}.key"), "-subj", f"/CN={cn}",
                 "-out", str(csr))
        _openssl("x509", "-req", "-in", str(csr), "-CA", str(out / "ca.crt"),
                 "-CAkey", str(out / "ca.key"), "-set_serial", f"0x{secrets.token_hex(16)}",
                 "-days", str(days), "-sha256", "-extfile", str(ext), "-out", str(crt))
        crt.chmod(0o644)
        shutil.move(str(crt), out / f"{cn}.crt")


def _make_leaf(out: Path, cn: str, days: int, *, force: bool, sans: Sequence[str] = (),
               progress: Callable[[str], None]) -> None:
    key, crt = out / f"{cn}.key", out / f"{cn}.crt"
    usage = "serverAuth,clientAuth" if sans else "clientAuth"
    extensions = f"extendedKeyUsage={usage}\n" + (
        f"subjectAltName={','.join(sans)}\n" if sans else "")
    if force or not key.exists():
        _new_key(key)
        _issue(out, cn, days, extensions)
        progress(f"{cn}: new key and certificate {crt}")
        return
    key.chmod(0o600)
    problem = _cert_problem(out / "ca.crt", key, crt, cn, days, sans)
    if problem is None:
        progress(f"{cn}: kept {crt}")
        return
    _issue(out, cn, days, extensions)
    progress(f"{cn}: certificate issued again from the existing key ({problem})")


def _read_template(path: Path | None, fallback: Mapping[str, Any]) -> str:
    if path is not None:
        try:
            return path.read_text()
        except OSError as exc:
            raise CertsError(f"{path}: cannot read the template: {exc.strerror}") from None
    return json.dumps(fallback, indent=2) + "\n"


def _with_tls_dir(text: str, tls_dir: str) -> str:
    return text.replace(f"{DEFAULT_TLS_DIR}/", f"{tls_dir.rstrip('/')}/")


def router_config_text(template: str, block: Mapping[str, Any], *,
                       tls_dir: str = DEFAULT_TLS_DIR, note: str = "") -> str:
    """The router config: ``template`` (json5 text of one object, e.g. router-tls.json5) with
    ``access_control: block`` added as its last member and the certificate paths under
    ``tls_dir``. ``note``: a comment line above the block."""
    if re.search(r"^\s*\"?access_control\"?\s*:", template, flags=re.M):
        raise CertsError("the router template already has an access_control section")
    end = template.rstrip().rfind("}")
    if end < 0:
        raise CertsError("the router template is not a json5 object")
    head = template[:end].rstrip()
    if not head.endswith((",", "{")):
        head += ","
    body = acl.render_json5(block).replace("\n", "\n  ")
    comment = f"  // {note}\n" if note else ""
    text = f"{head}\n{comment}  access_control: {body},\n}}\n"
    return _with_tls_dir(text, tls_dir)


def client_config_text(template: str, identity: str, host: str, *,
                       tls_dir: str = DEFAULT_TLS_DIR) -> str:
    """A client config of ``identity``: ``template`` (client-tls.json5) connecting to ``host``
    with ``<tls_dir>/<identity>.crt`` and ``.key``."""
    endpoint_host = f"[{host}]" if ":" in host else host
    text = template.replace("tls/BACKEND_HOST:", f"tls/{endpoint_host}:")
    text = text.replace(f"{DEFAULT_TLS_DIR}/client.", f"{DEFAULT_TLS_DIR}/{identity}.")
    head = (f"// Zenoh client of identity {identity} (certificate CN), generated by smartedge "
            f"certs:\n// put ca.crt, {identity}.crt and {identity}.key in {tls_dir}.\n")
    return head + _with_tls_dir(text, tls_dir)


def _check_config(text: str, name: str) -> None:
    try:
        import zenoh
    except ImportError:
        log.info("zenoh is not installed: %s not checked", name)
        return
    try:
        zenoh.Config.from_json5(text)
    except Exception as exc:
        raise CertsError(f"{name}: zenoh rejects the generated config: {exc}") from None


def _write(path: Path, text: str, mode: int = 0o644) -> None:
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(text)
    tmp.chmod(mode)
    os.replace(tmp, path)


def make_certs(
    site: Site,
    out: Path,
    *,
    router_hosts: Sequence[str] = (),
    days: int = DEFAULT_DAYS,
    ca_days: int = DEFAULT_CA_DAYS,
    viewers: Sequence[str] = (),
    ros_keys: acl.RosKeys | Mapping[str, acl.RosKeys] | None = None,
    tls_dir: str = DEFAULT_TLS_DIR,
    router_template: Path | None = None,
    client_template: Path | None = None,
    force: bool = False,
    progress: Callable[[str], None] = log.info,
) -> list[str]:
    """Make (or complete) the site's certificates and configs in ``out`` (see the module
    docstring); returns the identities. ``ros_keys``: the robots' ROS keys (default: from the
    site's ``ros`` section). Templates default to ``deploy/zenoh/router-tls.json5`` and
    ``client-tls.json5`` of the checkout, or built-in copies without it."""
    if days < 1 or ca_days < 1:
        raise CertsError("--days and --ca-days must be >= 1")
    sans = san_entries(router_hosts)
    ros_keys = ros_keys or acl.site_ros_keys(site)
    block = acl.access_control(site, ros_keys, viewers)
    names = [subject["id"] for subject in block["subjects"]]
    if router_template is None and (DEPLOY_ZENOH / "router-tls.json5").exists():
        router_template = DEPLOY_ZENOH / "router-tls.json5"
    if client_template is None and (DEPLOY_ZENOH / "client-tls.json5").exists():
        client_template = DEPLOY_ZENOH / "client-tls.json5"
    router_text = router_config_text(
        _read_template(router_template, _FALLBACK_ROUTER), block, tls_dir=tls_dir,
        note=f"generated by smartedge certs from {site.source_path}: {len(names)} identities "
             "(certificate CNs), default deny; see docs/deployment.md")
    _check_config(router_text, ROUTER_CONFIG_NAME)

    created = not out.exists()
    out.mkdir(parents=True, exist_ok=True)
    if created:
        out.chmod(0o700)
    _make_ca(out, site, ca_days, progress)
    _make_leaf(out, ROUTER_IDENTITY, days, force=force, sans=sans, progress=progress)
    for name in names:
        _make_leaf(out, name, days, force=force, progress=progress)

    _write(out / ROUTER_CONFIG_NAME, router_text)
    progress(f"router config: {out / ROUTER_CONFIG_NAME} (TLS listen, access control: "
             f"{len(block['rules'])} rules for {len(names)} identities)")
    clients = out / CLIENTS_DIR
    clients.mkdir(exist_ok=True)
    client_template_text = _read_template(client_template, _FALLBACK_CLIENT)
    host = sans[0].split(":", 1)[1]
    for name in names:
        text = client_config_text(client_template_text, name, host, tls_dir=tls_dir)
        _check_config(text, f"{CLIENTS_DIR}/{name}.json5")
        _write(clients / f"{name}.json5", text)
    progress(f"client configs: {clients}/<identity>.json5 (router at {host})")
    return names


def build_parser() -> argparse.ArgumentParser:
    """The command line of ``smartedge certs``."""
    parser = argparse.ArgumentParser(
        prog="smartedge certs",
        description="Make the site's CA, the router's certificate, one certificate per service "
        "identity (CN = identity), and the router config with Zenoh access control "
        "(default deny; each identity puts only its own keys). Uses openssl.",
    )
    parser.add_argument("--site", required=True, metavar="SITE.yaml", help="the site file")
    parser.add_argument("--out", required=True, metavar="DIR",
                        help="directory of the CA, certificates, keys and configs")
    parser.add_argument("--router-host", action="append", default=[], metavar="NAME_OR_IP",
                        help="a name or address clients use for the router (repeatable; "
                        "localhost and 127.0.0.1 are always in); the first goes in the client "
                        "configs")
    parser.add_argument("--days", type=int, default=DEFAULT_DAYS,
                        help=f"validity of the certificates (default {DEFAULT_DAYS})")
    parser.add_argument("--ca-days", type=int, default=DEFAULT_CA_DAYS,
                        help=f"validity of a new CA (default {DEFAULT_CA_DAYS})")
    parser.add_argument("--viewer", action="append", default=[], metavar="NAME",
                        help="an extra viewer identity viewer-NAME (a laptop; repeatable)")
    parser.add_argument("--ros1", action="store_true",
                        help="also allow the robots' ROS 1 keys (zenoh-plugin-ros1)")
    parser.add_argument("--tls-dir", default=DEFAULT_TLS_DIR, metavar="PATH",
                        help=f"where the certificates are on the machines, written into the "
                        f"configs (default {DEFAULT_TLS_DIR})")
    parser.add_argument("--template", type=Path, metavar="FILE",
                        help="router config to add access control to (default "
                        "deploy/zenoh/router-tls.json5)")
    parser.add_argument("--force", action="store_true",
                        help="new keys for the router and every identity, even if they exist")
    return parser


def main(argv: Sequence[str]) -> int:
    """``smartedge certs``: 0 when done, 1 on an error (one line on stderr), 2 on usage."""
    args = build_parser().parse_args(list(argv))
    try:
        site = load_site(args.site)
        # the bridge's parser validates the ros section (errors name the file and key); the
        # ground floor's acl module then only reads the keys it names
        for robot_id in site.robots:
            RosConfig.from_site(site, robot_id)
        ros_keys = acl.site_ros_keys(site, ros1=args.ros1)
        names = make_certs(
            site, Path(args.out), router_hosts=args.router_host, days=args.days,
            ca_days=args.ca_days, viewers=args.viewer, ros_keys=ros_keys, tls_dir=args.tls_dir,
            router_template=args.template, force=args.force, progress=print,
        )
    except BrokenPipeError:
        raise
    except (SmartedgeError, OSError, subprocess.TimeoutExpired) as exc:
        print(f"smartedge certs: error: {exc}", file=sys.stderr)
        return 1
    print(f"done: {len(names)} identities in {args.out}: {', '.join(names)}")
    print("install: install-backend.sh --tls DIR (router, backend, bridges); "
          "install-edge.sh --tls DIR (edge-<camera>); see docs/deployment.md")
    return 0
