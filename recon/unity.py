"""Export a calibrated rig as the Unity twin parameters of the paper's Table 1 (section 2.5).

Per device: focal length and sensor size in mm (pixel pitch times resolution), lens shift
(principal point offset as a fraction of the sensor, Unity's y up), field of view
(``FOV = 2 atan(w / 2f)``; eq. 22 gives back ``f_p = (PSS/2) / tan(FOV/2)``), position
``C = -R^T T`` (eq. 20) and Euler angles from ``R^T = R_z(phi) R_x(theta) R_y(psi)`` (eq. 21),
all in the turntable (world) frame of the calibration file. Axis conventions are the
paper's: converting to Unity's left-handed, y-up scene axes is left to the scene set-up.
"""

from __future__ import annotations

import math

import numpy as np

from gearscan.core.rig import PinholeDevice, Rig


def euler_zxy(r_t: np.ndarray) -> tuple[float, float, float]:
    """Angles ``(phi, theta, psi)`` (rad) with ``r_t = R_z(phi) R_x(theta) R_y(psi)`` (eq. 21)."""
    m = np.asarray(r_t, dtype=np.float64)
    if m.shape != (3, 3):
        raise ValueError(f"r_t: expected a 3x3 rotation, got shape {m.shape}")
    theta = math.asin(float(np.clip(m[2, 1], -1.0, 1.0)))
    if abs(m[2, 1]) > 1.0 - 1e-12:
        # gimbal lock (theta = +-90 deg, e.g. a horizontal camera with image rows along the
        # turntable axis): only phi +- psi is defined; take psi = 0, then M = R_z(phi) R_x(theta)
        return math.atan2(m[1, 0], m[0, 0]), theta, 0.0
    psi = math.atan2(-m[2, 0], m[2, 2])
    phi = math.atan2(-m[0, 1], m[1, 1])
    return phi, theta, psi


def compose_zxy(phi: float, theta: float, psi: float) -> np.ndarray:
    """``R_z(phi) R_x(theta) R_y(psi)`` (eq. 21), the inverse of :func:`euler_zxy`."""
    cz, sz, cx, sx, cy, sy = math.cos(phi), math.sin(phi), math.cos(theta), math.sin(theta), math.cos(psi), math.sin(psi)
    rz = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    rx = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    return rz @ rx @ ry


def device_parameters(device: PinholeDevice, pixel_pitch_mm: float) -> dict:
    """Table 1 parameters of one camera or projector (lengths mm, angles deg)."""
    if not pixel_pitch_mm > 0:
        raise ValueError(f"pixel_pitch_mm must be positive, got {pixel_pitch_mm}")
    k = device.K
    w, h = device.width, device.height
    sensor_w, sensor_h = w * pixel_pitch_mm, h * pixel_pitch_mm
    focal_mm = k[0, 0] * pixel_pitch_mm
    fov_h = 2 * math.degrees(math.atan(sensor_w / (2 * focal_mm)))
    fov_v = 2 * math.degrees(math.atan(sensor_h / (2 * k[1, 1] * pixel_pitch_mm)))
    r, t = device.T_from_world[:3, :3], device.T_from_world[:3, 3]
    phi, theta, psi = euler_zxy(r.T)
    return {
        "resolution_px": [w, h],
        "pixel_pitch_mm": pixel_pitch_mm,
        "focal_length_mm": focal_mm,
        "focal_length_y_mm": k[1, 1] * pixel_pitch_mm,
        "sensor_size_mm": [sensor_w, sensor_h],
        "lens_shift": [(k[0, 2] - (w - 1) / 2) / w, -(k[1, 2] - (h - 1) / 2) / h],
        "fov_horizontal_deg": fov_h,
        "fov_vertical_deg": fov_v,
        "focal_length_from_fov_mm": (sensor_w / 2) / math.tan(math.radians(fov_h) / 2),  # eq. 22
        "position_mm": (-r.T @ t).tolist(),  # eq. 20
        "euler_zxy_deg": {"z_phi": math.degrees(phi), "x_theta": math.degrees(theta), "y_psi": math.degrees(psi)},
        "distortion_opencv": device.dist.tolist(),
    }


def unity_parameters(rig: Rig, camera_pixel_mm: float = 0.00345, projector_pixel_mm: float = 0.0076) -> dict:
    """Table 1 export of the whole rig.

    ``camera_pixel_mm`` defaults to 3.45 um (a 2448x2048 industrial sensor), the projector's
    to 7.6 um (a DLP micromirror pitch); only the projector's FOV matters to Unity, its
    virtual sensor size (PSS) is free.
    """
    return {
        "source": "gearscan rig calibration, paper Table 1 / eqs. 20-22",
        "frame": "turntable (z = rotation axis), mm",
        "camera": device_parameters(rig.camera, camera_pixel_mm),
        "projector": device_parameters(rig.projector, projector_pixel_mm),
    }
