"""``smartedge dataset capture --recording``: a lab's ROS 2 bag of its cameras (written here by
rosbags' rosbag2 writer with MCAP storage, Image and CompressedImage topics) becomes the layout
``edge-agent --capture`` writes: frames named by their header stamps, raw images lossless, JPEG
kept byte for byte, a damaged message named and skipped."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest

from smartedge.commands.dataset import main

T0 = 1_700_000_000_000_000_000


def _store() -> Any:
    from robot_bridge.adapters.ros2 import typestore

    return typestore()


def _header(ts: Any, stamp_ns: int, frame_id: str) -> Any:
    t = ts.types
    sec, nsec = divmod(stamp_ns, 1_000_000_000)
    return t["std_msgs/msg/Header"](t["builtin_interfaces/msg/Time"](sec, nsec), frame_id)


def _bag(tmp_path: Path) -> tuple[Path, dict[int, np.ndarray], dict[int, bytes]]:
    from rosbags.rosbag2 import StoragePlugin, Writer

    ts = _store()
    rng = np.random.default_rng(3)
    raw: dict[int, np.ndarray] = {}
    jpegs: dict[int, bytes] = {}
    folder = tmp_path / "lab_bag"
    with Writer(folder, version=8, storage_plugin=StoragePlugin.MCAP) as w:
        img_conn = w.add_connection("/cam1/image_raw", "sensor_msgs/msg/Image", typestore=ts)
        jpg_conn = w.add_connection("/cam2/image/compressed", "sensor_msgs/msg/CompressedImage",
                                    typestore=ts)
        for i in range(6):
            stamp = T0 + i * 200_000_000  # 5 Hz, header stamps (the bag's times lag behind)
            rgb = rng.integers(0, 256, (48, 64, 3), dtype=np.uint8)
            raw[stamp] = rgb
            msg = ts.types["sensor_msgs/msg/Image"](_header(ts, stamp, "cam1_optical"), 48, 64,
                                                    "rgb8", 0, 64 * 3, rgb.reshape(-1))
            w.write(img_conn, stamp + 30_000_000, ts.serialize_cdr(msg, msg.__msgtype__))
            data = cv2.imencode(".jpg", cv2.GaussianBlur(rgb, (5, 5), 2))[1].tobytes()
            jpegs[stamp + 1] = data
            msg = ts.types["sensor_msgs/msg/CompressedImage"](
                _header(ts, stamp + 1, "cam2_optical"), "jpeg",
                np.frombuffer(data if i != 4 else data[:40], np.uint8))  # message 4 damaged
            w.write(jpg_conn, stamp + 31_000_000, ts.serialize_cdr(msg, msg.__msgtype__))
    (mcap,) = folder.glob("*.mcap")
    return mcap, raw, jpegs


def test_frames_of_a_ros2_bag_in_the_capture_layout(tmp_path: Path, capsys) -> None:
    mcap, raw, jpegs = _bag(tmp_path)
    out = tmp_path / "frames"
    assert main(["capture", "--recording", str(mcap), "--out", str(out),
                 "--camera", "/cam1/image_raw=cam1",
                 "--camera", "/cam2/image/compressed=cam2"]) == 0
    captured = capsys.readouterr()
    assert "/cam2/image/compressed message" in captured.err  # the damaged one, named
    cam1 = sorted((out / "cam1").iterdir())
    assert [p.name for p in cam1] == [f"{s}.png" for s in sorted(raw)]
    for p in cam1:
        back = cv2.cvtColor(cv2.imread(str(p)), cv2.COLOR_BGR2RGB)
        np.testing.assert_array_equal(back, raw[int(p.stem)])  # lossless, RGB order kept
    cam2 = sorted((out / "cam2").iterdir())
    assert len(cam2) == 5  # six messages, one damaged
    for p in cam2:
        assert p.suffix == ".jpg" and p.read_bytes() == jpegs[int(p.stem)]  # byte for byte

    # every image topic, named after the topic, at 2 Hz of capture time
    out2 = tmp_path / "frames2"
    assert main(["capture", "--recording", str(mcap), "--out", str(out2), "--rate", "2"]) == 0
    names = sorted(p.name for p in (out2 / "cam1_image_raw").iterdir())
    assert names == [f"{T0}.png", f"{T0 + 600_000_000}.png"]  # 0 and 0.6 s of 0..1 s at 5 Hz


def test_a_recording_without_images_or_damaged_is_named(tmp_path: Path, capsys) -> None:
    mcap, _, _ = _bag(tmp_path)
    assert main(["capture", "--recording", str(mcap), "--out", str(tmp_path / "o"),
                 "--camera", "/nothing=cam9"]) == 1
    assert "no sensor_msgs/Image or CompressedImage topic among ['/nothing']" in \
        capsys.readouterr().err
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(mcap.read_bytes()[: mcap.stat().st_size // 2])
    assert main(["capture", "--recording", str(cut), "--out", str(tmp_path / "o2")]) == 1
    err = capsys.readouterr().err
    assert "cut.mcap: not a complete MCAP recording" in err
    assert main(["capture", "--recording", str(tmp_path / "absent.mcap"), "--out", "x"]) == 1
    with pytest.raises(SystemExit):
        main(["capture", "--out", "x"])
