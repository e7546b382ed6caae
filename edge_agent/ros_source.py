"""``--source ros``: camera images from ROS 2 topics on the Zenoh bus.

A lab's camera drivers already publish ``sensor_msgs/Image`` or ``sensor_msgs/CompressedImage``
(jpeg, png) and ``sensor_msgs/CameraInfo``. The edge agent reads them straight off Zenoh, in
either of the two ways ROS 2 reaches Zenoh:

* ``rmw_zenoh`` (Jazzy and newer, ``RMW_IMPLEMENTATION=rmw_zenoh_cpp``): key
  ``<domain>/<topic>/sensor_msgs::msg::dds_::Image_/<type hash>`` (the hash is matched with
  ``*``), each sample with rmw_zenoh's attachment (sequence number, source timestamp, GID;
  sequence gaps are counted ``ros_messages_lost``);
* ``ros2dds`` (``zenoh-bridge-ros2dds`` beside the driver): key ``[<bridge namespace>/]<topic>``.

Both carry the CDR payload of the message. An edge board has neither rosbags nor a ROS
installation, so the three messages are decoded here (:func:`decode_image`,
:func:`decode_compressed_image`, :func:`decode_camera_info`): fixed layouts, every length
checked against the bytes that are left before anything is allocated. A truncated or hostile
message raises :class:`RosImageError`, whose ``counter`` names the status counter it is counted
under; the source logs it (once per kind and minute) and goes on with the next message.

The header stamp is the capture time of the frame. The newest ``CameraInfo`` is compared with
the site's calibration of the camera (size, K, distortion); a difference is logged once and
named in the status until a matching ``CameraInfo`` arrives.

Zenoh callbacks only keep the newest raw sample (replaced ones are counted ``frames_skipped``);
decoding and conversion to RGB happen in the service's worker loop (:meth:`RosImageSource.poll`).

Depth and RGB-D: ``sensor_msgs/Image`` depth in ``16UC1`` (millimetres, 0 = no depth) or
``32FC1`` (metres; NaN, inf, 0 or negative = no depth), either byte order, decodes to (H, W)
float32 metres with NaN where there is no depth (:func:`decode_depth_image`,
:func:`depth_to_m`). With a depth topic (``--ros-depth-topic``) the source pairs each colour
image with the aligned depth image of the same header stamp (exactly, or within
:attr:`RosTopicConfig.sync_tolerance_ns`, 5 ms by default): both streams are kept in bounded
buffers of :data:`RGBD_QUEUE` messages, a message that can no longer find its partner is
counted ``rgbd_unmatched``, a depth image of another size than its colour image
``depth_size_mismatch`` (the colour frame still gives detections). The frames then carry
``depth_m`` and the edge agent makes semantic clouds of them.
"""

from __future__ import annotations

import argparse
import collections
import dataclasses
import itertools
import logging
import re
import struct
import threading
import time
from collections.abc import Callable
from typing import Any, Final

import numpy as np

from core.site import Site
from edge_agent.frames import Frame
from edge_agent.sources import PipelineSource, execution_providers_from_args, register_source
from protocol.errors import SmartedgeError, UsageError

log = logging.getLogger(__name__)

IMAGE_TYPE: Final = "sensor_msgs/msg/Image"
COMPRESSED_IMAGE_TYPE: Final = "sensor_msgs/msg/CompressedImage"
CAMERA_INFO_TYPE: Final = "sensor_msgs/msg/CameraInfo"
TRANSPORTS: Final = ("rmw_zenoh", "ros2dds")
#: REP-2016 type hashes of the Jazzy definitions, for the subscriptions' liveliness tokens (the
#: tests check them against rosbags' typestore; the keys match any hash)
TYPE_HASHES: Final = {
    IMAGE_TYPE: "RIHS01_d31d41a9a4c4bc8eae9be757b0beed306564f7526c88ea6a4588fb9582527d47",
    COMPRESSED_IMAGE_TYPE:
        "RIHS01_15640771531571185e2efc8a100baf923961a4d15d5569652e6cb6691e8e371a",
    CAMERA_INFO_TYPE: "RIHS01_b3dfd68ff46c9d56c80fd3bd4ed22c7a4ddce8c8348f2f59c299e73118e7e275",
}
#: the QoS field of the subscriptions' tokens: best effort, keep last 10 (matches every
#: publisher; rmw_zenoh's token encoding, defaults left empty)
SUBSCRIPTION_QOS_FIELD: Final = "2::,10:,:,:,,"
#: node and entity ids of this process's rmw_zenoh tokens
_ENTITY_IDS = itertools.count()

#: largest image payload accepted (a 4096x3072 rgb8 frame is 36 MiB)
MAX_PAYLOAD_BYTES: Final = 64 * 1024 * 1024
#: largest width or height accepted
MAX_SIDE_PX: Final = 16384
#: longest string field (frame id, encoding, format, distortion model)
MAX_STRING_BYTES: Final = 256
#: most distortion coefficients accepted in a CameraInfo
MAX_DISTORTION: Final = 64
#: relative tolerance of K against the site's calibration
K_RTOL: Final = 1e-3
#: absolute tolerance of each distortion coefficient
DIST_ATOL: Final = 1e-4
#: seconds between two log lines of the same error kind
ERROR_LOG_PERIOD_S: Final = 60.0
#: seconds without a good frame after which the source reports ``degraded``
STALE_AFTER_S: Final = 5.0

#: bytes per pixel of the raw encodings handled, and how each becomes RGB
_RAW_BPP: Final = {"rgb8": 3, "bgr8": 3, "rgba8": 4, "bgra8": 4, "mono8": 1,
                   "yuv422": 2, "uyvy": 2, "yuv422_yuy2": 2, "yuyv": 2,
                   "bayer_rggb8": 1, "bayer_bggr8": 1, "bayer_gbrg8": 1, "bayer_grbg8": 1}
#: the encodings :func:`image_to_rgb` converts
SUPPORTED_ENCODINGS: Final = tuple(_RAW_BPP)
#: depth encodings (lower case): numpy element type and units per metre
_DEPTH_TYPES: Final = {"16uc1": ("u2", 1000.0), "32fc1": ("f4", 1.0)}
#: the encodings :func:`depth_to_m` converts, as ROS spells them
DEPTH_ENCODINGS: Final = ("16UC1", "32FC1")
#: messages kept per stream while an RGB-D pair is waiting for its partner
RGBD_QUEUE: Final = 4
#: default largest stamp difference of a colour image and its depth image
DEFAULT_SYNC_TOLERANCE_NS: Final = 5_000_000


class RosImageError(SmartedgeError):
    """A ROS image or camera info that cannot be used. ``counter``: the status counter it is
    counted under (``ros_truncated``, ``ros_bad_encoding``, ...)."""

    def __init__(self, counter: str, message: str) -> None:
        super().__init__(message)
        self.counter = counter


# --------------------------------------------------------------------------------------------
# CDR
# --------------------------------------------------------------------------------------------


class CdrReader:
    """Sequential reader of one CDR payload (4-byte encapsulation header, then the message;
    alignment counted from the end of the header, as DDS and rmw_zenoh write it)."""

    def __init__(self, payload: bytes | memoryview, what: str) -> None:
        self.buf = memoryview(payload)
        self.what = what
        if len(self.buf) < 4:
            raise RosImageError("ros_truncated", f"{what}: {len(self.buf)} bytes, no CDR header")
        kind = bytes(self.buf[:2])
        if kind in (b"\x00\x01", b"\x00\x03"):
            self.endian = "<"
        elif kind in (b"\x00\x00", b"\x00\x02"):
            self.endian = ">"
        else:
            raise RosImageError("ros_not_cdr", f"{what}: encapsulation {kind.hex()} is not "
                                "plain CDR")
        self.pos = 4

    def _need(self, n: int, field: str) -> None:
        if n < 0 or self.pos + n > len(self.buf):
            raise RosImageError("ros_truncated", f"{self.what}: ends inside {field} (needs {n} "
                                f"bytes at offset {self.pos}, has {len(self.buf) - self.pos})")

    def align(self, n: int) -> None:
        self.pos += (-(self.pos - 4)) % n

    def scalar(self, fmt: str, size: int, field: str) -> Any:
        self.align(size)
        self._need(size, field)
        value = struct.unpack_from(self.endian + fmt, self.buf, self.pos)[0]
        self.pos += size
        return value

    def u8(self, field: str) -> int:
        self._need(1, field)
        self.pos += 1
        return int(self.buf[self.pos - 1])

    def u32(self, field: str) -> int:
        return int(self.scalar("I", 4, field))

    def i32(self, field: str) -> int:
        return int(self.scalar("i", 4, field))

    def string(self, field: str) -> str:
        n = self.u32(f"the length of {field}")
        if n > MAX_STRING_BYTES + 1:
            raise RosImageError("ros_bad_field", f"{self.what}: {field} of {n} bytes (at most "
                                f"{MAX_STRING_BYTES})")
        self._need(n, field)
        raw = bytes(self.buf[self.pos:self.pos + n])
        self.pos += n
        try:
            return raw.rstrip(b"\x00").decode("utf-8")
        except UnicodeDecodeError:
            raise RosImageError("ros_bad_field", f"{self.what}: {field} is not UTF-8") from None

    def octets(self, field: str) -> memoryview:
        n = self.u32(f"the length of {field}")
        self._need(n, field)
        out = self.buf[self.pos:self.pos + n]
        self.pos += n
        return out

    def doubles(self, n: int, field: str) -> np.ndarray:
        self.align(8)
        self._need(8 * n, field)
        out = np.frombuffer(self.buf, dtype=self.endian + "f8", count=n, offset=self.pos)
        self.pos += 8 * n
        return out.astype(np.float64)

    def header(self) -> tuple[int, str]:
        sec = self.i32("header.stamp.sec")
        nanosec = self.u32("header.stamp.nanosec")
        if nanosec >= 1_000_000_000:
            raise RosImageError("ros_bad_field", f"{self.what}: header.stamp.nanosec {nanosec}")
        return sec * 1_000_000_000 + nanosec, self.string("header.frame_id")


# --------------------------------------------------------------------------------------------
# messages
# --------------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class RosImage:
    """A decoded ``sensor_msgs/Image``; ``data`` is a view into the payload (no copy)."""

    stamp_ns: int
    frame_id: str
    height: int
    width: int
    encoding: str
    is_bigendian: bool
    step: int
    data: memoryview


@dataclasses.dataclass(frozen=True)
class RosCompressedImage:
    """A decoded ``sensor_msgs/CompressedImage``."""

    stamp_ns: int
    frame_id: str
    format: str
    data: memoryview


@dataclasses.dataclass(frozen=True)
class RosCameraInfo:
    """The fields of a ``sensor_msgs/CameraInfo`` the edge agent checks (and R, P)."""

    stamp_ns: int
    frame_id: str
    height: int
    width: int
    distortion_model: str
    D: np.ndarray
    K: np.ndarray
    R: np.ndarray
    P: np.ndarray


def _size(cdr: CdrReader) -> tuple[int, int]:
    height, width = cdr.u32("height"), cdr.u32("width")
    if not (0 < height <= MAX_SIDE_PX and 0 < width <= MAX_SIDE_PX):
        raise RosImageError("ros_bad_size", f"{cdr.what}: size {width}x{height} (sides 1 to "
                            f"{MAX_SIDE_PX})")
    return height, width


def _read_image(payload: bytes | memoryview, what: str,
                bytes_per_pixel: Callable[[str], int], *, depth: bool) -> RosImage:
    """The fields of a ``sensor_msgs/Image`` with its size checks: ``bytes_per_pixel(encoding)``
    says how wide a pixel of that encoding is (or raises ``ros_bad_encoding``); a ``step``
    shorter than a row is ``ros_bad_size``, data shorter than ``step * height``
    ``ros_truncated``. The encoding is returned upper case for depth (``16UC1``), lower case
    otherwise."""
    cdr = CdrReader(payload, what)
    stamp_ns, frame_id = cdr.header()
    height, width = _size(cdr)
    encoding = cdr.string("encoding")
    is_bigendian = bool(cdr.u8("is_bigendian"))
    step = cdr.u32("step")
    data = cdr.octets("data")
    bpp = bytes_per_pixel(encoding)  # the encoding as sent, for the error message
    if step < width * bpp:
        raise RosImageError("ros_bad_size", f"{what}: step {step} < width {width} x {bpp} "
                            f"bytes ({encoding})")
    if len(data) < step * height:
        raise RosImageError("ros_truncated", f"{what}: {len(data)} data bytes for "
                            f"{height} rows of {step} ({width}x{height} {encoding})")
    return RosImage(stamp_ns, frame_id, height, width,
                    encoding.upper() if depth else encoding.lower(), is_bigendian, step, data)


def decode_image(payload: bytes | memoryview, what: str = "Image") -> RosImage:
    """``sensor_msgs/Image`` from its CDR bytes; :class:`RosImageError` when truncated or
    inconsistent (``step`` too small for the encoding, data shorter than ``step * height``)."""

    def colour_bpp(encoding: str) -> int:
        bpp = _RAW_BPP.get(encoding.lower())
        if bpp is None and encoding.lower() in _DEPTH_TYPES:
            raise RosImageError("ros_bad_encoding", f"{what}: encoding {encoding!r} is a "
                                "depth image, not a colour image (a depth topic is read with "
                                "--ros-depth-topic)")
        if bpp is None:
            raise RosImageError("ros_bad_encoding", f"{what}: encoding {encoding!r} is not "
                                f"supported (one of {', '.join(SUPPORTED_ENCODINGS)})")
        return bpp

    return _read_image(payload, what, colour_bpp, depth=False)


def decode_depth_image(payload: bytes | memoryview, what: str = "depth Image") -> RosImage:
    """A depth ``sensor_msgs/Image`` (``16UC1`` or ``32FC1``, either byte order) from its CDR
    bytes; :class:`RosImageError` for another encoding (``ros_bad_encoding``), a ``step``
    shorter than a row (``ros_bad_size``) and data shorter than ``step * height``
    (``ros_truncated``). Row padding of any length, also not a whole number of pixels, is
    handled. Convert with :func:`depth_to_m`."""

    def depth_bpp(encoding: str) -> int:
        kind = _DEPTH_TYPES.get(encoding.lower())
        if kind is None:
            raise RosImageError("ros_bad_encoding", f"{what}: encoding {encoding!r} is not a "
                                f"depth encoding (one of {', '.join(DEPTH_ENCODINGS)})")
        return int(kind[0][1])

    return _read_image(payload, what, depth_bpp, depth=True)


def depth_to_m(image: RosImage) -> np.ndarray:
    """(H, W) float32 depth in metres of a decoded depth image, NaN where there is none
    (``16UC1`` 0; ``32FC1`` NaN, inf, 0 or negative); row padding dropped, the message's byte
    order honoured."""
    kind = _DEPTH_TYPES.get(image.encoding.lower())
    if kind is None:
        raise RosImageError("ros_bad_encoding", f"depth image: encoding {image.encoding!r} is "
                            f"not a depth encoding (one of {', '.join(DEPTH_ENCODINGS)})")
    code, per_metre = kind
    bpp = int(code[1])
    dtype = np.dtype((">" if image.is_bigendian else "<") + code)
    rows = np.frombuffer(image.data, np.uint8, count=image.step * image.height)
    raw = rows.reshape(image.height, image.step)[:, :image.width * bpp]
    values = np.ascontiguousarray(raw).view(dtype)  # a copy only with row padding
    out = values.astype(np.float32)
    if per_metre != 1.0:
        out /= np.float32(per_metre)  # correctly rounded: 1500 mm is exactly 1.5 m
        out[values == 0] = np.nan
    else:
        with np.errstate(invalid="ignore"):
            out[~(np.isfinite(out) & (out > 0.0))] = np.nan
    return out


def decode_header(payload: bytes | memoryview, what: str = "message") -> tuple[int, str]:
    """(header stamp ns, frame id) of any message that starts with a ``std_msgs/Header``
    (Image, CompressedImage, CameraInfo), without reading the rest."""
    return CdrReader(payload, what).header()


def decode_compressed_image(payload: bytes | memoryview,
                            what: str = "CompressedImage") -> RosCompressedImage:
    """``sensor_msgs/CompressedImage`` from its CDR bytes."""
    cdr = CdrReader(payload, what)
    stamp_ns, frame_id = cdr.header()
    fmt = cdr.string("format")
    data = cdr.octets("data")
    if not data:
        raise RosImageError("ros_truncated", f"{what}: no data")
    return RosCompressedImage(stamp_ns, frame_id, fmt, data)


def decode_camera_info(payload: bytes | memoryview, what: str = "CameraInfo") -> RosCameraInfo:
    """``sensor_msgs/CameraInfo`` from its CDR bytes (binning and ROI are read, not kept)."""
    cdr = CdrReader(payload, what)
    stamp_ns, frame_id = cdr.header()
    height, width = _size(cdr)
    model = cdr.string("distortion_model")
    n = cdr.u32("the length of d")
    if n > MAX_DISTORTION:
        raise RosImageError("ros_bad_field", f"{what}: {n} distortion coefficients (at most "
                            f"{MAX_DISTORTION})")
    D = cdr.doubles(n, "d")
    K = cdr.doubles(9, "k").reshape(3, 3)
    R = cdr.doubles(9, "r").reshape(3, 3)
    P = cdr.doubles(12, "p").reshape(3, 4)
    for field in ("binning_x", "binning_y", "roi.x_offset", "roi.y_offset", "roi.height",
                  "roi.width"):
        cdr.u32(field)
    cdr.u8("roi.do_rectify")
    if not (np.all(np.isfinite(D)) and np.all(np.isfinite(K))):
        raise RosImageError("ros_bad_field", f"{what}: K or d is not finite")
    return RosCameraInfo(stamp_ns, frame_id, height, width, model, D, K, R, P)


# --------------------------------------------------------------------------------------------
# conversion to RGB
# --------------------------------------------------------------------------------------------

_BAYER: Final = {"bayer_rggb8": "COLOR_BayerBG2RGB", "bayer_bggr8": "COLOR_BayerRG2RGB",
                 "bayer_gbrg8": "COLOR_BayerGR2RGB", "bayer_grbg8": "COLOR_BayerGB2RGB"}


def image_to_rgb(image: RosImage) -> np.ndarray:
    """(H, W, 3) uint8 RGB of a decoded raw image (rows of ``step`` bytes, padding dropped)."""
    import cv2

    bpp = _RAW_BPP[image.encoding]
    rows = np.frombuffer(image.data, np.uint8, count=image.step * image.height)
    pixels = rows.reshape(image.height, image.step)[:, :image.width * bpp]
    enc = image.encoding
    if enc == "rgb8":
        return np.ascontiguousarray(pixels.reshape(image.height, image.width, 3))
    if enc in ("bgr8", "rgba8", "bgra8"):
        code = {"bgr8": cv2.COLOR_BGR2RGB, "rgba8": cv2.COLOR_RGBA2RGB,
                "bgra8": cv2.COLOR_BGRA2RGB}[enc]
        return cv2.cvtColor(pixels.reshape(image.height, image.width, bpp), code)
    if enc == "mono8":
        return cv2.cvtColor(np.ascontiguousarray(pixels), cv2.COLOR_GRAY2RGB)
    if enc in ("yuv422", "uyvy", "yuv422_yuy2", "yuyv"):
        if image.width % 2:
            raise RosImageError("ros_bad_size", f"{enc}: odd width {image.width}")
        code = cv2.COLOR_YUV2RGB_UYVY if enc in ("yuv422", "uyvy") else cv2.COLOR_YUV2RGB_YUY2
        return cv2.cvtColor(pixels.reshape(image.height, image.width, 2), code)
    return cv2.cvtColor(np.ascontiguousarray(pixels), getattr(cv2, _BAYER[enc]))


#: most pixels a compressed image may declare (checked in its header before decoding)
MAX_COMPRESSED_PIXELS: Final = 4096 * 4096
_SOF_MARKERS: Final = frozenset(range(0xC0, 0xD0)) - {0xC4, 0xC8, 0xCC}


def compressed_size(data: bytes | memoryview) -> tuple[int, int] | None:
    """(width, height) a png or jpeg declares in its header (IHDR, the first SOF segment),
    read without decoding; ``None`` when neither is found."""
    buf = bytes(data[:min(len(data), 1 << 16)])
    if buf.startswith(b"\x89PNG\r\n\x1a\n") and len(buf) >= 24 and buf[12:16] == b"IHDR":
        w, h = struct.unpack_from(">II", buf, 16)
        return int(w), int(h)
    if not buf.startswith(b"\xff\xd8"):
        return None
    pos = 2
    while pos + 4 <= len(buf):
        if buf[pos] != 0xFF:
            return None
        marker = buf[pos + 1]
        if marker == 0xFF:  # fill byte
            pos += 1
            continue
        if marker in (0x01, *range(0xD0, 0xD8)):  # markers without a length
            pos += 2
            continue
        length = struct.unpack_from(">H", buf, pos + 2)[0]
        if marker in _SOF_MARKERS:
            if pos + 9 > len(buf):
                return None
            h, w = struct.unpack_from(">HH", buf, pos + 5)
            return int(w), int(h)
        pos += 2 + length
    return None


def compressed_to_rgb(image: RosCompressedImage) -> np.ndarray:
    """(H, W, 3) uint8 RGB of a jpeg or png ``CompressedImage`` (``format`` as image_transport
    writes it: ``jpeg``, ``png``, ``bgr8; jpeg compressed bgr8``...)."""
    import cv2

    fmt = image.format.lower()
    if not any(word in fmt for word in ("jpeg", "jpg", "png")):
        raise RosImageError("ros_bad_encoding", f"CompressedImage: format {image.format!r} is "
                            "not jpeg or png")
    if "compresseddepth" in fmt.replace(" ", ""):
        raise RosImageError("ros_bad_encoding", f"CompressedImage: format {image.format!r} "
                            "is a depth image")
    size = compressed_size(image.data)
    if size is None:
        raise RosImageError("ros_undecodable", f"CompressedImage: {len(image.data)} bytes of "
                            f"{image.format!r} have no png or jpeg header")
    if not (0 < size[0] <= MAX_SIDE_PX and 0 < size[1] <= MAX_SIDE_PX
            and size[0] * size[1] <= MAX_COMPRESSED_PIXELS):
        raise RosImageError("ros_bad_size", f"CompressedImage: declares {size[0]}x{size[1]} "
                            f"pixels (at most {MAX_COMPRESSED_PIXELS}); not decoded")
    bgr = cv2.imdecode(np.frombuffer(image.data, np.uint8), cv2.IMREAD_COLOR)
    if bgr is None or bgr.ndim != 3 or not (0 < bgr.shape[0] <= MAX_SIDE_PX
                                            and 0 < bgr.shape[1] <= MAX_SIDE_PX):
        raise RosImageError("ros_undecodable", f"CompressedImage: {len(image.data)} bytes of "
                            f"{image.format!r} do not decode")
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)


def check_camera_info(info: RosCameraInfo, camera: Any) -> list[str]:
    """How ``info`` differs from the site's calibration ``camera`` (a
    :class:`core.camera.CameraModel`): size, K (relative :data:`K_RTOL`), distortion
    (:data:`DIST_ATOL`, missing coefficients read as 0); empty when it agrees."""
    out = []
    if (info.width, info.height) != (camera.width, camera.height):
        out.append(f"size {info.width}x{info.height} (site: {camera.width}x{camera.height})")
    K_site = np.asarray(camera.K, np.float64)
    if not np.allclose(info.K, K_site, rtol=K_RTOL, atol=K_RTOL):
        fx, fy, cx, cy = info.K[0, 0], info.K[1, 1], info.K[0, 2], info.K[1, 2]
        sx, sy, scx, scy = K_site[0, 0], K_site[1, 1], K_site[0, 2], K_site[1, 2]
        out.append(f"K fx fy cx cy = {fx:.2f} {fy:.2f} {cx:.2f} {cy:.2f} (site: {sx:.2f} "
                   f"{sy:.2f} {scx:.2f} {scy:.2f})")
    d_site = np.asarray(camera.dist, np.float64).reshape(-1)
    n = max(d_site.size, info.D.size)
    a, b = np.zeros(n), np.zeros(n)
    a[:info.D.size], b[:d_site.size] = info.D, d_site
    if not np.allclose(a, b, rtol=0.0, atol=DIST_ATOL):
        out.append(f"distortion {info.distortion_model} {np.round(info.D, 5).tolist()} "
                   f"(site: {np.round(d_site, 5).tolist()})")
    return out


# --------------------------------------------------------------------------------------------
# keys and attachment
# --------------------------------------------------------------------------------------------


def _topic_tokens(topic: str) -> list[str]:
    tokens = [t for t in str(topic).strip().split("/") if t]
    if not tokens or any(not (t[0].isalpha() or t[0] == "_") or
                         not all(c.isalnum() or c == "_" for c in t) for t in tokens):
        raise UsageError(f"invalid ROS topic name {topic!r} (tokens of letters, digits and _)")
    return tokens


def dds_type_name(ros_type: str) -> str:
    """``sensor_msgs/msg/Image`` → ``sensor_msgs::msg::dds_::Image_`` (rmw_zenoh's keys)."""
    package, kind, name = ros_type.split("/")
    return f"{package}::{kind}::dds_::{name}_"


def topic_key(transport: str, topic: str, ros_type: str, *, domain_id: int = 0,
              namespace: str = "") -> str:
    """The key expression a ROS 2 topic is on: rmw_zenoh
    ``<domain>/<topic>/<dds type>/*`` (any type hash), ros2dds ``[<namespace>/]<topic>``."""
    name = "/".join(_topic_tokens(topic))
    if transport == "rmw_zenoh":
        return f"{int(domain_id)}/{name}/{dds_type_name(ros_type)}/*"
    if transport == "ros2dds":
        ns = "/".join(_topic_tokens(namespace)) if str(namespace).strip("/ ") else ""
        return f"{ns}/{name}" if ns else name
    raise UsageError(f"ROS transport {transport!r}: expected one of {TRANSPORTS}")


def camera_info_topic(image_topic: str) -> str:
    """The ``camera_info`` beside an image topic, as image_transport pairs them:
    ``/cam/color/image_raw`` and ``/cam/color/image_raw/compressed`` →
    ``/cam/color/camera_info``."""
    tokens = _topic_tokens(image_topic)
    if len(tokens) > 1 and tokens[-1] in ("compressed", "theora", "zstd"):
        tokens = tokens[:-1]
    return "/" + "/".join([*tokens[:-1], "camera_info"])


def liveliness_tokens(domain_id: int, zid: str, node_name: str,
                      subscriptions: list[tuple[str, str]]) -> list[str]:
    """The rmw_zenoh liveliness keys of a node ``node_name`` (namespace and enclave ``/``)
    with a subscription per ``(topic, ros type)``: the node's token first. A driver behind
    image_transport publishes only while it sees a subscriber in the ROS graph, which under
    rmw_zenoh is made of these tokens."""
    node = re.sub(r"[^A-Za-z0-9_]", "_", node_name)
    if not node or node[0].isdigit():
        node = f"n_{node}"
    node_id = next(_ENTITY_IDS)
    head = f"@ros2_lv/{int(domain_id)}/{zid}/{node_id}"
    out = [f"{head}/{node_id}/NN/%/%/{node}"]
    for topic, ros_type in subscriptions:
        mangled = "%" + "%".join(_topic_tokens(topic))
        out.append(f"{head}/{next(_ENTITY_IDS)}/MS/%/%/{node}/{mangled}/"
                   f"{dds_type_name(ros_type)}/{TYPE_HASHES[ros_type]}/{SUBSCRIPTION_QOS_FIELD}")
    return out


_KEYED_PREFIX: Final = b"\x0fsequence_number"


def attachment_sequence(attachment: bytes | None) -> tuple[bytes, int] | None:
    """(GID, sequence number) of an rmw_zenoh attachment (the 33-byte layout of
    rmw_zenoh_cpp >= 0.2.4 or the keyed one before it), ``None`` when it is neither."""
    if not attachment:
        return None
    data = bytes(attachment)
    if data.startswith(_KEYED_PREFIX):  # name, int64, name, int64, name, len, gid
        pos = len(_KEYED_PREFIX)
        if len(data) < pos + 8:
            return None
        seq = struct.unpack_from("<q", data, pos)[0]
        pos += 8 + 1 + len(b"source_timestamp") + 8 + 1 + len(b"source_gid")
        return (data[pos + 1:pos + 17], int(seq)) if len(data) >= pos + 17 else None
    if len(data) < 33 or data[16] != 16:
        return None
    return data[17:33], int(struct.unpack_from("<q", data, 0)[0])


# --------------------------------------------------------------------------------------------
# the frame source
# --------------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class RosTopicConfig:
    """Where the images are: ``transport`` (rmw_zenoh or ros2dds), the image ``topic``,
    ``compressed`` (CompressedImage instead of Image), the ``info_topic`` (``None``: no
    calibration check), rmw_zenoh's ``domain_id`` and the ros2dds bridge's ``namespace``;
    ``depth_topic``: an aligned depth ``Image`` topic (``None``: colour only) paired with the
    colour images when their stamps differ by at most ``sync_tolerance_ns``."""

    transport: str
    topic: str
    compressed: bool = False
    info_topic: str | None = None
    domain_id: int = 0
    namespace: str = ""
    depth_topic: str | None = None
    sync_tolerance_ns: int = DEFAULT_SYNC_TOLERANCE_NS

    def __post_init__(self) -> None:
        if not 0 <= int(self.sync_tolerance_ns) <= 1_000_000_000:
            raise UsageError(f"RGB-D sync tolerance {self.sync_tolerance_ns} ns: expected 0 to "
                             "1 s")

    @property
    def image_key(self) -> str:
        ros_type = COMPRESSED_IMAGE_TYPE if self.compressed else IMAGE_TYPE
        return topic_key(self.transport, self.topic, ros_type, domain_id=self.domain_id,
                         namespace=self.namespace)

    @property
    def info_key(self) -> str | None:
        if self.info_topic is None:
            return None
        return topic_key(self.transport, self.info_topic, CAMERA_INFO_TYPE,
                         domain_id=self.domain_id, namespace=self.namespace)

    @property
    def depth_key(self) -> str | None:
        if self.depth_topic is None:
            return None
        return topic_key(self.transport, self.depth_topic, IMAGE_TYPE,
                         domain_id=self.domain_id, namespace=self.namespace)


class _Slot:
    """The newest ``capacity`` samples of one key, handed from a Zenoh thread to the worker
    (capacity 1: newest only). ``replaced``: samples pushed out before the worker took them."""

    def __init__(self, capacity: int = 1) -> None:
        self.lock = threading.Lock()
        self.items: collections.deque[tuple[bytes, bytes | None]] = collections.deque()
        #: attachments of the samples pushed out (their sequence numbers are not losses)
        self.replaced_attachments: collections.deque[bytes | None] = collections.deque(
            maxlen=256)
        self.capacity = max(1, int(capacity))
        self.received = 0
        self.replaced = 0
        self.oversized = 0

    def put(self, sample: Any) -> None:
        if len(sample.payload) > MAX_PAYLOAD_BYTES:  # refused before its bytes are copied
            with self.lock:
                self.oversized += 1
            return
        att = sample.attachment
        item = (sample.payload.to_bytes(), None if att is None else att.to_bytes())
        with self.lock:
            if len(self.items) >= self.capacity:
                self.replaced_attachments.append(self.items.popleft()[1])
                self.replaced += 1
            self.items.append(item)
            self.received += 1

    def take(self) -> tuple[bytes, bytes | None] | None:
        """The newest sample (older ones still held are counted ``replaced``)."""
        with self.lock:
            if not self.items:
                return None
            self.replaced += len(self.items) - 1
            self.replaced_attachments.extend(att for _, att in list(self.items)[:-1])
            item = self.items[-1]
            self.items.clear()
            return item

    def take_replaced_attachments(self) -> list[bytes | None]:
        """The attachments of the samples replaced since the last call, oldest first."""
        with self.lock:
            out = list(self.replaced_attachments)
            self.replaced_attachments.clear()
            return out

    def take_all(self) -> list[tuple[bytes, bytes | None]]:
        """Every sample held, oldest first."""
        with self.lock:
            out = list(self.items)
            self.items.clear()
            return out


@dataclasses.dataclass
class _Pending:
    """A colour or depth message waiting for its RGB-D partner (header already read)."""

    stamp_ns: int
    payload: bytes
    attachment: bytes | None


@dataclasses.dataclass(frozen=True)
class RosFrame:
    """One decoded frame: the :class:`Frame` (RGB, header stamp, ``depth_m`` when paired)
    and the colour image's ``frame_id`` (the optical frame TF knows it by)."""

    frame: Frame
    frame_id: str


class RosImageSource(PipelineSource):
    """Frames from a ROS 2 image topic through the edge pipeline (see the module docstring).

    ``camera``: the site's calibration of this camera (the ``CameraInfo`` is checked against
    it; ``None``: no check, e.g. a robot's camera known only from its ``CameraInfo``).
    :meth:`attach` subscribes on the service's Zenoh session; :meth:`poll` decodes the
    newest image (and camera info, and with a depth topic the newest RGB-D pair), converts it
    to RGB and runs the pipeline; :meth:`take_frame` does the same without the pipeline."""

    def __init__(self, config: RosTopicConfig, pipeline: Any, camera: Any) -> None:
        super().__init__(pipeline)
        self.config = config
        self.camera = camera
        self.label = f"ros:{config.transport}:{config.topic}"
        self.provides_depth = config.depth_topic is not None
        self._image = _Slot(RGBD_QUEUE if self.provides_depth else 1)
        self._depth = _Slot(RGBD_QUEUE)
        self._info = _Slot()
        self._colour_pending: list[_Pending] = []
        self._depth_pending: list[_Pending] = []
        self._rgbd_skipped = 0
        self._seen_depth_replaced = 0
        self._subscribers: list[Any] = []
        #: the rmw_zenoh liveliness keys declared by :meth:`attach`
        self.token_keys: list[str] = []
        self._seq = 0
        self._last_gid_seq: dict[bytes, int] = {}
        self._seen_skipped = 0
        self._seen_oversized = 0
        self._errors: dict[str, int] = {}
        self._last_logged: dict[str, float] = {}
        self.last_error = ""
        self._last_error_s = 0.0
        self._last_frame_s: float | None = None
        self.calibration_mismatch = ""
        self.info_checked = False
        #: the newest ``CameraInfo`` that decoded (``None`` before the first)
        self.latest_info: RosCameraInfo | None = None
        #: seconds spent decoding + converting the last image (and depth) (for benchmarks)
        self.last_decode_s = 0.0

    # -- transport ---------------------------------------------------------------------------

    def attach(self, session: Any) -> None:
        """Subscribe on ``session`` (the service's); under rmw_zenoh also declare the node's
        and the subscriptions' liveliness tokens (node ``smartedge_edge_<camera>``)."""
        cfg = self.config
        self._subscribers.append(session.declare_subscriber(cfg.image_key, self._image.put))
        if cfg.info_key is not None:
            self._subscribers.append(session.declare_subscriber(cfg.info_key, self._info.put))
        if cfg.depth_key is not None:
            self._subscribers.append(session.declare_subscriber(cfg.depth_key, self._depth.put))
        if cfg.transport == "rmw_zenoh":
            subs = [(cfg.topic, COMPRESSED_IMAGE_TYPE if cfg.compressed else IMAGE_TYPE)]
            if cfg.info_topic is not None:
                subs.append((cfg.info_topic, CAMERA_INFO_TYPE))
            if cfg.depth_topic is not None:
                subs.append((cfg.depth_topic, IMAGE_TYPE))
            name = self.camera.camera_id if self.camera is not None else \
                "_".join(_topic_tokens(cfg.topic))
            self.token_keys = liveliness_tokens(cfg.domain_id, str(session.info.zid()),
                                                f"smartedge_edge_{name}", subs)
            tokens = [session.liveliness().declare_token(key) for key in self.token_keys]
            # entity tokens undeclared first, the node's last (as rmw_zenoh shuts down)
            self._subscribers = tokens[1:] + self._subscribers + tokens[:1]
        log.info("%s: images on %s, camera info on %s%s", self.label, cfg.image_key,
                 cfg.info_key or "(none: no calibration check)",
                 f", depth on {cfg.depth_key} (paired within "
                 f"{cfg.sync_tolerance_ns / 1e6:g} ms)" if cfg.depth_key else "")

    def close(self) -> None:
        for sub in self._subscribers:
            try:
                sub.undeclare()
            except Exception:  # the session is already closed
                log.debug("undeclare failed", exc_info=True)
        self._subscribers = []

    # -- errors ------------------------------------------------------------------------------

    def _count(self, name: str, n: int = 1) -> None:
        self._errors[name] = self._errors.get(name, 0) + n
        if self._stats is not None:
            self._stats.count(name, n)

    def _fail(self, exc: RosImageError, dropped: bool = True) -> None:
        self._count(exc.counter)
        self.last_error = str(exc)
        self._last_error_s = time.monotonic()
        last = self._last_logged.get(exc.counter)
        if last is None or time.monotonic() - last >= ERROR_LOG_PERIOD_S:
            self._last_logged[exc.counter] = time.monotonic()
            log.error("%s: %s (counted %s%s)", self.label, exc, exc.counter,
                      "; the message is dropped" if dropped else "")

    def error_counts(self) -> dict[str, int]:
        """The error counters so far (also in the service's stats)."""
        return dict(self._errors)

    # -- worker ------------------------------------------------------------------------------

    def _check_info(self, payload: bytes) -> None:
        try:
            info = decode_camera_info(payload, f"CameraInfo on {self.config.info_key}")
        except RosImageError as exc:
            self._fail(exc)
            return
        self.info_checked = True
        self.latest_info = info
        if self.camera is None:
            return
        diffs = check_camera_info(info, self.camera)
        text = "; ".join(diffs)
        if text and text != self.calibration_mismatch:
            self._count("ros_camera_info_mismatch")
            log.error("%s: the CameraInfo on %s differs from the site's calibration of %s: %s",
                      self.label, self.config.info_key, self.camera.camera_id, text)
        elif not text and self.calibration_mismatch:
            log.info("%s: the CameraInfo now agrees with the site's calibration", self.label)
        self.calibration_mismatch = text

    def _sequence(self, attachment: bytes | None) -> None:
        """Count sequence gaps per publisher (rmw_zenoh): the colour images replaced before
        the worker took them first (skipped, not lost), then ``attachment``."""
        if self.config.transport != "rmw_zenoh":
            return
        for replaced in self._image.take_replaced_attachments():
            self._sequence_one(replaced, count_missing=False)
        self._sequence_one(attachment)

    def _sequence_one(self, attachment: bytes | None, count_missing: bool = True) -> None:
        parsed = attachment_sequence(attachment)
        if parsed is None:
            if count_missing:
                self._count("ros_missing_attachment" if attachment is None
                            else "ros_invalid_attachment")
            return
        gid, seq = parsed
        last = self._last_gid_seq.get(gid)
        self._last_gid_seq[gid] = seq
        if last is not None and seq > last + 1:
            self._count("ros_messages_lost", seq - last - 1)

    def _decode_colour(self, payload: bytes) -> tuple[np.ndarray, int, str]:
        what = f"{'CompressedImage' if self.config.compressed else 'Image'} on " \
            f"{self.config.image_key}"
        if self.config.compressed:
            msg_c = decode_compressed_image(payload, what)
            return compressed_to_rgb(msg_c), msg_c.stamp_ns, msg_c.frame_id
        msg = decode_image(payload, what)
        return image_to_rgb(msg), msg.stamp_ns, msg.frame_id

    def decode(self, payload: bytes) -> tuple[np.ndarray, int]:
        """(RGB image, header stamp ns) of one image payload; :class:`RosImageError`."""
        rgb, stamp_ns, _ = self._decode_colour(payload)
        return rgb, stamp_ns

    def decode_depth(self, payload: bytes) -> tuple[np.ndarray, int]:
        """(depth (H, W) float32 metres, NaN = none; header stamp ns) of one depth image
        payload; :class:`RosImageError`."""
        msg = decode_depth_image(payload, f"depth Image on {self.config.depth_key}")
        return depth_to_m(msg), msg.stamp_ns

    # -- RGB-D pairing -----------------------------------------------------------------------

    def _pend(self, slot: _Slot, pending: list[_Pending], what: str) -> None:
        for payload, attachment in slot.take_all():
            if slot is self._image:
                self._sequence(attachment)
            try:
                stamp_ns, _ = decode_header(payload, what)
            except RosImageError as exc:
                self._fail(exc)
                continue
            pending.append(_Pending(stamp_ns, payload, attachment))
        pending.sort(key=lambda p: p.stamp_ns)

    def _unmatched(self, n: int = 1) -> None:
        if n > 0:
            self._count("rgbd_unmatched", n)

    def _take_pair(self) -> tuple[_Pending, _Pending] | None:
        """The newest colour message with a depth message within the tolerance, removed with
        everything older; messages that can no longer be paired are counted
        ``rgbd_unmatched``, older colour messages that had a partner ``frames_skipped``."""
        cfg = self.config
        tol = int(cfg.sync_tolerance_ns)
        self._pend(self._image, self._colour_pending, f"Image on {cfg.image_key}")
        self._pend(self._depth, self._depth_pending, f"depth Image on {cfg.depth_key}")
        with self._depth.lock:
            lost = self._depth.replaced - self._seen_depth_replaced
            self._seen_depth_replaced = self._depth.replaced
        self._unmatched(lost)
        colours, depths = self._colour_pending, self._depth_pending

        def partner(c: _Pending) -> _Pending | None:
            best = min(depths, key=lambda d: abs(d.stamp_ns - c.stamp_ns), default=None)
            return best if best is not None and abs(best.stamp_ns - c.stamp_ns) <= tol else None

        pair = None
        for colour in reversed(colours):
            depth = partner(colour)
            if depth is not None:
                pair = (colour, depth)
                break
        if pair is None:
            # streams arrive in stamp order: a message older (beyond the tolerance) than the
            # other stream's newest will never find its partner
            if depths:
                stale = [c for c in colours if c.stamp_ns + tol < depths[-1].stamp_ns]
                self._unmatched(len(stale))
                colours[:] = [c for c in colours if c not in stale]
            if colours:
                stale = [d for d in depths if d.stamp_ns + tol < colours[-1].stamp_ns]
                self._unmatched(len(stale))
                depths[:] = [d for d in depths if d not in stale]
            for queue in (colours, depths):
                while len(queue) > RGBD_QUEUE:
                    queue.pop(0)
                    self._unmatched()
            return None
        colour, depth = pair
        older = [c for c in colours if c.stamp_ns < colour.stamp_ns]
        matched_older = [c for c in older if partner(c) is not None]
        self._rgbd_skipped += len(matched_older)
        self._unmatched(len(older) - len(matched_older))
        older_depths = [d for d in depths if d.stamp_ns <= depth.stamp_ns and d is not depth]
        self._unmatched(sum(1 for d in older_depths
                            if not any(abs(d.stamp_ns - c.stamp_ns) <= tol
                                       for c in matched_older)))
        colours[:] = [c for c in colours if c.stamp_ns > colour.stamp_ns]
        depths[:] = [d for d in depths if d.stamp_ns > depth.stamp_ns]
        return colour, depth

    def skipped_total(self) -> int:
        """Colour images never processed because a newer one was (``frames_skipped``)."""
        return self._image.replaced + self._rgbd_skipped

    # -- frames ------------------------------------------------------------------------------

    def take_frame(self, want: Callable[[int], bool] | None = None) -> RosFrame | None:
        """The newest frame (with depth when the source pairs RGB-D) decoded, or ``None``;
        bad messages are counted and named (:meth:`health`), never raised. ``want``: called
        with the newest image's header stamp first; when it says ``False`` the image is
        dropped undecoded (a node that uses one frame a second decodes only that one)."""
        info = self._info.take()
        if info is not None:
            self._check_info(info[0])
        with self._image.lock:
            oversized = self._image.oversized + self._info.oversized + self._depth.oversized
        if oversized > self._seen_oversized:
            self._fail(RosImageError("ros_oversized", f"{oversized - self._seen_oversized} "
                                     f"sample(s) over {MAX_PAYLOAD_BYTES} bytes refused"))
            self._seen_oversized = oversized
        depth_payload: bytes | None = None
        if self.provides_depth:
            pair = self._take_pair()
            if pair is None:
                return None
            payload = pair[0].payload
            depth_payload = pair[1].payload
            if want is not None and not want(pair[0].stamp_ns):
                return None
        else:
            item = self._image.take()
            if item is None:
                return None
            payload, attachment = item
            self._sequence(attachment)
        if want is not None and depth_payload is None:
            try:
                stamp_ns, _ = decode_header(payload, f"Image on {self.config.image_key}")
            except RosImageError as exc:
                self._fail(exc)
                return None
            if not want(stamp_ns):
                return None
        t0 = time.perf_counter()
        try:
            rgb, stamp_ns, frame_id = self._decode_colour(payload)
        except RosImageError as exc:
            self._fail(exc)
            return None
        depth_m = None
        if depth_payload is not None:
            try:
                depth_m, _ = self.decode_depth(depth_payload)
            except RosImageError as exc:
                self._fail(exc, dropped=False)
            if depth_m is not None and depth_m.shape != rgb.shape[:2]:
                self._fail(RosImageError(
                    "depth_size_mismatch", f"{self.label}: depth image "
                    f"{depth_m.shape[1]}x{depth_m.shape[0]} on {self.config.depth_key}, the "
                    f"colour image is {rgb.shape[1]}x{rgb.shape[0]} (depth must be aligned to "
                    "colour: a depth_registered topic)"), dropped=False)
                depth_m = None
        self.last_decode_s = time.perf_counter() - t0
        if self._stats is not None:
            self._stats.latency("decode", self.last_decode_s)
        h, w = rgb.shape[:2]
        if self.camera is not None and (w, h) != (self.camera.width, self.camera.height):
            self._fail(RosImageError("ros_image_size_mismatch", f"{self.label}: image "
                                     f"{w}x{h}, the site's calibration is "
                                     f"{self.camera.width}x{self.camera.height}"),
                       dropped=False)  # still processed: keypoints in the frame's pixels
        self._seq += 1
        self._last_frame_s = time.monotonic()
        return RosFrame(Frame(rgb, stamp_ns, self._seq, depth_m), frame_id)

    def poll(self, now_ns: int) -> list[Any]:
        got = self.take_frame()
        if got is None:
            return []
        return [self.process(got.frame, now_ns, self.skipped_total())]

    def health(self) -> tuple[str, str]:
        detail = f"source={self.label} frames={self._seq} skipped={self.skipped_total()}"
        if self.provides_depth:
            detail += f" rgbd_unmatched={self._errors.get('rgbd_unmatched', 0)}"
        if self.calibration_mismatch:
            return "degraded", f"{detail}; CameraInfo differs from the site's calibration: " \
                f"{self.calibration_mismatch}"
        now = time.monotonic()
        if self.last_error and now - self._last_error_s < STALE_AFTER_S:
            return "degraded", f"{detail}; {self.last_error}"
        if self._last_frame_s is None:
            if self.provides_depth and self._image.received:
                return "starting", f"{detail}; colour images arrive, waiting for depth " \
                    f"images of the same stamps on {self.config.depth_key}"
            return "starting", f"{detail}; waiting for images on {self.config.image_key}"
        if now - self._last_frame_s > STALE_AFTER_S:
            return "degraded", f"{detail}; no image for {now - self._last_frame_s:.0f} s on " \
                f"{self.config.image_key}"
        return "ok", detail


class RosSourcePlugin:
    """``--source ros``: images from a ROS 2 topic (rmw_zenoh or zenoh-bridge-ros2dds)
    through the site robot model's ONNX models (the camera source's ``--model``,
    ``--threads``, ``--providers``, ``--min-score`` apply)."""

    def add_arguments(self, parser: argparse.ArgumentParser) -> None:
        g = parser.add_argument_group("ROS 2 image source (--source ros; also reads --model, "
                                      "--threads, --providers, --min-score)")
        g.add_argument("--ros-image-topic", metavar="TOPIC",
                       help="sensor_msgs/Image topic, or CompressedImage when it ends in "
                       "/compressed (e.g. /camera/color/image_raw)")
        g.add_argument("--ros-camera-info-topic", metavar="TOPIC",
                       help="sensor_msgs/CameraInfo checked against the site's calibration "
                       "(default: camera_info beside the image topic; 'none': no check)")
        g.add_argument("--ros-transport", choices=TRANSPORTS, default="rmw_zenoh",
                       help="rmw_zenoh (ROS 2 Jazzy+ with RMW_IMPLEMENTATION=rmw_zenoh_cpp) or "
                       "ros2dds (zenoh-bridge-ros2dds; default rmw_zenoh)")
        g.add_argument("--ros-domain-id", type=int, default=None, metavar="N",
                       help="rmw_zenoh: the ROS domain id (default: $ROS_DOMAIN_ID, else 0)")
        g.add_argument("--ros-namespace", default="", metavar="NS",
                       help="ros2dds: the bridge's namespace prefixed to its keys")
        g.add_argument("--ros-depth-topic", metavar="TOPIC",
                       help="aligned depth sensor_msgs/Image (16UC1 mm or 32FC1 m, e.g. "
                       "/camera/aligned_depth_to_color/image_raw): frames are colour + depth "
                       "pairs of the same stamp and become semantic clouds (--cloud-rate)")
        g.add_argument("--ros-sync-tolerance-ms", type=float,
                       default=DEFAULT_SYNC_TOLERANCE_NS / 1e6, metavar="MS",
                       help="largest stamp difference of a colour image and its depth image "
                       f"(default {DEFAULT_SYNC_TOLERANCE_NS / 1e6:g} ms)")

    def build(self, args: argparse.Namespace, site: Site | None) -> RosImageSource:
        import os

        from edge_agent.models import models_for_site
        from edge_agent.pipeline import EdgePipeline, far_band_from_args

        if site is None:
            raise UsageError("--source ros needs --site (the camera's calibration and the "
                             "robot model)")
        if not args.ros_image_topic:
            raise UsageError("--source ros needs --ros-image-topic TOPIC")
        camera = site.camera(args.camera)
        domain = args.ros_domain_id
        if domain is None:
            text = os.environ.get("ROS_DOMAIN_ID", "").strip() or "0"
            if not text.isdigit():
                raise UsageError(f"ROS_DOMAIN_ID={text!r}: expected an integer >= 0")
            domain = int(text)
        if domain < 0:
            raise UsageError(f"--ros-domain-id {domain}: expected an integer >= 0")
        topic = args.ros_image_topic
        info = args.ros_camera_info_topic
        info_topic = None if info == "none" else (info or camera_info_topic(topic))
        tolerance_ms = args.ros_sync_tolerance_ms
        if not 0.0 <= tolerance_ms <= 1000.0:
            raise UsageError(f"--ros-sync-tolerance-ms {tolerance_ms}: expected 0 to 1000")
        config = RosTopicConfig(args.ros_transport, topic,
                                compressed=_topic_tokens(topic)[-1] == "compressed",
                                info_topic=info_topic, domain_id=domain,
                                namespace=args.ros_namespace,
                                depth_topic=args.ros_depth_topic or None,
                                sync_tolerance_ns=round(tolerance_ms * 1e6))
        config.image_key, config.info_key, config.depth_key  # noqa: B018 (names checked early)
        providers = execution_providers_from_args(args)  # --providers, --fp16, --trt-cache
        # every robot model (type) of the site, one set of networks each
        models = models_for_site(site, args.model, threads=args.threads, providers=providers)
        pipeline = EdgePipeline(args.camera, models, min_score=args.min_score,
                                expected_size=(camera.width, camera.height),
                                far_band=far_band_from_args(args, site, models))
        return RosImageSource(config, pipeline, camera)


register_source("ros", RosSourcePlugin())
