"""The ChArUco calibration board: its spec, the printable image (PNG at a set DPI, PDF at 1:1
scale), the spec file written beside it, and detection of its corners in an image.

Board frame (OpenCV's): origin at the outer corner of the top-left square of the printed board,
x along the board's columns (to the right on the print), y along its rows (down on the print),
z into the board (a camera that sees the printed side looks along +z), metres. Inner corner
``i`` (the ``corner_ids`` of a detection) sits at ``((i % (squares_x - 1) + 1) * s,
(i // (squares_x - 1) + 1) * s, 0)`` with ``s`` the square length.

A view is rejected with a reason (:attr:`BoardDetection.reason`): no board, too few corners,
corners on one line, or blurred (variance of the Laplacian over the board region below
:data:`MIN_SHARPNESS`).
"""

from __future__ import annotations

import dataclasses
import logging
import math
import struct
import zlib
from pathlib import Path
from typing import Any, Final

import cv2
import numpy as np
import yaml

from core.config_file import ConfigReader, join_key, read_yaml_file
from protocol.errors import ConfigFileError, SmartedgeError

log = logging.getLogger(__name__)

#: Fewest ChArUco corners a usable view has (a homography needs 4; a few more keep one noisy
#: corner from steering the view's pose).
MIN_CORNERS: Final = 6
#: Least variance of the Laplacian (8-bit grey levels squared) over the board region of a
#: usable view. Rendered sharp boards measure 3500-6000, the same blurred by a Gaussian of
#: sigma 1 px 500-1200, of 2 px 100-160 (where the markers are barely decoded any more); camera
#: noise raises the figure, so a noisy camera may need a higher bar (``--min-sharpness``).
MIN_SHARPNESS: Final = 100.0
#: Half-size of the ``cv2.cornerSubPix`` window that refines the detector's corners, pixels
#: (7 x 7). On rendered boards it halves the detector's own corner error (0.15 -> 0.11 px RMS)
#: and removes its 0.025 px bias; larger windows reach into the neighbouring squares' markers.
SUBPIX_HALF_WINDOW_PX: Final = 3
_SUBPIX_CRITERIA: Final = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 50, 1e-4)
#: Grey-level standard deviation above which an image without a board is said to be blurred
#: (when its sharpness is low too) rather than empty.
_MIN_CONTRAST: Final = 20.0
#: Top-level key of the board spec file.
SPEC_KEY: Final = "charuco_board"
#: Millimetres per inch, PDF points per inch.
_MM_PER_INCH: Final = 25.4
_PT_PER_INCH: Final = 72.0


class CalibrationError(SmartedgeError):
    """Calibration cannot go on with what it was given (too few usable views, no sightings that
    tie a camera to the others, ...); the message says what was usable and why the rest was
    not."""


class BoardSpecError(ConfigFileError):
    """A board spec file is missing, unreadable or invalid (names the file and the key)."""


def _dictionary_id(name: str) -> int:
    value = getattr(cv2.aruco, name, None) if name.startswith("DICT_") else None
    if not isinstance(value, int):
        known = sorted(n for n in dir(cv2.aruco) if n.startswith("DICT_") and n.upper() == n)
        raise ValueError(f"unknown ArUco dictionary {name!r}; known: {', '.join(known)}")
    return value


@dataclasses.dataclass(frozen=True)
class CharucoBoardSpec:
    """A ChArUco board: ``squares_x`` columns by ``squares_y`` rows of squares of
    ``square_length_m`` (the top-left one black), ArUco markers of ``marker_length_m`` from
    ``dictionary`` (an OpenCV name such as ``DICT_5X5_100``) in the white squares."""

    squares_x: int = 7
    squares_y: int = 5
    square_length_m: float = 0.04
    marker_length_m: float = 0.03
    dictionary: str = "DICT_5X5_100"

    def __post_init__(self) -> None:
        for name in ("squares_x", "squares_y"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or not 3 <= value <= 100:
                raise ValueError(f"{name} must be an integer in [3, 100], got {value!r}")
        if not (math.isfinite(self.square_length_m) and 0.0 < self.square_length_m <= 10.0):
            raise ValueError(f"square_length_m must be in (0, 10] m, got {self.square_length_m}")
        if not (math.isfinite(self.marker_length_m)
                and 0.0 < self.marker_length_m < self.square_length_m):
            raise ValueError(f"marker_length_m must be in (0, square_length_m = "
                             f"{self.square_length_m}), got {self.marker_length_m}")
        dictionary = cv2.aruco.getPredefinedDictionary(_dictionary_id(self.dictionary))
        num_markers = self.squares_x * self.squares_y // 2
        if num_markers > dictionary.bytesList.shape[0]:
            raise ValueError(f"a {self.squares_x}x{self.squares_y} board needs {num_markers} "
                             f"markers; {self.dictionary} has {dictionary.bytesList.shape[0]}")

    # ------------------------------------------------------------------------------ geometry
    @property
    def num_corners(self) -> int:
        """Inner chessboard corners (the ChArUco corners), ``(squares_x-1) * (squares_y-1)``."""
        return (self.squares_x - 1) * (self.squares_y - 1)

    @property
    def size_m(self) -> tuple[float, float]:
        """(width, height) of the square grid, metres (without the printed margin)."""
        return self.squares_x * self.square_length_m, self.squares_y * self.square_length_m

    def corners_board_m(self) -> np.ndarray:
        """(num_corners, 3) ChArUco corner positions in the board frame, metres, by corner id."""
        return np.asarray(self.opencv_board().getChessboardCorners(), np.float64).reshape(-1, 3)

    def opencv_board(self) -> Any:
        """The ``cv2.aruco.CharucoBoard`` of this spec."""
        dictionary = cv2.aruco.getPredefinedDictionary(_dictionary_id(self.dictionary))
        return cv2.aruco.CharucoBoard((self.squares_x, self.squares_y), self.square_length_m,
                                      self.marker_length_m, dictionary)

    def describe(self) -> str:
        w, h = self.size_m
        return (f"{self.squares_x}x{self.squares_y} ChArUco, squares {self.square_length_m * 1e3:g}"
                f" mm, markers {self.marker_length_m * 1e3:g} mm, {self.dictionary}, "
                f"{w * 1e3:g} x {h * 1e3:g} mm")

    # ------------------------------------------------------------------------------ spec file
    def to_yaml_dict(self) -> dict[str, Any]:
        return {SPEC_KEY: {"squares": [self.squares_x, self.squares_y],
                           "square_length_m": self.square_length_m,
                           "marker_length_m": self.marker_length_m,
                           "dictionary": self.dictionary}}

    def write(self, path: str | Path) -> Path:
        """Write the spec as YAML (``charuco_board: {squares, square_length_m, ...}``)."""
        p = Path(path)
        text = ("# ChArUco board spec written by `smartedge calibrate board`; pass it to\n"
                "# `smartedge calibrate intrinsics/extrinsics --board`. Measure a printed\n"
                "# square and correct square_length_m / marker_length_m if the print scaled.\n")
        p.write_text(text + yaml.safe_dump(self.to_yaml_dict(), sort_keys=False),
                     encoding="utf-8")
        return p


def load_board_spec(path: str | Path) -> CharucoBoardSpec:
    """Read a spec written by :meth:`CharucoBoardSpec.write`; :class:`BoardSpecError` names the
    file and the key that is wrong."""
    doc = read_yaml_file(path, "board spec", BoardSpecError)
    ctx = ConfigReader(str(path), BoardSpecError)
    top = ctx.mapping("", doc)
    ctx.no_unknown("", top, {SPEC_KEY})
    node = ctx.mapping(SPEC_KEY, ctx.require("", top, SPEC_KEY))
    ctx.no_unknown(SPEC_KEY, node, {"squares", "square_length_m", "marker_length_m",
                                    "dictionary"})
    sq_key = join_key(SPEC_KEY, "squares")
    squares = ctx.require(SPEC_KEY, node, "squares")
    if not isinstance(squares, list) or len(squares) != 2:
        raise ctx.fail(sq_key, "expected [squares_x, squares_y]")
    sx = ctx.integer(f"{sq_key}[0]", squares[0], lo=3, hi=100)
    sy = ctx.integer(f"{sq_key}[1]", squares[1], lo=3, hi=100)
    square = ctx.number(join_key(SPEC_KEY, "square_length_m"),
                        ctx.require(SPEC_KEY, node, "square_length_m"), lo=1e-4, hi=10.0)
    marker = ctx.number(join_key(SPEC_KEY, "marker_length_m"),
                        ctx.require(SPEC_KEY, node, "marker_length_m"), lo=1e-4, hi=10.0)
    dictionary = ctx.require(SPEC_KEY, node, "dictionary")
    if not isinstance(dictionary, str):
        raise ctx.fail(join_key(SPEC_KEY, "dictionary"), f"expected a name such as DICT_5X5_100, "
                       f"got {dictionary!r}")
    try:
        return CharucoBoardSpec(sx, sy, square, marker, dictionary)
    except ValueError as exc:
        key = "dictionary" if "dictionary" in str(exc) else (
            "marker_length_m" if "marker" in str(exc) else "squares")
        raise ctx.fail(join_key(SPEC_KEY, key), str(exc)) from None


# ----------------------------------------------------------------------------------- images


@dataclasses.dataclass(frozen=True, eq=False)
class BoardImage:
    """The printable board: ``image`` (H, W) uint8 grey, ``px_per_square`` pixels per square,
    ``margin_px`` white margin (quiet zone) around the square grid on every side."""

    spec: CharucoBoardSpec
    image: np.ndarray
    px_per_square: int
    margin_px: int

    @property
    def px_per_m(self) -> float:
        return self.px_per_square / self.spec.square_length_m

    @property
    def extent_board_m(self) -> tuple[float, float, float, float]:
        """(x0, y0, x1, y1): the image's edges in the board frame, metres (the margin is outside
        the square grid, so x0, y0 < 0)."""
        m = self.margin_px / self.px_per_m
        w, h = self.spec.size_m
        return (-m, -m, w + m, h + m)

    @property
    def dpi(self) -> float:
        """Dots per inch at which the image prints at its true size."""
        return self.px_per_m * _MM_PER_INCH / 1e3


def board_image(spec: CharucoBoardSpec, px_per_square: int = 100,
                margin_squares: float = 0.5) -> BoardImage:
    """The board drawn with exactly ``px_per_square`` pixels per square (corners on pixel
    edges) and a white margin of ``margin_squares`` squares (rounded to whole pixels)."""
    if px_per_square < 10:
        raise ValueError(f"px_per_square must be >= 10, got {px_per_square}")
    margin_px = round(margin_squares * px_per_square)
    size = (spec.squares_x * px_per_square + 2 * margin_px,
            spec.squares_y * px_per_square + 2 * margin_px)
    img = spec.opencv_board().generateImage(size, marginSize=margin_px, borderBits=1)
    return BoardImage(spec, np.ascontiguousarray(img, np.uint8), px_per_square, margin_px)


def board_image_for_dpi(spec: CharucoBoardSpec, dpi: float, margin_squares: float = 0.5
                        ) -> BoardImage:
    """:func:`board_image` with the whole pixels per square nearest to ``dpi``."""
    px = max(10, round(spec.square_length_m * 1e3 / _MM_PER_INCH * dpi))
    return board_image(spec, px, margin_squares)


def _png_chunk(kind: bytes, data: bytes) -> bytes:
    return (struct.pack(">I", len(data)) + kind + data
            + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF))


def write_board_png(board: BoardImage, path: str | Path) -> Path:
    """The board as a PNG that carries its physical resolution (a ``pHYs`` chunk), so an image
    viewer prints it at its true size."""
    ok, buf = cv2.imencode(".png", board.image)
    if not ok:
        raise OSError(f"{path}: OpenCV could not encode the board as PNG")
    data = buf.tobytes()
    px_per_metre = round(board.px_per_m)
    phys = _png_chunk(b"pHYs", struct.pack(">IIB", px_per_metre, px_per_metre, 1))
    ihdr_end = 8 + 4 + 4 + 13 + 4  # signature, IHDR length + type + data + crc
    p = Path(path)
    p.write_bytes(data[:ihdr_end] + phys + data[ihdr_end:])
    return p


def write_board_pdf(board: BoardImage, path: str | Path) -> Path:
    """The board as a one-page PDF whose page is the board with its margin at 1:1 scale
    (print at "actual size", no "fit to page"). The image is embedded losslessly."""
    h, w = board.image.shape
    width_pt = w / board.px_per_m / (_MM_PER_INCH / 1e3) * _PT_PER_INCH
    height_pt = h / board.px_per_m / (_MM_PER_INCH / 1e3) * _PT_PER_INCH
    pixels = zlib.compress(np.ascontiguousarray(board.image).tobytes(), 9)
    content = f"q {width_pt:.4f} 0 0 {height_pt:.4f} 0 0 cm /Board Do Q\n".encode("ascii")
    objects = [
        b"<< /Type /Catalog /Pages 2 0 R >>",
        b"<< /Type /Pages /Kids [3 0 R] /Count 1 >>",
        (f"<< /Type /Page /Parent 2 0 R /MediaBox [0 0 {width_pt:.4f} {height_pt:.4f}] "
         "/Resources << /XObject << /Board 4 0 R >> >> /Contents 5 0 R >>").encode("ascii"),
        (f"<< /Type /XObject /Subtype /Image /Width {w} /Height {h} /ColorSpace /DeviceGray "
         f"/BitsPerComponent 8 /Filter /FlateDecode /Interpolate false /Length {len(pixels)} >>"
         "\nstream\n").encode("ascii") + pixels + b"\nendstream",
        f"<< /Length {len(content)} >>\nstream\n".encode("ascii") + content + b"endstream",
    ]
    out = bytearray(b"%PDF-1.4\n%\xe2\xe3\xcf\xd3\n")
    offsets = []
    for i, body in enumerate(objects, start=1):
        offsets.append(len(out))
        out += f"{i} 0 obj\n".encode("ascii") + body + b"\nendobj\n"
    xref = len(out)
    out += f"xref\n0 {len(objects) + 1}\n0000000000 65535 f \n".encode("ascii")
    out += b"".join(f"{o:010d} 00000 n \n".encode("ascii") for o in offsets)
    out += (f"trailer\n<< /Size {len(objects) + 1} /Root 1 0 R >>\nstartxref\n{xref}\n%%EOF\n"
            ).encode("ascii")
    p = Path(path)
    p.write_bytes(bytes(out))
    return p


# -------------------------------------------------------------------------------- detection


@dataclasses.dataclass(frozen=True, eq=False)
class BoardDetection:
    """The board found in one image.

    ``corner_ids`` (N,) int32 ChArUco corner ids; ``corners_px`` (N, 2) float64 their sub-pixel
    positions (u, v), pixel centres at integers; ``num_markers`` ArUco markers decoded;
    ``sharpness`` variance of the Laplacian over the board region (whole image when no board);
    ``image_size`` (width, height). ``reason``: why the view is not usable, ``None`` if it is.
    """

    corner_ids: np.ndarray
    corners_px: np.ndarray
    num_markers: int
    sharpness: float
    image_size: tuple[int, int]
    reason: str | None = None

    @property
    def usable(self) -> bool:
        return self.reason is None

    @property
    def num_corners(self) -> int:
        return len(self.corner_ids)


class BoardDetector:
    """Detects one board in images (one OpenCV detector, re-used). ``min_corners`` and
    ``min_sharpness`` decide which views are usable."""

    def __init__(self, spec: CharucoBoardSpec, *, min_corners: int = MIN_CORNERS,
                 min_sharpness: float = MIN_SHARPNESS) -> None:
        self.spec = spec
        self.min_corners = max(4, int(min_corners))
        self.min_sharpness = float(min_sharpness)
        self._board = spec.opencv_board()
        params = cv2.aruco.DetectorParameters()
        params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
        # small, tilted markers (a board across a room): sample 8 px per marker cell instead
        # of 4 when reading the bits, and look again for the markers the board's layout says
        # are missing; on rendered sightings of the paper lab (~2 px per cell) 25 % more
        # corners, no cost in accuracy
        params.perspectiveRemovePixelPerCell = 8
        charuco = cv2.aruco.CharucoParameters()
        charuco.tryRefineMarkers = True
        self._detector = cv2.aruco.CharucoDetector(self._board, charuco, params)

    def detect(self, image: np.ndarray) -> BoardDetection:
        """Detect the board in ``image`` ((H, W) grey or (H, W, 3) BGR/RGB uint8)."""
        img = np.asarray(image)
        if img.ndim == 3:
            img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
        if img.ndim != 2 or img.dtype != np.uint8 or min(img.shape) < 8:
            raise ValueError(f"expected an 8-bit grey or colour image, got {img.dtype} "
                             f"{img.shape}")
        size = (int(img.shape[1]), int(img.shape[0]))
        corners, ids, marker_corners, marker_ids = self._detector.detectBoard(img)
        num_markers = 0 if marker_ids is None else len(marker_ids)
        if corners is None or ids is None or len(ids) == 0:
            sharp = _sharpness(img, None)
            why = "no board found" if num_markers == 0 else (
                f"no ChArUco corners ({num_markers} markers decoded)")
            # blur is named only where there is something to be blurred (not a blank wall)
            if sharp < self.min_sharpness and float(img.std()) > _MIN_CONTRAST:
                why += f"; image blurred (sharpness {sharp:.0f} < {self.min_sharpness:.0f})"
            return BoardDetection(np.zeros(0, np.int32), np.zeros((0, 2)), num_markers, sharp,
                                  size, why)
        ids = np.asarray(ids, np.int32).reshape(-1)
        refined = np.ascontiguousarray(np.asarray(corners, np.float32).reshape(-1, 1, 2))
        win = (SUBPIX_HALF_WINDOW_PX, SUBPIX_HALF_WINDOW_PX)
        cv2.cornerSubPix(img, refined, win, (-1, -1), _SUBPIX_CRITERIA)
        pts = refined.reshape(-1, 2).astype(np.float64)
        hull_pts = pts if marker_corners is None or not len(marker_corners) else np.vstack(
            [pts, np.concatenate([np.asarray(c, np.float64).reshape(-1, 2)
                                  for c in marker_corners])])
        sharp = _sharpness(img, hull_pts)
        reason: str | None = None
        if sharp < self.min_sharpness:  # first: blur also costs corners
            reason = (f"blurred (sharpness {sharp:.0f} < {self.min_sharpness:.0f}; "
                      f"{len(ids)} corners)")
        elif len(ids) < self.min_corners:
            reason = (f"too few corners ({len(ids)} < {self.min_corners} of "
                      f"{self.spec.num_corners}; board partly outside the image or occluded)")
        elif self._board.checkCharucoCornersCollinear(ids.reshape(-1, 1)):
            reason = f"corners on one line ({len(ids)} corners): no pose from this view"
        return BoardDetection(ids, pts, num_markers, sharp, size, reason)


def _sharpness(gray: np.ndarray, points_px: np.ndarray | None) -> float:
    """Variance of the Laplacian over the bounding box of ``points_px`` (whole image: None)."""
    if points_px is not None and len(points_px):
        h, w = gray.shape
        x0, y0 = np.floor(points_px.min(axis=0)).astype(int)
        x1, y1 = np.ceil(points_px.max(axis=0)).astype(int)
        x0, y0 = max(0, x0 - 2), max(0, y0 - 2)
        x1, y1 = min(w, x1 + 3), min(h, y1 + 3)
        if x1 - x0 >= 8 and y1 - y0 >= 8:
            gray = gray[y0:y1, x0:x1]
    return float(cv2.Laplacian(gray, cv2.CV_64F).var())


def detect_board(image: np.ndarray, spec: CharucoBoardSpec) -> BoardDetection:
    """One-off :meth:`BoardDetector.detect` (build a :class:`BoardDetector` for many images)."""
    return BoardDetector(spec).detect(image)


def draw_detection(image: np.ndarray, detection: BoardDetection) -> np.ndarray:
    """A BGR copy of ``image`` with the detected corners and their ids drawn (green: usable
    view, red: rejected, with the reason written at the top)."""
    img = np.asarray(image)
    out = cv2.cvtColor(img, cv2.COLOR_GRAY2BGR) if img.ndim == 2 else img.copy()
    color = (40, 200, 40) if detection.usable else (40, 40, 230)
    scale = max(out.shape[:2]) / 1000.0
    for cid, (u, v) in zip(detection.corner_ids, detection.corners_px, strict=True):
        c = (round(float(u)), round(float(v)))
        cv2.circle(out, c, max(3, round(4 * scale)), color, max(1, round(2 * scale)),
                   cv2.LINE_AA)
        cv2.putText(out, str(int(cid)), (c[0] + 4, c[1] - 4), cv2.FONT_HERSHEY_SIMPLEX,
                    0.35 * max(scale, 1.0), color, 1, cv2.LINE_AA)
    label = (f"{detection.num_corners} corners, sharpness {detection.sharpness:.0f}"
             if detection.usable else f"skipped: {detection.reason}")
    text_scale = 0.55 * max(scale, 1.0)
    for i, line in enumerate(label.split("; ")):
        cv2.putText(out, line, (8, round((22 + 22 * i) * max(scale, 1.0))),
                    cv2.FONT_HERSHEY_SIMPLEX, text_scale, color, 2, cv2.LINE_AA)
    return out
