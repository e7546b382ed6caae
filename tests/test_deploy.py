"""The deployment kit (deploy/): zenoh configs load in the installed zenoh and carry traffic (TLS
included), the systemd units are complete, hardened and accepted by systemd, and the install
scripts do what they print without touching the machine (everything runs under a temp --root)."""

from __future__ import annotations

import contextlib
import json
import os
import re
import shlex
import shutil
import stat
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

from core.runtime import EXIT_CONFIG
from smartedge.cli import COMMANDS
from tests.conftest import EXAMPLE_SITE, REPO_ROOT, free_port, wait_until

DEPLOY = REPO_ROOT / "deploy"
ZENOH_DIR = DEPLOY / "zenoh"
UNIT_DIR = DEPLOY / "systemd"
SMARTEDGE_BIN = "/opt/smartedge/bin/smartedge"
SERVICE_UNITS = {
    "smartedge-edge-agent@.service": "edge-agent",
    "smartedge-backend.service": "backend",
    "smartedge-mapper.service": "mapper",
    "smartedge-robot-bridge@.service": "robot-bridge",
    "smartedge-viewer.service": "viewer",
}
ROUTER_UNITS = ("smartedge-router.service", "smartedge-zenohd.service")
ALL_UNITS = (*SERVICE_UNITS, *ROUTER_UNITS)
#: file → (mode, connect endpoints, listen endpoints) after BACKEND_HOST → 127.0.0.1
ZENOH_EXPECTED = {
    "router.json5": ("router", [], ["tcp/0.0.0.0:7447"]),
    "client.json5": ("client", ["tcp/127.0.0.1:7447"], []),
    "router-tls.json5": ("router", [], ["tls/0.0.0.0:7447"]),
    "client-tls.json5": ("client", ["tls/127.0.0.1:7447"], []),
}


# --------------------------------------------------------------------------------------------
# zenoh configs
# --------------------------------------------------------------------------------------------


def _render(name: str, tmp_path: Path, **subst: str) -> Path:
    text = (ZENOH_DIR / name).read_text()
    subst = {"BACKEND_HOST": "127.0.0.1", **subst}
    for old, new in subst.items():
        text = text.replace(old, new)
    out = tmp_path / f"rendered-{len(list(tmp_path.glob('rendered-*')))}-{name}"
    out.write_text(text)
    return out


def test_every_zenoh_config_has_expectations() -> None:
    assert sorted(p.name for p in ZENOH_DIR.glob("*.json5")) == sorted(ZENOH_EXPECTED)


@pytest.mark.parametrize("name", sorted(ZENOH_EXPECTED))
def test_zenoh_config_loads_with_expected_mode_and_endpoints(name: str, tmp_path: Path) -> None:
    zenoh = pytest.importorskip("zenoh")
    conf = zenoh.Config.from_file(str(_render(name, tmp_path)))
    mode, connect, listen = ZENOH_EXPECTED[name]
    assert json.loads(conf.get_json("mode")) == mode
    assert json.loads(conf.get_json("connect/endpoints")) == connect
    assert json.loads(conf.get_json("listen/endpoints")) == listen
    assert json.loads(conf.get_json("scouting/multicast/enabled")) is False
    if "tls" in name:
        tls = json.loads(conf.get_json("transport/link/tls"))
        assert json.loads(conf.get_json("transport/link/protocols")) == ["tls"]
        assert tls["enable_mtls"] is True
        assert tls["root_ca_certificate"] == "/etc/smartedge/tls/ca.crt"
        side = "listen" if mode == "router" else "connect"
        assert tls[f"{side}_certificate"].startswith("/etc/smartedge/tls/")
        assert tls[f"{side}_private_key"].startswith("/etc/smartedge/tls/")


def test_zenoh_rejects_unknown_keys(tmp_path: Path) -> None:
    """Loading is a real check of key names: zenoh 0.x's TLS names no longer load."""
    zenoh = pytest.importorskip("zenoh")
    bad = tmp_path / "old.json5"
    bad.write_text('{mode: "router", transport: {link: {tls: {server_private_key: "k.pem"}}}}')
    with pytest.raises(Exception, match="server_private_key"):
        zenoh.Config.from_file(str(bad))


def _pub_sub_works(zenoh, router_conf, client_conf) -> bool:
    got: list[bytes] = []
    with zenoh.open(router_conf) as router:
        sub = router.declare_subscriber("deploytest/**", lambda s: got.append(s.payload.to_bytes()))
        try:
            client = zenoh.open(client_conf)
        except Exception:
            return False
        try:
            pub = client.declare_publisher("deploytest/x")
            wait_until(lambda: (pub.put(b"hello"), bool(got))[1], timeout_s=5.0, step_s=0.1)
        finally:
            client.close()
        sub.undeclare()
    return got[:1] == [b"hello"]


def _on_port(name: str, tmp_path: Path, port: int, **subst: str):
    import zenoh

    path = _render(
        name,
        tmp_path,
        **{"0.0.0.0:7447": f"127.0.0.1:{port}", "127.0.0.1:7447": f"127.0.0.1:{port}", **subst},
    )
    return zenoh.Config.from_file(str(path))


def test_plain_router_and_client_configs_carry_traffic(tmp_path: Path) -> None:
    zenoh = pytest.importorskip("zenoh")
    port = free_port()
    assert _pub_sub_works(
        zenoh,
        _on_port("router.json5", tmp_path, port),
        _on_port("client.json5", tmp_path, port),
    )


def _openssl(*args: str, cwd: Path) -> None:
    subprocess.run(["openssl", *args], cwd=cwd, check=True, capture_output=True, timeout=30)


def _make_pki(d: Path, ca: str, leaves: dict[str, str]) -> None:
    """The commands of docs/deployment.md: an EC P-256 CA and leaf certificates signed by it.
    ``leaves``: name → extension text (subjectAltName, extendedKeyUsage)."""
    d.mkdir(parents=True, exist_ok=True)
    ec = ("-algorithm", "EC", "-pkeyopt", "ec_paramgen_curve:P-256")
    _openssl("genpkey", *ec, "-out", f"{ca}.key", cwd=d)
    _openssl(
        "req", "-x509", "-new", "-key", f"{ca}.key", "-sha256", "-days", "30",
        "-subj", f"/CN={ca}", "-addext", "basicConstraints=critical,CA:TRUE",
        "-addext", "keyUsage=critical,keyCertSign,cRLSign", "-out", f"{ca}.crt",
        cwd=d,
    )  # fmt: skip
    for name, ext in leaves.items():
        (d / f"{name}.ext").write_text(
            "basicConstraints=critical,CA:FALSE\nkeyUsage=critical,digitalSignature\n" + ext
        )
        _openssl("genpkey", *ec, "-out", f"{name}.key", cwd=d)
        _openssl("req", "-new", "-key", f"{name}.key", "-subj", f"/CN={name}",
                 "-out", f"{name}.csr", cwd=d)  # fmt: skip
        _openssl(
            "x509", "-req", "-in", f"{name}.csr", "-CA", f"{ca}.crt", "-CAkey", f"{ca}.key",
            "-CAcreateserial", "-days", "30", "-sha256", "-extfile", f"{name}.ext",
            "-out", f"{name}.crt",
            cwd=d,
        )  # fmt: skip


@pytest.mark.skipif(shutil.which("openssl") is None, reason="openssl not installed")
def test_tls_configs_handshake_with_mtls_and_refuse_foreign_certificates(tmp_path: Path) -> None:
    zenoh = pytest.importorskip("zenoh")
    pki = tmp_path / "pki"
    _make_pki(
        pki,
        "ca",
        {
            "router": "extendedKeyUsage=serverAuth\n"
            "subjectAltName=DNS:backend.lab,DNS:localhost,IP:127.0.0.1\n",
            "client": "extendedKeyUsage=clientAuth\n",
        },
    )
    _make_pki(pki / "rogue", "rogueca", {"client": "extendedKeyUsage=clientAuth\n"})
    tls = {"/etc/smartedge/tls/": f"{pki}/"}
    port = free_port()
    router = _on_port("router-tls.json5", tmp_path, port, **tls)
    assert _pub_sub_works(zenoh, router, _on_port("client-tls.json5", tmp_path, port, **tls))

    # mTLS: a certificate from another CA is refused.
    port = free_port()
    rogue = {
        "/etc/smartedge/tls/ca.crt": f"{pki}/ca.crt",
        "/etc/smartedge/tls/client.": f"{pki}/rogue/client.",
    }
    assert not _pub_sub_works(
        zenoh,
        _on_port("router-tls.json5", tmp_path, port, **tls),
        _on_port("client-tls.json5", tmp_path, port, **rogue),
    )


# --------------------------------------------------------------------------------------------
# systemd units
# --------------------------------------------------------------------------------------------


def parse_unit(path: Path) -> dict[str, dict[str, list[str]]]:
    """A systemd unit as {section: {key: [values in order]}} (keys may repeat)."""
    sections: dict[str, dict[str, list[str]]] = {}
    current: dict[str, list[str]] | None = None
    for lineno, raw in enumerate(path.read_text().splitlines(), 1):
        line = raw.strip()
        if not line or line.startswith(("#", ";")):
            continue
        if line.startswith("[") and line.endswith("]"):
            current = sections.setdefault(line[1:-1], {})
            continue
        assert current is not None, f"{path.name}:{lineno}: key outside a section"
        assert "=" in line, f"{path.name}:{lineno}: not KEY=VALUE: {line!r}"
        assert not line.endswith("\\"), f"{path.name}:{lineno}: keep ExecStart on one line"
        key, value = line.split("=", 1)
        current.setdefault(key.strip(), []).append(value.strip())
    return sections


def _one(unit: dict[str, dict[str, list[str]]], section: str, key: str) -> str:
    values = unit[section].get(key, [])
    assert len(values) == 1, f"[{section}] {key}: expected one value, got {values}"
    return values[0]


def _env_defaults(unit: dict[str, dict[str, list[str]]]) -> dict[str, str]:
    env: dict[str, str] = {}
    for assignment in unit["Service"].get("Environment", []):
        for word in shlex.split(assignment):
            k, v = word.split("=", 1)
            env[k] = v
    return env


def _example_env() -> dict[str, str]:
    env = {}
    for line in (DEPLOY / "smartedge.env.example").read_text().splitlines():
        if line and not line.startswith("#"):
            k, v = line.split("=", 1)
            env[k] = v
    return env


@pytest.mark.parametrize("name", sorted(SERVICE_UNITS))
def test_service_unit_has_the_required_keys(name: str) -> None:
    unit = parse_unit(UNIT_DIR / name)
    assert _one(unit, "Service", "Type") == "notify"
    assert _one(unit, "Service", "NotifyAccess") == "main"
    assert re.fullmatch(r"\d+s", _one(unit, "Service", "WatchdogSec"))
    assert _one(unit, "Service", "Restart") == "on-failure"
    assert re.fullmatch(r"\d+s", _one(unit, "Service", "RestartSec"))
    assert _one(unit, "Service", "User") == "smartedge"
    files = unit["Service"]["EnvironmentFile"]
    assert files[0] == "/etc/smartedge/smartedge.env"
    assert len(files) == 2 and files[1].startswith("-/etc/smartedge/")
    assert _one(unit, "Install", "WantedBy") == "multi-user.target"
    assert "smartedge" in _one(unit, "Service", "StateDirectory").split()
    assert _one(unit, "Service", "LogsDirectory") == "smartedge"
    assert _env_defaults(unit)["ZENOH_CONFIG"] == "/etc/smartedge/zenoh-client.json5"


def _exec_words(name: str) -> list[str]:
    return shlex.split(_one(parse_unit(UNIT_DIR / name), "Service", "ExecStart"))


def _subcommand(words: list[str]) -> tuple[str, list[str]]:
    """(subcommand, its arguments) of a ``smartedge [--log-level X] SUB ARGS`` command line."""
    assert words[0] == SMARTEDGE_BIN
    i = 1
    while words[i].startswith("-"):
        i += 2  # global options all take a value (--log-level LEVEL)
    return words[i], words[i + 1 :]


@pytest.mark.parametrize("name", sorted(SERVICE_UNITS))
def test_exec_start_runs_a_real_subcommand_with_its_flags(name: str) -> None:
    sub, args = _subcommand(_exec_words(name))
    assert sub == SERVICE_UNITS[name]
    assert sub in COMMANDS
    assert args[:2] == ["--site", "${SMARTEDGE_SITE}"]
    instance_flag = {"edge-agent": "--camera", "robot-bridge": "--robot"}.get(sub)
    if instance_flag:
        assert args[args.index(instance_flag) + 1] == "%i"
    if sub == "robot-bridge":
        assert args[args.index("--adapter") + 1] == "${SMARTEDGE_ADAPTER}"
    if sub == "edge-agent":
        assert args[args.index("--source") + 1] == "${SMARTEDGE_SOURCE}"
    if sub == "viewer":
        assert args[args.index("--rerun") + 1] == "${SMARTEDGE_RERUN}"
    else:
        assert "--rerun" not in args  # drawing in Rerun is the viewer's job alone


@pytest.mark.parametrize("name", ALL_UNITS)
def test_exec_start_variables_are_defined(name: str) -> None:
    """``${X}`` is one argument and must not be empty: the unit defines a default. ``$X`` may be
    empty (zero words) but must be documented in smartedge.env.example."""
    unit = parse_unit(UNIT_DIR / name)
    exec_start = _one(unit, "Service", "ExecStart")
    defaults, example = _env_defaults(unit), _example_env()
    for var in re.findall(r"\$\{(\w+)\}", exec_start):
        assert defaults.get(var), f"{name}: ${{{var}}} has no default in Environment="
    for var in re.findall(r"\$(\w+)", exec_start):
        assert var in example, f"{name}: ${var} not documented in smartedge.env.example"
    for var in set(example) & set(defaults):
        assert example[var] == defaults[var], f"{var}: example and unit default differ"


def test_viewer_unit_is_independent_of_the_backend() -> None:
    """The viewer is optional: nothing ties its unit to the backend's, so its failure (or its
    absence) never stops or restarts the backend, and it records into its own state directory."""
    viewer = parse_unit(UNIT_DIR / "smartedge-viewer.service")
    for key in ("Requires", "Requisite", "BindsTo", "PartOf", "Wants", "Upholds"):
        for value in viewer["Unit"].get(key, []):
            assert "smartedge-backend" not in value, f"viewer {key}={value}"
    backend = parse_unit(UNIT_DIR / "smartedge-backend.service")
    for values in backend["Unit"].values():
        assert not any("smartedge-viewer" in v for v in values)
    assert "smartedge/recordings" in _one(viewer, "Service", "StateDirectory").split()
    sink = _env_defaults(viewer)["SMARTEDGE_RERUN"]
    assert sink.startswith("save:/var/lib/smartedge/recordings/") and sink.endswith(".rrd")
    assert "SMARTEDGE_RERUN" not in _env_defaults(backend)


def test_router_unit_runs_smartedge_router_on_the_installed_router_config() -> None:
    """smartedge-router.service: ``smartedge router --config`` on the file install-backend.sh
    writes, Type=notify like the services, no restart on a config error, never beside zenohd."""
    unit = parse_unit(UNIT_DIR / "smartedge-router.service")
    sub, args = _subcommand(_exec_words("smartedge-router.service"))
    assert sub == "router" and sub in COMMANDS
    assert args == ["--config", "${SMARTEDGE_ROUTER_CONFIG}"]
    assert _env_defaults(unit)["SMARTEDGE_ROUTER_CONFIG"] == "/etc/smartedge/zenoh-router.json5"
    assert "ZENOH_CONFIG" not in _env_defaults(unit)  # the router is nobody's client
    assert _one(unit, "Service", "Type") == "notify"
    assert _one(unit, "Service", "NotifyAccess") == "main"
    assert re.fullmatch(r"\d+s", _one(unit, "Service", "WatchdogSec"))
    assert _one(unit, "Service", "Restart") == "on-failure"
    assert _one(unit, "Service", "User") == "smartedge"
    assert unit["Service"]["EnvironmentFile"] == [
        "/etc/smartedge/smartedge.env", "-/etc/smartedge/router.env"
    ]
    assert "smartedge-zenohd.service" in _one(unit, "Unit", "Conflicts").split()
    assert "smartedge-backend.service" in _one(unit, "Unit", "Before").split()
    assert _one(unit, "Install", "WantedBy") == "multi-user.target"
    proc = subprocess.run(
        [sys.executable, "-m", "smartedge", "router", "--help"],
        capture_output=True, text=True, timeout=60, cwd=REPO_ROOT,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    assert "--config" in proc.stdout and "--listen" in proc.stdout


@pytest.mark.parametrize("name", [*sorted(SERVICE_UNITS), "smartedge-router.service"])
def test_units_do_not_restart_on_a_configuration_error(name: str) -> None:
    unit = parse_unit(UNIT_DIR / name)
    statuses = _one(unit, "Service", "RestartPreventExitStatus").split()
    assert statuses == ["2", str(EXIT_CONFIG)]


@pytest.mark.parametrize("name", sorted(SERVICE_UNITS))
def test_a_bad_site_file_exits_with_the_status_the_unit_does_not_restart_on(
    name: str, tmp_path: Path
) -> None:
    """The unit's command line with a site file that is not valid YAML: the service names the
    file on stderr and exits 78 (EX_CONFIG), not with a traceback systemd would restart forever."""
    instance, settings = SERVICE_RUNS.get(name, ("", {}))
    unit = parse_unit(UNIT_DIR / name)
    bad = tmp_path / "bad.yaml"
    bad.write_text(EXAMPLE_SITE.read_text() + "\ncameras: [\n")
    env = {**_example_env(), **_env_defaults(unit), **settings, "SMARTEDGE_SITE": str(bad)}
    argv = expand_exec_start(_one(unit, "Service", "ExecStart"), env, instance)
    assert argv[0] == SMARTEDGE_BIN
    proc = subprocess.run(
        [sys.executable, "-m", "smartedge", *argv[1:]],
        capture_output=True, text=True, timeout=120, cwd=REPO_ROOT,
    )  # fmt: skip
    assert proc.returncode == EXIT_CONFIG, proc.stderr[-2000:]
    assert str(bad) in proc.stderr and "Traceback" not in proc.stderr


@pytest.mark.parametrize("name", sorted(SERVICE_UNITS))
def test_exec_start_flags_are_accepted_by_the_service(name: str) -> None:
    """Cross-check with the service's own argument parser once it exists."""
    sub, args = _subcommand(_exec_words(name))
    proc = subprocess.run(
        [sys.executable, "-m", "smartedge", sub, "--help"],
        capture_output=True, text=True, timeout=60, cwd=REPO_ROOT,
    )  # fmt: skip
    if "not available in this version" in proc.stderr or "missing dependency" in proc.stderr:
        pytest.skip(f"smartedge {sub} is not importable here: {proc.stderr.strip()}")
    assert proc.returncode == 0, proc.stderr
    flags = [a for a in args if a.startswith("--")] + ["--mode", "--connect", "--config"]
    missing = [f for f in flags if f not in proc.stdout]
    assert not missing, f"smartedge {sub} --help does not mention {missing}"


HARDENING = {
    "NoNewPrivileges": "yes",
    "ProtectSystem": "strict",
    "ProtectHome": "yes",
    "PrivateTmp": "yes",
    "ProtectKernelTunables": "yes",
    "ProtectKernelModules": "yes",
    "ProtectControlGroups": "yes",
    "RestrictNamespaces": "yes",
    "LockPersonality": "yes",
    "SystemCallArchitectures": "native",
    "RestrictAddressFamilies": "AF_UNIX AF_INET AF_INET6 AF_NETLINK",
    "MemoryDenyWriteExecute": "yes",
    "CapabilityBoundingSet": "",
}


@pytest.mark.parametrize("name", ALL_UNITS)
def test_units_are_hardened(name: str) -> None:
    unit = parse_unit(UNIT_DIR / name)
    for key, value in HARDENING.items():
        assert _one(unit, "Service", key) == value, key
    if name.startswith("smartedge-edge-agent"):
        # the camera is a device: a closed allow-list instead of PrivateDevices
        assert _one(unit, "Service", "PrivateDevices") == "no"
        assert _one(unit, "Service", "DevicePolicy") == "closed"
        assert "char-video4linux rw" in unit["Service"]["DeviceAllow"]
        assert _one(unit, "Service", "SupplementaryGroups") == "video"
    else:
        assert _one(unit, "Service", "PrivateDevices") == "yes"


def _verifiable_copy(tmp_path: Path) -> list[Path]:
    """Units as installed, with ExecStart pointing at executables that exist on this machine
    (verify checks them), instantiated, with the Jetson drop-in beside the edge agent."""
    smartedge = shutil.which("smartedge") or str(Path(sys.executable).with_name("smartedge"))
    if not Path(smartedge).exists():
        pytest.skip("no smartedge executable to point ExecStart at")
    out = []
    for name in ALL_UNITS:
        text = (UNIT_DIR / name).read_text()
        text = text.replace(SMARTEDGE_BIN, smartedge).replace("/usr/bin/zenohd", "/bin/true")
        target = tmp_path / name.replace("@.", "@lab1.")
        target.write_text(text)
        out.append(target)
    dropin = tmp_path / "smartedge-edge-agent@.service.d"
    dropin.mkdir()
    shutil.copy(UNIT_DIR / "jetson-gpu.conf", dropin / "jetson-gpu.conf")
    return out


@pytest.mark.skipif(shutil.which("systemd-analyze") is None, reason="no systemd-analyze")
def test_systemd_analyze_verify_accepts_the_units(tmp_path: Path) -> None:
    units = _verifiable_copy(tmp_path)
    proc = subprocess.run(
        ["systemd-analyze", "verify", "--man=no", *map(str, units)],
        capture_output=True, text=True, timeout=60, cwd=tmp_path,
    )  # fmt: skip
    # verify exits 0 on unknown keys; they only show up as "Unknown key ..., ignoring" lines.
    assert proc.returncode == 0, proc.stderr
    assert proc.stderr.strip() == "", proc.stderr


@pytest.mark.skipif(shutil.which("systemd-analyze") is None, reason="no systemd-analyze")
def test_systemd_exposure_score_is_low(tmp_path: Path) -> None:
    for unit in _verifiable_copy(tmp_path):
        proc = subprocess.run(
            ["systemd-analyze", "security", "--offline=true", "--no-pager", str(unit)],
            capture_output=True, text=True, timeout=60, cwd=tmp_path,
        )  # fmt: skip
        if "--offline" in proc.stderr or "unrecognized option" in proc.stderr:
            pytest.skip("systemd-analyze security --offline needs systemd >= 250")
        match = re.search(r"Overall exposure level for \S+: (\d+\.\d+)", proc.stdout)
        assert match, proc.stdout[-500:] + proc.stderr
        assert float(match.group(1)) <= 3.0, f"{unit.name}: exposure {match.group(1)}"


MDWE_WORKLOAD = textwrap.dedent(
    """
    import ctypes, sys
    libc = ctypes.CDLL(None, use_errno=True)
    if libc.prctl(65, 1, 0, 0, 0) != 0:  # PR_SET_MDWE, PR_MDWE_REFUSE_EXEC_GAIN
        print("no-mdwe"); sys.exit(0)
    import numpy as np
    import casadi as ca
    x = ca.SX.sym("x", 3)
    solver = ca.nlpsol("s", "ipopt", {"x": x, "f": ca.sumsqr(x - ca.DM([1, 2, 3]))},
                       {"ipopt.print_level": 0, "print_time": 0, "ipopt.sb": "yes"})
    assert np.allclose(np.array(solver(x0=[0, 0, 0])["x"]).ravel(), [1, 2, 3], atol=1e-6)
    import gtsam
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    noise = gtsam.noiseModel.Diagonal.Sigmas(np.array([0.1, 0.1, 0.05]))
    graph.add(gtsam.PriorFactorPose2(0, gtsam.Pose2(1, 2, 0.3), noise))
    values.insert(0, gtsam.Pose2(0, 0, 0))
    isam = gtsam.ISAM2(); isam.update(graph, values)
    assert abs(isam.calculateEstimate().atPose2(0).x() - 1) < 1e-6
    import open3d as o3d
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.random.rand(300, 3)))
    assert o3d.pipelines.registration.registration_icp(cloud, cloud, 0.05).fitness > 0.99
    import rerun as rr
    rr.init("mdwe"); rr.save(sys.argv[1]); rr.log("p", rr.Points3D(np.zeros((3, 3))))
    import onnxruntime as ort, onnxruntime.datasets as datasets
    sess = ort.InferenceSession(datasets.get_example("sigmoid.onnx"),
                                providers=["CPUExecutionProvider"])
    inp = sess.get_inputs()[0]
    out = sess.run(None, {inp.name: np.zeros([3, 4, 5], np.float32)})[0]
    assert np.allclose(out, 0.5)
    import cv2, zenoh
    cv2.GaussianBlur(np.zeros((32, 32), np.uint8), (5, 5), 0)
    conf = zenoh.Config.from_json5('{mode: "peer", scouting: {multicast: {enabled: false}}}')
    zenoh.open(conf).close()
    print("ok")
    """
)


def test_backend_and_edge_stacks_run_with_write_xor_execute(tmp_path: Path) -> None:
    """MemoryDenyWriteExecute=yes in the units is safe: the same libraries work in a process
    where the kernel refuses writable+executable memory (PR_SET_MDWE, Linux >= 6.3)."""
    for module in ("casadi", "gtsam", "open3d", "rerun", "onnxruntime", "cv2", "zenoh"):
        pytest.importorskip(module)
    proc = subprocess.run(
        [sys.executable, "-c", MDWE_WORKLOAD, str(tmp_path / "m.rrd")],
        capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    if proc.stdout.strip() == "no-mdwe":
        pytest.skip("kernel without PR_SET_MDWE")
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert proc.stdout.strip().endswith("ok")


MDWE_VIEWER_WORKLOAD = textwrap.dedent(
    """
    import ctypes, sys, urllib.request
    libc = ctypes.CDLL(None, use_errno=True)
    if libc.prctl(65, 1, 0, 0, 0) != 0:  # PR_SET_MDWE, PR_MDWE_REFUSE_EXEC_GAIN
        print("no-mdwe"); sys.exit(0)
    import numpy as np, rerun as rr
    rec = rr.RecordingStream("mdwe")
    url = rec.serve_grpc(grpc_port=int(sys.argv[1]))
    rr.serve_web_viewer(web_port=int(sys.argv[2]), open_browser=False, connect_to=url)
    rec.log("p", rr.Points3D(np.zeros((3, 3))))
    assert urllib.request.urlopen(f"http://127.0.0.1:{sys.argv[2]}/", timeout=10).status == 200
    print("ok")
    """
)


def test_viewer_rerun_serve_runs_with_write_xor_execute() -> None:
    """The viewer unit's MemoryDenyWriteExecute=yes also holds for ``--rerun serve`` (rerun's
    gRPC server and web viewer server); saving a recording is covered above."""
    pytest.importorskip("rerun")
    proc = subprocess.run(
        [sys.executable, "-c", MDWE_VIEWER_WORKLOAD, str(free_port()), str(free_port())],
        capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    if proc.stdout.strip() == "no-mdwe":
        pytest.skip("kernel without PR_SET_MDWE")
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert proc.stdout.strip().endswith("ok")


# --------------------------------------------------------------------------------------------
# install scripts
# --------------------------------------------------------------------------------------------

SCRIPTS = ("install-edge.sh", "install-backend.sh", "install-common.sh")


def _run_script(
    name: str, *args: str, timeout: float = 60, path: str | None = None
) -> subprocess.CompletedProcess:
    """Run an install script; ``path``: its $PATH (default: this process's)."""
    env = {**os.environ, "PATH": path or os.environ.get("PATH", "/usr/bin:/bin")}
    return subprocess.run(
        ["bash", str(DEPLOY / name), *args],
        capture_output=True, text=True, timeout=timeout, env=env,
    )  # fmt: skip


def _tree(root: Path) -> dict[str, tuple[int, bytes]]:
    return {
        str(p.relative_to(root)): (p.stat().st_mode, p.read_bytes())
        for p in sorted(root.rglob("*"))
        if p.is_file()
    }


def _fake_venv(root: Path) -> None:
    """Stand-in for /opt/smartedge under --root: its python is this test's interpreter (so the
    scripts' site check runs the real core.site)."""
    bin_dir = root / "opt" / "smartedge" / "bin"
    bin_dir.mkdir(parents=True)
    python = bin_dir / "python"
    python.write_text(f'#!/bin/sh\nexec {shlex.quote(sys.executable)} "$@"\n')
    python.chmod(0o755)


@pytest.mark.parametrize("name", SCRIPTS)
def test_scripts_are_valid_bash(name: str) -> None:
    proc = subprocess.run(["bash", "-n", str(DEPLOY / name)], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr


@pytest.mark.parametrize("name", SCRIPTS[:2])
def test_scripts_print_usage(name: str) -> None:
    proc = _run_script(name, "--help")
    assert proc.returncode == 0
    assert proc.stdout.startswith("Usage:") and "--dry-run" in proc.stdout
    bad = _run_script(name, "--no-such-option")
    assert bad.returncode == 2 and "unknown option --no-such-option" in bad.stderr


def test_edge_dry_run_prints_the_steps_and_changes_nothing(tmp_path: Path) -> None:
    root = tmp_path / "root"
    proc = _run_script(
        "install-edge.sh", "--dry-run", "--root", str(root), "--site", str(EXAMPLE_SITE),
        "--backend-host", "10.1.2.3", "--jetson", "yes", "cam_sw", "cam_se",
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    out = proc.stdout
    assert not root.exists()
    assert "dry run: nothing is changed" in out
    assert re.search(r"would: \S+ -m venv \S*/opt/smartedge", out)
    assert re.search(r"pip install --quiet --upgrade '\S+\[edge\]'", out), out
    assert "useradd --system" in out
    assert "zenoh/client.json5 → " in out and "s/BACKEND_HOST/10.1.2.3/g" in out
    assert "smartedge-edge-agent@.service" in out and "jetson-gpu.conf" in out
    assert "systemctl enable smartedge-edge-agent@cam_sw.service smartedge-edge-agent@cam_se" in out
    assert "[backend" not in out  # an edge board never gets the backend extras


def test_backend_dry_run_prints_the_steps_and_changes_nothing(tmp_path: Path) -> None:
    root = tmp_path / "root"
    proc = _run_script(
        "install-backend.sh", "--dry-run", "--root", str(root), "--site", str(EXAMPLE_SITE),
        "--router", "backend", "hsr",
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    out = proc.stdout
    assert not root.exists()
    assert re.search(r"pip install --quiet --upgrade '\S+\[backend,bridge\]'", out), out
    assert "libusb-1.0-0" in out
    assert "zenoh/router.json5 → " in out
    assert "smartedge-backend.service.d/zenoh-router.conf" in out
    assert "smartedge-robot-bridge@hsr.service" in out
    assert ("systemctl enable smartedge-backend.service smartedge-mapper.service "
            "smartedge-viewer.service ") in out

    no_viewer = _run_script(
        "install-backend.sh", "--dry-run", "--root", str(root), "--site", str(EXAMPLE_SITE),
        "--no-viewer", "hsr",
    )  # fmt: skip
    assert no_viewer.returncode == 0, no_viewer.stderr
    assert "smartedge-viewer.service" not in no_viewer.stdout.replace(
        "systemctl disable --now smartedge-viewer.service", ""
    )
    assert "systemctl disable --now smartedge-viewer.service" in no_viewer.stdout
    assert not root.exists()

    both = _run_script("install-backend.sh", "--dry-run", "--site", str(EXAMPLE_SITE),
                       "--no-viewer", "--rerun", "serve")  # fmt: skip
    assert both.returncode == 2 and "--rerun configures the viewer" in both.stderr


def test_edge_staged_install_is_complete_and_idempotent(tmp_path: Path) -> None:
    zenoh = pytest.importorskip("zenoh")
    root = tmp_path / "root"
    _fake_venv(root)
    args = ("--root", str(root), "--skip-pip", "--site", str(EXAMPLE_SITE),
            "--backend-host", "backend.lab", "--source", "sim", "cam_sw", "cam_ne")  # fmt: skip
    proc = _run_script("install-edge.sh", *args)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "site 'lab': 4 cameras" in proc.stdout
    etc = root / "etc" / "smartedge"
    assert (etc / "site.yaml").read_bytes() == EXAMPLE_SITE.read_bytes()
    assert stat.S_IMODE((etc / "site.yaml").stat().st_mode) == 0o640
    assert stat.S_IMODE(etc.stat().st_mode) == 0o750
    conf = zenoh.Config.from_file(str(etc / "zenoh-client.json5"))
    assert json.loads(conf.get_json("connect/endpoints")) == ["tcp/backend.lab:7447"]
    env = (etc / "smartedge.env").read_text()
    assert "\nSMARTEDGE_SOURCE=sim\n" in env
    units = root / "etc" / "systemd" / "system"
    assert (units / "smartedge-edge-agent@.service").read_bytes() == (
        UNIT_DIR / "smartedge-edge-agent@.service"
    ).read_bytes()
    assert not (root / "etc" / "systemd" / "system" / "smartedge-backend.service").exists()
    assert not (root / "etc" / "systemd" / "system" / "smartedge-viewer.service").exists()

    # Re-run: same result, the administrator's edits of smartedge.env survive.
    (etc / "smartedge.env").write_text(env + "SMARTEDGE_EDGE_AGENT_ARGS=--edited\n")
    before = _tree(root)
    again = _run_script("install-edge.sh", *args)
    assert again.returncode == 0, again.stderr
    assert "keep existing" in again.stdout
    assert _tree(root) == before


def test_edge_install_refuses_unknown_camera_before_configuring(tmp_path: Path) -> None:
    root = tmp_path / "root"
    _fake_venv(root)
    proc = _run_script(
        "install-edge.sh", "--root", str(root), "--skip-pip", "--site", str(EXAMPLE_SITE),
        "--backend-host", "backend.lab", "cam_sw", "cam_typo",
    )  # fmt: skip
    assert proc.returncode != 0
    assert "cam_typo" in proc.stderr + proc.stdout
    assert not (root / "etc").exists()


def test_edge_install_device_writes_each_cameras_input(tmp_path: Path) -> None:
    """``--device CAMERA=URI`` writes the camera's env file with its --device argument (the
    unit passes $SMARTEDGE_EDGE_AGENT_ARGS to the agent); a camera without an input is warned
    about; with one camera ``--device URI`` is enough; bad specs are refused before anything
    is installed."""
    root = tmp_path / "root"
    _fake_venv(root)
    base = ("--root", str(root), "--skip-pip", "--site", str(EXAMPLE_SITE),
            "--backend-host", "backend.lab", "--no-start")
    proc = _run_script("install-edge.sh", *base, "--device", "cam_sw=/dev/video0",
                       "--device", "cam_se=rtsp://u:p@10.0.0.5:554/s1", "cam_sw", "cam_se",
                       "cam_nw")
    assert proc.returncode == 0, proc.stdout + proc.stderr
    etc = root / "etc" / "smartedge"
    sw = (etc / "edge-agent@cam_sw.env").read_text()
    assert "SMARTEDGE_EDGE_AGENT_ARGS=--device /dev/video0\n" in sw
    se = etc / "edge-agent@cam_se.env"
    assert "SMARTEDGE_EDGE_AGENT_ARGS=--device rtsp://u:p@10.0.0.5:554/s1\n" in se.read_text()
    assert stat.S_IMODE(se.stat().st_mode) == 0o640  # a stream URL may hold a password
    assert not (etc / "edge-agent@cam_nw.env").exists()
    out = proc.stdout + proc.stderr
    assert "cam_nw has no input yet" in out and "78" in out
    unit = (root / "etc" / "systemd" / "system" / "smartedge-edge-agent@.service").read_text()
    assert "EnvironmentFile=-/etc/smartedge/edge-agent@%i.env" in unit
    assert "$SMARTEDGE_EDGE_AGENT_ARGS" in unit and "RestartPreventExitStatus=2 78" in unit

    one = tmp_path / "one"
    _fake_venv(one)
    proc = _run_script("install-edge.sh", "--root", str(one), "--skip-pip", "--site",
                       str(EXAMPLE_SITE), "--backend-host", "b", "--no-start", "--device", "2",
                       "cam_sw")
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "--device 2\n" in (one / "etc" / "smartedge" / "edge-agent@cam_sw.env").read_text()

    for bad, why in ((["--device", "/dev/video0", "cam_sw", "cam_se"], "CAMERA=URI"),
                     (["--device", "cam_xx=/dev/video0", "cam_sw"], "cam_xx"),
                     (["--device", "cam_sw=/dev/video0 x", "cam_sw"], "spaces"),
                     (["--device", "cam_sw=a", "--device", "cam_sw=b", "cam_sw"], "twice")):
        fresh = tmp_path / f"bad_{why}"
        _fake_venv(fresh)
        proc = _run_script("install-edge.sh", "--root", str(fresh), "--skip-pip", "--site",
                           str(EXAMPLE_SITE), "--backend-host", "b", *bad)
        assert proc.returncode != 0 and why in proc.stdout + proc.stderr, bad
        assert not (fresh / "etc").exists(), bad


def test_backend_staged_install_router_modes_and_tls(tmp_path: Path) -> None:
    zenoh = pytest.importorskip("zenoh")
    root = tmp_path / "root"
    _fake_venv(root)
    tls = tmp_path / "tls"
    tls.mkdir()
    for f in ("ca.crt", "router.crt", "router.key", "client.crt", "client.key"):
        (tls / f).write_text(f"placeholder {f}\n")
    base = ("--root", str(root), "--skip-pip", "--site", str(EXAMPLE_SITE))
    units = root / "etc" / "systemd" / "system"
    etc = root / "etc" / "smartedge"

    proc = _run_script("install-backend.sh", *base, "--router", "backend", "--tls", str(tls), "hsr")
    assert proc.returncode == 0, proc.stdout + proc.stderr
    dropin = units / "smartedge-backend.service.d" / "zenoh-router.conf"
    assert "ZENOH_CONFIG=/etc/smartedge/zenoh-router.json5" in dropin.read_text()
    router = zenoh.Config.from_file(str(etc / "zenoh-router.json5"))
    assert json.loads(router.get_json("listen/endpoints")) == ["tls/0.0.0.0:7447"]
    client = zenoh.Config.from_file(str(etc / "zenoh-client.json5"))
    assert json.loads(client.get_json("connect/endpoints")) == ["tls/127.0.0.1:7447"]
    assert stat.S_IMODE((etc / "tls" / "router.key").stat().st_mode) == 0o640
    assert (units / "smartedge-robot-bridge@.service").exists()
    assert not (units / "smartedge-zenohd.service").exists()
    assert not (units / "smartedge-router.service").exists()
    assert "router: the backend's own session" in proc.stdout

    fake_zenohd = tmp_path / "bin" / "zenohd"
    fake_zenohd.parent.mkdir()
    fake_zenohd.write_text("#!/bin/sh\n")
    fake_zenohd.chmod(0o755)
    proc = _run_script("install-backend.sh", *base, "--router", "zenohd", "--zenohd",
                       str(fake_zenohd), "hsr")  # fmt: skip
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert not dropin.exists()  # the backend is no longer the router
    assert (units / "smartedge-zenohd.service").exists()
    path_dropin = (units / "smartedge-zenohd.service.d" / "zenohd-path.conf").read_text()
    assert f"ExecStart={fake_zenohd} -c" in path_dropin
    assert not (units / "smartedge-router.service").exists()
    router = zenoh.Config.from_file(str(etc / "zenoh-router.json5"))
    assert json.loads(router.get_json("listen/endpoints")) == ["tcp/0.0.0.0:7447"]


@pytest.mark.skipif(shutil.which("openssl") is None, reason="openssl not installed")
def test_staged_installs_with_smartedge_certs_give_each_service_its_identity(
    tmp_path: Path,
) -> None:
    """``--tls DIR`` made by ``smartedge certs``: the backend host gets router-acl.json5 as its
    router config, the ``backend`` certificate for its services and one identity per robot
    bridge (config + drop-in); an edge board one identity per camera."""
    zenoh = pytest.importorskip("zenoh")
    from smartedge.commands.certs import main as certs_main

    pki = tmp_path / "pki"
    assert certs_main(["--site", str(EXAMPLE_SITE), "--out", str(pki), "--router-host",
                       "backend.lab", "--days", "2"]) == 0  # fmt: skip
    root = tmp_path / "backend"
    _fake_venv(root)
    base = ("--root", str(root), "--skip-pip", "--site", str(EXAMPLE_SITE), "--tls", str(pki))
    proc = _run_script("install-backend.sh", *base, "hsr")
    assert proc.returncode == 0, proc.stdout + proc.stderr
    etc, units = root / "etc" / "smartedge", root / "etc" / "systemd" / "system"
    router = zenoh.Config.from_file(str(etc / "zenoh-router.json5"))
    acl = json.loads(router.get_json("access_control"))
    assert acl["enabled"] is True and acl["default_permission"] == "deny"
    assert (etc / "tls" / "client.crt").read_bytes() == (pki / "backend.crt").read_bytes()
    dropin = units / "smartedge-robot-bridge@hsr.service.d" / "zenoh-identity.conf"
    assert "Environment=ZENOH_CONFIG=/etc/smartedge/zenoh-client-bridge-hsr.json5" in (
        dropin.read_text())
    bridge = zenoh.Config.from_file(str(etc / "zenoh-client-bridge-hsr.json5"))
    tls = json.loads(bridge.get_json("transport/link/tls"))
    assert tls["connect_certificate"] == "/etc/smartedge/tls/bridge-hsr.crt"
    assert tls["connect_private_key"] == "/etc/smartedge/tls/bridge-hsr.key"
    assert json.loads(bridge.get_json("connect/endpoints")) == ["tls/127.0.0.1:7447"]
    assert stat.S_IMODE((etc / "tls" / "bridge-hsr.key").stat().st_mode) == 0o640

    # router-acl.json5 without the bridge's certificate: refused before configuring anything
    partial = tmp_path / "partial"
    shutil.copytree(pki, partial)
    (partial / "bridge-hsr.key").unlink()
    fresh = tmp_path / "fresh"
    _fake_venv(fresh)
    proc = _run_script("install-backend.sh", "--root", str(fresh), "--skip-pip", "--site",
                       str(EXAMPLE_SITE), "--tls", str(partial), "hsr")  # fmt: skip
    assert proc.returncode != 0 and "bridge-hsr.key" in proc.stderr
    assert not (fresh / "etc").exists()

    root = tmp_path / "edge"
    _fake_venv(root)
    proc = _run_script("install-edge.sh", "--root", str(root), "--skip-pip", "--site",
                       str(EXAMPLE_SITE), "--backend-host", "backend.lab", "--source", "sim",
                       "--tls", str(pki), "cam_sw", "cam_se")  # fmt: skip
    assert proc.returncode == 0, proc.stdout + proc.stderr
    etc, units = root / "etc" / "smartedge", root / "etc" / "systemd" / "system"
    for cam in ("cam_sw", "cam_se"):
        dropin = units / f"smartedge-edge-agent@{cam}.service.d" / "zenoh-identity.conf"
        assert f"ZENOH_CONFIG=/etc/smartedge/zenoh-client-edge-{cam}.json5" in dropin.read_text()
        conf = zenoh.Config.from_file(str(etc / f"zenoh-client-edge-{cam}.json5"))
        tls = json.loads(conf.get_json("transport/link/tls"))
        assert tls["connect_certificate"] == f"/etc/smartedge/tls/edge-{cam}.crt"
        assert json.loads(conf.get_json("connect/endpoints")) == ["tls/backend.lab:7447"]
        assert stat.S_IMODE((etc / "tls" / f"edge-{cam}.key").stat().st_mode) == 0o640
    assert not (etc / "tls" / "client.key").exists()


def test_backend_install_router_is_smartedge_unless_zenohd_is_asked_for(tmp_path: Path) -> None:
    """The default router is ``smartedge router`` (smartedge-router.service), even with a zenohd
    on PATH; zenohd only with --router zenohd or --zenohd PATH. The installer says which router
    it set up and why, and removes the router unit it no longer uses."""
    zenoh = pytest.importorskip("zenoh")
    root = tmp_path / "root"
    _fake_venv(root)
    fake_zenohd = tmp_path / "bin" / "zenohd"
    fake_zenohd.parent.mkdir()
    fake_zenohd.write_text("#!/bin/sh\n")
    fake_zenohd.chmod(0o755)
    with_zenohd = f"{fake_zenohd.parent}:{os.environ.get('PATH', '/usr/bin:/bin')}"
    base = ("--root", str(root), "--skip-pip", "--site", str(EXAMPLE_SITE), "--no-start")
    units = root / "etc" / "systemd" / "system"
    etc = root / "etc" / "smartedge"
    router_unit = units / "smartedge-router.service"
    zenohd_unit = units / "smartedge-zenohd.service"
    path_dropin = units / "smartedge-zenohd.service.d" / "zenohd-path.conf"

    proc = _run_script("install-backend.sh", *base, "hsr", path=with_zenohd)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert ("router: smartedge-router.service (smartedge router, from the smartedge package; "
            "the default; zenohd not requested)") in proc.stdout
    assert router_unit.read_bytes() == (UNIT_DIR / "smartedge-router.service").read_bytes()
    assert not zenohd_unit.exists()
    assert not (units / "smartedge-backend.service.d" / "zenoh-router.conf").exists()
    assert "systemctl enable smartedge-router.service smartedge-backend.service" in proc.stdout
    # the config the unit's ExecStart names is the one installed
    config = _env_defaults(parse_unit(router_unit))["SMARTEDGE_ROUTER_CONFIG"]
    installed = zenoh.Config.from_file(str(root / config.lstrip("/")))
    assert json.loads(installed.get_json("mode")) == "router"
    assert (etc / "zenoh-router.json5").exists()

    proc = _run_script("install-backend.sh", *base, "--router", "zenohd", "hsr", path=with_zenohd)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert f"router: smartedge-zenohd.service (zenohd {fake_zenohd}; --router zenohd)" in (
        proc.stdout
    )
    assert zenohd_unit.exists() and path_dropin.exists()
    assert not router_unit.exists()
    assert "systemctl disable --now smartedge-router.service" in proc.stdout

    proc = _run_script("install-backend.sh", *base, "--zenohd", str(fake_zenohd), "hsr")
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert f"(zenohd {fake_zenohd}; --zenohd {fake_zenohd} given)" in proc.stdout

    proc = _run_script("install-backend.sh", *base, "--router", "smartedge", "hsr")
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "(smartedge router, from the smartedge package; --router smartedge)" in proc.stdout
    assert router_unit.exists()
    assert not zenohd_unit.exists() and not path_dropin.exists()

    proc = _run_script("install-backend.sh", *base, "--router", "external", "--router-host",
                       "router.lab", "hsr")  # fmt: skip
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "router: external, at router.lab; none runs here (--router external)" in proc.stdout
    assert not router_unit.exists() and not zenohd_unit.exists()
    assert not (etc / "zenoh-router.json5").exists()

    for bad, why in ((["--router", "zenohd", "--zenohd", str(tmp_path / "nope")], "not an exec"),
                     (["--router", "backend", "--zenohd", str(fake_zenohd)], "--zenohd goes"),
                     (["--router", "mosquitto"], "expected smartedge, zenohd")):
        proc = _run_script("install-backend.sh", "--dry-run", "--site", str(EXAMPLE_SITE), *bad)
        assert proc.returncode == 2 and why in proc.stderr, (bad, proc.stderr)
    if shutil.which("zenohd", path="/usr/bin:/bin") is None:
        proc = _run_script("install-backend.sh", "--dry-run", "--site", str(EXAMPLE_SITE),
                           "--router", "zenohd", path="/usr/bin:/bin")  # fmt: skip
        assert proc.returncode == 2
        assert "zenohd not found" in proc.stderr and "--router smartedge" in proc.stderr


def test_backend_staged_install_viewer_sink_and_no_viewer(tmp_path: Path) -> None:
    """--rerun SINK is the viewer's sink in a new smartedge.env; the viewer unit is installed
    next to the backend's, and --no-viewer removes it again without touching the backend."""
    root = tmp_path / "root"
    _fake_venv(root)
    base = ("--root", str(root), "--skip-pip", "--site", str(EXAMPLE_SITE), "--router", "backend")
    units = root / "etc" / "systemd" / "system"
    etc = root / "etc" / "smartedge"

    proc = _run_script("install-backend.sh", *base, "--rerun", "serve", "hsr")
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert (units / "smartedge-viewer.service").read_bytes() == (
        UNIT_DIR / "smartedge-viewer.service"
    ).read_bytes()
    env = (etc / "smartedge.env").read_text()
    assert "\nSMARTEDGE_RERUN=serve\n" in env
    assert "\nSMARTEDGE_VIEWER_ARGS=\n" in env
    assert ("enable smartedge-backend.service smartedge-mapper.service "
            "smartedge-viewer.service") in proc.stdout
    backend = (units / "smartedge-backend.service").read_bytes()

    proc = _run_script("install-backend.sh", *base, "--no-viewer", "hsr")
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert not (units / "smartedge-viewer.service").exists()
    assert "smartedge-viewer.service" not in proc.stdout.split("systemctl daemon-reload")[-1]
    assert (units / "smartedge-backend.service").read_bytes() == backend
    assert (units / "smartedge-backend.service.d" / "zenoh-router.conf").exists()


# --------------------------------------------------------------------------------------------
# documentation
# --------------------------------------------------------------------------------------------


def test_deployment_doc_covers_the_tls_keys_and_scripts() -> None:
    doc = (REPO_ROOT / "docs" / "deployment.md").read_text()
    keys: set[str] = set()
    for name in ("router-tls.json5", "client-tls.json5"):
        text = (ZENOH_DIR / name).read_text()
        block = text[text.index("tls: {") :]
        keys |= set(re.findall(r"^\s+(\w+):", block, flags=re.M))
    missing = sorted(k for k in keys if k not in doc)
    assert not missing, f"docs/deployment.md does not explain {missing}"
    for needle in ("install-edge.sh", "install-backend.sh", "smartedge site check", "openssl",
                   "journalctl", "--rerun serve", "smartedge-viewer.service",
                   "smartedge viewer --site"):  # fmt: skip
        assert needle in doc, needle


# --------------------------------------------------------------------------------------------
# the units' command lines against the real services, under a stand-in for systemd's notify
# --------------------------------------------------------------------------------------------


def expand_exec_start(exec_start: str, env: dict[str, str], instance: str) -> list[str]:
    """systemd's expansion: ``$X`` as a whole word splits into zero or more words, ``${X}`` is
    replaced in place (one word), ``%i`` is the instance name."""
    words: list[str] = []
    for word in shlex.split(exec_start):
        whole = re.fullmatch(r"\$(\w+)", word)
        if whole:
            words.extend(env.get(whole.group(1), "").split())
            continue
        word = re.sub(r"\$\{(\w+)\}", lambda m: env.get(m.group(1), ""), word)
        words.append(word.replace("%i", instance))
    return words


class NotifySocket:
    """The datagram socket systemd gives a Type=notify service in $NOTIFY_SOCKET."""

    def __init__(self, path: Path) -> None:
        import socket

        self.path = path
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        self.sock.bind(str(path))
        self.sock.settimeout(0.1)
        self.messages: list[str] = []

    def wait_for(
        self, state: str, timeout_s: float, proc: subprocess.Popen | None = None
    ) -> bool:
        """Collect messages until one has the line ``state``, ``timeout_s`` passes, or ``proc``
        has exited (then only what it already sent counts)."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if any(state in m.splitlines() for m in self.messages):
                return True
            if proc is not None and proc.poll() is not None:
                proc = None
                deadline = time.monotonic() + 0.2  # drain what is queued
            with contextlib.suppress(TimeoutError):
                self.messages.append(self.sock.recv(4096).decode())
        return any(state in m.splitlines() for m in self.messages)

    def close(self) -> None:
        self.sock.close()


SIM_SITE = REPO_ROOT / "simulation" / "sites" / "paper_lab.yaml"
SERVICE_RUNS = {
    # unit → (instance, settings on top of the unit's defaults); the simulated paper site
    "smartedge-edge-agent@.service": ("cam1", {"SMARTEDGE_SOURCE": "sim"}),
    "smartedge-robot-bridge@.service": ("hsr", {"SMARTEDGE_ADAPTER": "sim"}),
    "smartedge-backend.service": ("", {}),
    "smartedge-viewer.service": ("", {}),  # SMARTEDGE_RERUN: a recording under tmp_path
}


@pytest.mark.parametrize("name", sorted(SERVICE_RUNS))
def test_unit_command_line_notifies_ready_watchdog_and_stops_cleanly(
    name: str, tmp_path: Path
) -> None:
    """What systemd would run (ExecStart expanded with the unit's Environment= and the example
    settings, the installed zenoh client config) starts, reports READY=1, pings the watchdog,
    and on SIGTERM says STOPPING=1 and exits 0."""
    zenoh = pytest.importorskip("zenoh")
    import signal

    instance, settings = SERVICE_RUNS[name]
    unit = parse_unit(UNIT_DIR / name)
    smartedge = Path(sys.executable).with_name("smartedge")
    if not smartedge.exists():
        pytest.skip("no smartedge executable next to the interpreter")
    port = free_port()
    client_conf = _render("client.json5", tmp_path, **{"127.0.0.1:7447": f"127.0.0.1:{port}"})
    env = {**_example_env(), **_env_defaults(unit), **settings}
    env.update(
        SMARTEDGE_SITE=str(SIM_SITE),
        ZENOH_CONFIG=str(client_conf),
        SMARTEDGE_RERUN=f"save:{tmp_path / 'recordings' / 'viewer.rrd'}",
    )
    argv = expand_exec_start(_one(unit, "Service", "ExecStart"), env, instance)
    assert argv[0] == SMARTEDGE_BIN
    argv[0] = str(smartedge)
    notify = NotifySocket(tmp_path / "notify.sock")
    proc_env = {**os.environ, **env, "NOTIFY_SOCKET": str(notify.path), "WATCHDOG_USEC": "1000000"}
    router_conf = _on_port("router.json5", tmp_path, port)
    with zenoh.open(router_conf):
        proc = subprocess.Popen(
            argv, env=proc_env, cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.STDOUT
        )
        try:
            ready = notify.wait_for("READY=1", timeout_s=60, proc=proc)
            watchdog = ready and notify.wait_for("WATCHDOG=1", timeout_s=3, proc=proc)
            proc.send_signal(signal.SIGTERM)
            code = proc.wait(timeout=20)
            stopping = notify.wait_for("STOPPING=1", timeout_s=0.5)
        finally:
            if proc.poll() is None:
                proc.kill()
            output = proc.communicate()[0].decode(errors="replace")[-3000:]
            notify.close()
    assert ready, f"no READY=1: {notify.messages}\n{output}"
    assert watchdog, f"no WATCHDOG=1 within 3 s: {notify.messages}\n{output}"
    assert stopping, notify.messages
    assert code == 0, output
    if name == "smartedge-viewer.service":
        recording = tmp_path / "recordings" / "viewer.rrd"
        assert recording.is_file() and recording.stat().st_size > 0, output


def test_router_unit_command_line_notifies_carries_traffic_and_stops_cleanly(
    tmp_path: Path,
) -> None:
    """smartedge-router.service's ExecStart (expanded like systemd does, on the shipped router
    config moved to a free loopback port): READY=1 once listening, the watchdog pinged, two
    clients with the shipped client config reach each other through it, SIGTERM → STOPPING=1
    and exit 0."""
    zenoh = pytest.importorskip("zenoh")
    import signal

    unit = parse_unit(UNIT_DIR / "smartedge-router.service")
    smartedge = Path(sys.executable).with_name("smartedge")
    if not smartedge.exists():
        pytest.skip("no smartedge executable next to the interpreter")
    port = free_port()
    router_conf = _render("router.json5", tmp_path, **{"0.0.0.0:7447": f"127.0.0.1:{port}"})
    env = {**_example_env(), **_env_defaults(unit), "SMARTEDGE_ROUTER_CONFIG": str(router_conf)}
    argv = expand_exec_start(_one(unit, "Service", "ExecStart"), env, "")
    assert argv[0] == SMARTEDGE_BIN
    argv[0] = str(smartedge)
    notify = NotifySocket(tmp_path / "notify.sock")
    proc_env = {**os.environ, **env, "NOTIFY_SOCKET": str(notify.path), "WATCHDOG_USEC": "1000000"}
    proc = subprocess.Popen(
        argv, env=proc_env, cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.STDOUT
    )
    got: list[bytes] = []
    try:
        ready = notify.wait_for("READY=1", timeout_s=30, proc=proc)
        watchdog = ready and notify.wait_for("WATCHDOG=1", timeout_s=3, proc=proc)
        if ready:
            client_conf = _on_port("client.json5", tmp_path, port)
            with zenoh.open(client_conf) as sub_session, zenoh.open(client_conf) as pub_session:
                sub_session.declare_subscriber(
                    "deploytest/**", lambda s: got.append(s.payload.to_bytes())
                )
                pub = pub_session.declare_publisher("deploytest/x")
                wait_until(lambda: (pub.put(b"hello"), bool(got))[1], timeout_s=5.0, step_s=0.1)
        proc.send_signal(signal.SIGTERM)
        code = proc.wait(timeout=20)
        stopping = notify.wait_for("STOPPING=1", timeout_s=0.5)
    finally:
        if proc.poll() is None:
            proc.kill()
        output = proc.communicate()[0].decode(errors="replace")[-3000:]
        notify.close()
    assert ready, f"no READY=1: {notify.messages}\n{output}"
    assert watchdog, f"no WATCHDOG=1 within 3 s: {notify.messages}\n{output}"
    assert got[:1] == [b"hello"], output
    assert stopping, notify.messages
    assert code == 0, output
    assert f"listening on tcp/127.0.0.1:{port}" in output
