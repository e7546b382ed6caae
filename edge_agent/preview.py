"""Preview images for the viewer: a processed frame as a JPEG :class:`protocol.CameraImage`.

The edge agent publishes one at ``--preview-rate`` (off by default: camera images leave the
board only when asked for) on ``smartedge/<site>/edge/<camera_id>/image``, with the stamp of the
detections that came from the same frame, so the viewer draws boxes and keypoints on the image
they were found in.
"""

from __future__ import annotations

import cv2
import numpy as np

from edge_agent.frames import Frame
from protocol.messages import CameraImage

#: JPEG quality of previews (an 848x480 lab frame is ~40-80 kB)
DEFAULT_QUALITY = 80


def encode_preview(frame: Frame, camera_id: str, quality: int = DEFAULT_QUALITY) -> CameraImage:
    """``frame`` (RGB) as a JPEG :class:`CameraImage` at full size (the detections' pixel
    coordinates stay valid). Raises ``ValueError`` if OpenCV cannot encode it."""
    image = np.ascontiguousarray(frame.image_rgb[:, :, ::-1])  # OpenCV wants BGR
    ok, buf = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    if not ok:
        raise ValueError(f"{camera_id}: JPEG encoding of a {image.shape} frame failed")
    h, w = image.shape[:2]
    return CameraImage(camera_id, int(frame.stamp_ns), int(frame.seq), w, h, "jpeg",
                       np.asarray(buf, np.uint8).reshape(-1))
