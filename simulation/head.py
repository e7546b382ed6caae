"""The simulated robot's head: pan and tilt joints, its TF tree, and a head that looks around.

On the HSR the RGB-D camera sits on a head that pans (about the torso's vertical axis) and tilts
(about the pan link's y axis), so the camera's pose in ``base_link`` changes while the robot
drives. This module is that head for the simulated HSR-like robot:

* :class:`HeadKinematics`: the frames with HSR names, ``base_link`` -> ``torso_lift_link``
  (static: the torso is not lifted in the simulation) -> ``head_pan_link`` (dynamic:
  ``Rz(pan)``) -> ``head_tilt_link`` (dynamic: ``Ry(tilt)``, positive tilt looks down) ->
  ``head_rgbd_sensor_rgb_frame`` (static: the colour camera's optical frame, z forward, x right,
  y down). The static camera transform is derived from the site file's
  ``head_camera.T_base_cam`` so that pan = tilt = 0 gives exactly that mounting: a site that
  calibrated its head camera with the head at rest keeps its calibration.
* :class:`HeadMotion`: a smooth look-around while the robot drives, a sinusoidal pan sweep
  (default +-70 deg, peak speed 2 pi A / period = 36.7 deg/s) and a gentle tilt nod of another
  period (+-8 deg), phases drawn from the scenario seed; the same seed and time give the same
  joints in every process.
* :class:`SimulatedHead`: both, with the simulation's epoch: joint values, the TF transforms
  and the true ``T_base_cam`` at a stamp (ns, the live simulation's wall-clock stamps).

Pure numpy; no rendering and no transport (``lab.simulated_head`` publishes it).
"""

from __future__ import annotations

import dataclasses
import math
from typing import Final

import numpy as np

from core.geometry import invert_transform, rotation_z
from protocol.messages import NS_PER_S

#: HSR frame names (hsrb_description)
BASE_FRAME: Final = "base_link"
TORSO_FRAME: Final = "torso_lift_link"
PAN_FRAME: Final = "head_pan_link"
TILT_FRAME: Final = "head_tilt_link"
CAMERA_FRAME: Final = "head_rgbd_sensor_rgb_frame"

#: HSR-like joint placement: the torso link above the base origin, the pan joint on the torso,
#: the tilt joint a little forward of and above the pan joint (metres)
DEFAULT_TORSO_IN_BASE_M: Final = (0.0, 0.0, 0.60)
DEFAULT_PAN_IN_TORSO_M: Final = (0.0, 0.0, 0.15)
DEFAULT_TILT_IN_PAN_M: Final = (0.02, 0.0, 0.19)
#: joint limits (radians): the HSR's pan range; tilt 30 deg up (negative) to 90 deg down
DEFAULT_PAN_LIMITS_RAD: Final = (-3.84, 1.75)
DEFAULT_TILT_LIMITS_RAD: Final = (-0.52, 1.57)



def rotation_y(angle_rad: float) -> np.ndarray:
    c, s = math.cos(angle_rad), math.sin(angle_rad)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def _transform(R: np.ndarray, t_m: tuple[float, float, float] | np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = np.asarray(t_m, np.float64)
    return T


@dataclasses.dataclass(frozen=True)
class FrameTransform:
    """One edge of the TF tree: ``child`` in ``parent`` (``T_parent_child`` (4, 4), metres);
    ``static``: on ``/tf_static`` (holds at any time), else on ``/tf`` at its stamp."""

    parent: str
    child: str
    T_parent_child: np.ndarray
    static: bool


@dataclasses.dataclass(frozen=True, eq=False)
class HeadKinematics:
    """The head's joints and frames (see the module docstring).

    ``T_base_cam_home``: (4, 4) the camera optical frame in ``base_link`` at pan = tilt = 0 (the
    site file's ``head_camera.T_base_cam``); the offsets place the torso link, the pan joint and
    the tilt joint (metres); limits (min, max) in radians."""

    T_base_cam_home: np.ndarray
    torso_in_base_m: tuple[float, float, float] = DEFAULT_TORSO_IN_BASE_M
    pan_in_torso_m: tuple[float, float, float] = DEFAULT_PAN_IN_TORSO_M
    tilt_in_pan_m: tuple[float, float, float] = DEFAULT_TILT_IN_PAN_M
    pan_limits_rad: tuple[float, float] = DEFAULT_PAN_LIMITS_RAD
    tilt_limits_rad: tuple[float, float] = DEFAULT_TILT_LIMITS_RAD

    def __post_init__(self) -> None:
        T = np.asarray(self.T_base_cam_home, np.float64)
        if T.shape != (4, 4) or not np.all(np.isfinite(T)):
            raise ValueError(f"T_base_cam_home: expected a finite (4, 4) transform, got shape "
                             f"{T.shape}")
        for name in ("pan_limits_rad", "tilt_limits_rad"):
            lo, hi = getattr(self, name)
            if not (math.isfinite(lo) and math.isfinite(hi) and lo <= 0.0 <= hi):
                raise ValueError(f"{name} {(lo, hi)}: expected finite min <= 0 <= max")
        object.__setattr__(self, "T_base_cam_home", T.copy())

    @property
    def T_base_torso(self) -> np.ndarray:
        return _transform(np.eye(3), self.torso_in_base_m)

    def T_torso_pan(self, pan_rad: float) -> np.ndarray:
        return _transform(rotation_z(pan_rad), self.pan_in_torso_m)

    def T_pan_tilt(self, tilt_rad: float) -> np.ndarray:
        return _transform(rotation_y(tilt_rad), self.tilt_in_pan_m)

    @property
    def T_tilt_cam(self) -> np.ndarray:
        """The camera's optical frame in ``head_tilt_link`` (static), chosen so that pan =
        tilt = 0 gives :attr:`T_base_cam_home`."""
        T_base_tilt_home = self.T_base_torso @ self.T_torso_pan(0.0) @ self.T_pan_tilt(0.0)
        return invert_transform(T_base_tilt_home) @ self.T_base_cam_home

    def check_joints(self, pan_rad: float, tilt_rad: float) -> None:
        """``ValueError`` naming the joint when a value is outside its limits or not finite."""
        for name, value, (lo, hi) in (("pan", pan_rad, self.pan_limits_rad),
                                      ("tilt", tilt_rad, self.tilt_limits_rad)):
            if not (math.isfinite(value) and lo <= value <= hi):
                raise ValueError(f"head {name} {value!r} rad: outside its limits [{lo}, {hi}]")

    def transforms(self, pan_rad: float, tilt_rad: float) -> list[FrameTransform]:
        """The whole tree at these joint values, root first: static, pan, tilt, camera."""
        self.check_joints(pan_rad, tilt_rad)
        return [
            FrameTransform(BASE_FRAME, TORSO_FRAME, self.T_base_torso, True),
            FrameTransform(TORSO_FRAME, PAN_FRAME, self.T_torso_pan(pan_rad), False),
            FrameTransform(PAN_FRAME, TILT_FRAME, self.T_pan_tilt(tilt_rad), False),
            FrameTransform(TILT_FRAME, CAMERA_FRAME, self.T_tilt_cam, True),
        ]

    def static_transforms(self) -> list[FrameTransform]:
        """The ``/tf_static`` edges (joint-independent)."""
        return [t for t in self.transforms(0.0, 0.0) if t.static]

    def T_base_cam(self, pan_rad: float, tilt_rad: float) -> np.ndarray:
        """(4, 4) camera optical frame -> ``base_link`` at these joint values."""
        self.check_joints(pan_rad, tilt_rad)
        return (self.T_base_torso @ self.T_torso_pan(pan_rad) @ self.T_pan_tilt(tilt_rad)
                @ self.T_tilt_cam)


@dataclasses.dataclass(frozen=True)
class HeadMotion:
    """A head that looks around: ``pan(t) = pan_amplitude sin(2 pi t / pan_period + phase_pan)``
    and ``tilt(t) = tilt_offset + tilt_amplitude sin(2 pi t / tilt_period + phase_tilt)`` (t in
    seconds of simulated time, radians). The phases come from ``seed``. Peak joint speeds are
    ``2 pi amplitude / period``; the profile is clipped to the joint limits by
    :class:`SimulatedHead` (the defaults stay inside them)."""

    pan_amplitude_rad: float = math.radians(70.0)
    pan_period_s: float = 12.0
    tilt_amplitude_rad: float = math.radians(8.0)
    tilt_period_s: float = 17.0
    tilt_offset_rad: float = 0.0
    seed: int = 0

    def __post_init__(self) -> None:
        for name in ("pan_amplitude_rad", "tilt_amplitude_rad"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0.0):
                raise ValueError(f"HeadMotion.{name} {value!r}: must be >= 0")
        for name in ("pan_period_s", "tilt_period_s"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0.0):
                raise ValueError(f"HeadMotion.{name} {value!r}: must be > 0 s")
        if not math.isfinite(self.tilt_offset_rad):
            raise ValueError(f"HeadMotion.tilt_offset_rad {self.tilt_offset_rad!r}: not finite")

    @property
    def phases_rad(self) -> tuple[float, float]:
        rng = np.random.default_rng([int(self.seed), 5000])
        pan, tilt = rng.uniform(0.0, 2.0 * math.pi, 2)
        return float(pan), float(tilt)

    @property
    def peak_speeds_rad_s(self) -> tuple[float, float]:
        """(pan, tilt) peak joint speeds, rad/s."""
        return (2.0 * math.pi * self.pan_amplitude_rad / self.pan_period_s,
                2.0 * math.pi * self.tilt_amplitude_rad / self.tilt_period_s)

    def joints(self, t_s: float) -> tuple[float, float]:
        """(pan, tilt) in radians at simulated time ``t_s``."""
        phase_pan, phase_tilt = self.phases_rad
        pan = self.pan_amplitude_rad * math.sin(2.0 * math.pi * t_s / self.pan_period_s
                                                + phase_pan)
        tilt = self.tilt_offset_rad + self.tilt_amplitude_rad * math.sin(
            2.0 * math.pi * t_s / self.tilt_period_s + phase_tilt)
        return pan, tilt


class SimulatedHead:
    """The simulated head over time: ``kinematics`` moved by ``motion`` (``None``: a head held
    at pan = tilt = 0, the fixed mounting), t = 0 at ``epoch_ns``."""

    def __init__(self, kinematics: HeadKinematics, motion: HeadMotion | None,
                 epoch_ns: int) -> None:
        self.kinematics = kinematics
        self.motion = motion
        self.epoch_ns = int(epoch_ns)

    @classmethod
    def for_site_head(cls, T_base_cam_home: np.ndarray, epoch_ns: int, seed: int,
                      moving: bool = True) -> SimulatedHead:
        """The HSR-like head on a site file's head camera mounting, looking around with the
        default profile (``moving`` False: held at rest)."""
        return cls(HeadKinematics(np.asarray(T_base_cam_home, np.float64)),
                   HeadMotion(seed=seed) if moving else None, epoch_ns)

    def joints_at(self, stamp_ns: int) -> tuple[float, float]:
        """(pan, tilt) radians at ``stamp_ns``, inside the joint limits."""
        if self.motion is None:
            return 0.0, 0.0
        pan, tilt = self.motion.joints((int(stamp_ns) - self.epoch_ns) / NS_PER_S)
        k = self.kinematics
        return (min(max(pan, k.pan_limits_rad[0]), k.pan_limits_rad[1]),
                min(max(tilt, k.tilt_limits_rad[0]), k.tilt_limits_rad[1]))

    def T_base_cam(self, stamp_ns: int) -> np.ndarray:
        """The true (4, 4) camera optical frame -> ``base_link`` at ``stamp_ns``."""
        return self.kinematics.T_base_cam(*self.joints_at(stamp_ns))

    def dynamic_transforms(self, stamp_ns: int) -> list[FrameTransform]:
        """The ``/tf`` edges (pan, tilt) at ``stamp_ns``."""
        return [t for t in self.kinematics.transforms(*self.joints_at(stamp_ns)) if not t.static]

    def static_transforms(self) -> list[FrameTransform]:
        return self.kinematics.static_transforms()
