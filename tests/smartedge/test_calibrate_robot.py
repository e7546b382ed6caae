"""``smartedge calibrate robot`` end to end on MCAP recordings of simulated drives (the
``smartedge record`` format): the updated site file, ``--camera``, refusals, bad input."""

from __future__ import annotations

import json

import msgpack  # type: ignore[import-untyped]
import numpy as np
import pytest
import yaml

from calibration.site_file import write_site_with_cameras
from core.geometry import pose_error
from core.site import load_site
from protocol import keys
from protocol.codec import decode
from protocol.messages import RobotDetections
from simulation.calibration_drive import perturbed_camera_poses, record_drive
from simulation.detections import true_cameras
from simulation.scenario import load_scenario
from smartedge.commands import calibrate as cli
from smartedge.commands.calibrate_robot import main
from smartedge.commands.record import Recorder

DRIVE_S = 60.0
FAST = ["--max-rate", "3"]


@pytest.fixture(scope="module")
def lab(tmp_path_factory):
    """A 60 s drive of the paper lab recorded to MCAP, one with cam2's detections left out,
    the nominal site file and the simulator's true camera poses."""
    scenario = load_scenario()
    d = tmp_path_factory.mktemp("calib_robot")
    rec = Recorder(d / "drive.mcap")
    summary = record_drive(rec.write, scenario, "traj3x3", duration_s=DRIVE_S)
    rec.close()
    rec = Recorder(d / "no_cam2.mcap")
    record_drive(rec.write, scenario, "traj3x3", duration_s=DRIVE_S,
                 cameras=["cam1", "cam3", "cam4"])
    rec.close()
    truth = {c: m.T_world_cam for c, m in true_cameras(scenario).items()}
    return {"dir": d, "site": scenario.site.source_path, "scenario": scenario,
            "truth": truth, "summary": summary}


def _doc(path):
    return yaml.safe_load(open(path, encoding="utf-8"))


def test_recording_to_updated_site_file(lab, tmp_path, capsys):
    perturbed = tmp_path / "site_20cm.yaml"
    start = perturbed_camera_poses(load_site(lab["site"]), 0.20, 3.0, seed=1)
    write_site_with_cameras(lab["site"], perturbed, start)
    out, report = tmp_path / "site_new.yaml", tmp_path / "report.json"
    rc = cli.main(["robot", "--site", str(perturbed), "--recording",
                   str(lab["dir"] / "drive.mcap"), "--out", str(out), "--report", str(report),
                   *FAST])
    text = capsys.readouterr().out
    assert rc == 0, text
    assert "corr cm" in text and "wrote" in text and "comments" in text
    new = load_site(out)
    offsets = []
    for c, T in lab["truth"].items():
        _, dr0 = pose_error(start[c], T)
        _, dr = pose_error(new.cameras[c].T_world_cam, T)
        assert dr < 0.3 and dr < dr0 / 10, (c, dr, dr0)
        offsets.append(new.cameras[c].T_world_cam[:3, 3] - T[:3, 3])
    offsets = np.array(offsets)
    # relative geometry recovered; the common placement is the localization's (see docs)
    assert np.all(np.linalg.norm(offsets - offsets.mean(axis=0), axis=1) < 0.02)
    # everything but the camera poses is kept
    before, after = _doc(perturbed), _doc(out)
    for key in before:
        if key != "cameras":
            assert after[key] == before[key], key
    for b, a in zip(before["cameras"], after["cameras"], strict=True):
        assert {k: v for k, v in a.items() if k != "T_world_cam"} == \
               {k: v for k, v in b.items() if k != "T_world_cam"}
    rep = json.loads(report.read_text())
    assert rep["written"] == ["cam1", "cam2", "cam3", "cam4"]
    assert all(c["status"] == "ok" and c["sightings"] >= 30 for c in rep["cameras"].values())


def test_camera_option_changes_only_that_camera(lab, tmp_path, capsys):
    site = load_site(lab["site"])
    bumped_T = perturbed_camera_poses(site, 0.05, 1.0, seed=3)["cam3"]
    bumped = tmp_path / "bumped.yaml"
    write_site_with_cameras(lab["site"], bumped, {"cam3": bumped_T})
    out = tmp_path / "fixed.yaml"
    rc = main(["--site", str(bumped), "--recording", str(lab["dir"] / "drive.mcap"),
               "--camera", "cam3", "--out", str(out), *FAST])
    text = capsys.readouterr().out
    assert rc == 0, text
    assert "fixed" in text
    before, after = _doc(bumped), _doc(out)
    for b, a in zip(before["cameras"], after["cameras"], strict=True):
        if b["id"] != "cam3":
            assert a == b
    dt0, dr0 = pose_error(bumped_T, lab["truth"]["cam3"])
    dt, dr = pose_error(load_site(out).cameras["cam3"].T_world_cam, lab["truth"]["cam3"])
    assert dt < 0.03 and dr < 0.2 and dr0 > 0.8, (dt, dr, dt0, dr0)


def test_refused_camera_writes_nothing_unless_partial(lab, tmp_path, capsys):
    out = tmp_path / "out.yaml"
    args = ["--site", lab["site"], "--recording", str(lab["dir"] / "no_cam2.mcap"),
            "--out", str(out), *FAST]
    assert main(args) == 3
    err = capsys.readouterr().err
    assert "REFUSED cam2: cam2 saw the robot in 0 usable frames (minimum 30)" in err
    assert "nothing written" in err and not out.exists()
    assert main([*args, "--partial"]) == 0
    capsys.readouterr()
    new, old = load_site(out), load_site(lab["site"])
    np.testing.assert_allclose(new.cameras["cam2"].T_world_cam, old.cameras["cam2"].T_world_cam)
    assert not np.allclose(new.cameras["cam1"].T_world_cam, old.cameras["cam1"].T_world_cam)


def test_empty_missing_and_damaged_recordings(lab, tmp_path, capsys):
    empty = tmp_path / "empty.mcap"
    Recorder(empty).close()
    out = tmp_path / "o.yaml"
    assert main(["--site", lab["site"], "--recording", str(empty), "--out", str(out)]) == 4
    assert "no messages" in capsys.readouterr().err
    assert main(["--site", lab["site"], "--recording", str(tmp_path / "nope.mcap"),
                 "--out", str(out)]) == 1
    assert "no such recording" in capsys.readouterr().err
    damaged = tmp_path / "damaged.mcap"
    damaged.write_bytes((lab["dir"] / "drive.mcap").read_bytes()[:5000])
    assert main(["--site", lab["site"], "--recording", str(damaged), "--out", str(out)]) == 1
    assert "not a complete MCAP" in capsys.readouterr().err
    assert main(["--site", lab["site"], "--recording", str(empty), "--camera", "cam9",
                 "--out", str(out)]) == 1
    assert "cam9" in capsys.readouterr().err
    assert not out.exists()


def test_nan_keypoints_and_unknown_camera_are_counted(lab, tmp_path, capsys):
    """A recording with hostile messages among the good ones: the good ones calibrate, the
    bad ones are counted and the first error of each kind is named."""
    from smartedge.commands.record import read_recording

    site_name = lab["scenario"].site.name
    path = tmp_path / "mixed.mcap"
    rec = Recorder(path)
    nan_done = unknown_done = False
    for key, receive_ns, payload in read_recording(lab["dir"] / "drive.mcap"):
        rec.write(key, payload, receive_ns)
        msg = decode(payload)
        if isinstance(msg, RobotDetections) and msg.detections and not nan_done:
            wire = msgpack.unpackb(payload, raw=False)
            kp = np.frombuffer(wire["detections"][0]["keypoints_px"]["data"], "<f8").copy()
            kp[3] = np.nan
            wire["detections"][0]["keypoints_px"]["data"] = kp.tobytes()
            rec.write(key, msgpack.packb(wire), receive_ns + 1)
            nan_done = True
        elif isinstance(msg, RobotDetections) and not unknown_done:
            wire = msgpack.unpackb(payload, raw=False)
            wire["camera_id"] = "cam9"
            rec.write(keys.detections_key(site_name, "cam9"), msgpack.packb(wire),
                      receive_ns + 1)
            unknown_done = True
    rec.close()
    out = tmp_path / "o.yaml"
    rc = main(["--site", lab["site"], "--recording", str(path), "--out", str(out), *FAST])
    text = capsys.readouterr().out
    assert rc == 0, text
    assert "undecodable 1" in text and "keypoints_px" in text
    assert "unknown_camera 1" in text and "cam9" in text


def test_live_on_the_bus(lab, tmp_path, capsys):
    """--live: a real Zenoh subscription on loopback; the recorded drive is published on its
    keys while the command listens."""
    import threading
    import time

    import zenoh

    from core.session import loopback_config
    from smartedge.commands.record import read_recording
    from tests.conftest import free_port

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    out = tmp_path / "live.yaml"
    messages = list(read_recording(lab["dir"] / "drive.mcap"))
    result: dict[str, int] = {}
    with zenoh.open(loopback_config(listen=[endpoint])) as hub:
        pubs = {key: hub.declare_publisher(key, congestion_control=zenoh.CongestionControl.BLOCK,
                                           reliability=zenoh.Reliability.RELIABLE)
                for key in sorted({k for k, _, _ in messages})}

        def run() -> None:
            # the drive is put all at once (well under a second) as soon as the command's
            # subscriptions match; what arrives before the end is read, the count is exact
            result["rc"] = main(["--site", lab["site"], "--live", "--duration", "4",
                                 "--out", str(out), *FAST, "--mode", "client", "--connect",
                                 endpoint, "--no-multicast-scouting"])

        thread = threading.Thread(target=run, daemon=True)
        thread.start()
        deadline = time.monotonic() + 20
        while not all(p.matching_status.matching for p in pubs.values()):
            assert time.monotonic() < deadline, "the command's subscriptions never matched"
            time.sleep(0.05)
        for key, _ns, payload in messages:
            pubs[key].put(payload)
        sent = len(messages)
        thread.join(60)
    text = capsys.readouterr().out
    assert result.get("rc") == 0, text
    assert f"{sent} messages read" in text and "listening on" in text
    assert load_site(out).cameras.keys() == load_site(lab["site"]).cameras.keys()
