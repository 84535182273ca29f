"""The paper's evaluation protocol: seeded random perturbations and per-parameter pose errors.

Convention (used for both sampling and error decomposition): a rotation is
R = Rz(yaw) @ Ry(pitch) @ Rx(roll), angles in degrees, translations in metres.
A perturbation is applied about a centre point c (the source's centroid), so its
six parameters are exactly the initial error a method starts from:

    P = translate(c + t) @ R @ translate(-c)

Errors of an estimate are read from E = T_est @ inv(T_true) expressed about the
centre of the aligned source, so a rotation error does not turn into a fake
kilometre-sized translation error when the cloud sits at UTM coordinates.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from plotmosaic.config.bench import PROTOCOLS, Protocol
from plotmosaic.io.frame import translation

PARAMS = ("roll", "pitch", "yaw", "tx", "ty", "tz")


def get_protocol(
    name: str,
    rotation: float | None = None,
    yaw: float | None = None,
    translation_m: float | None = None,
) -> Protocol:
    """`paper`, `beyond`, or `custom` (+-rotation for roll/pitch, +-yaw, +-translation_m on x/y/z)."""
    if name in PROTOCOLS:
        return PROTOCOLS[name]
    if name != "custom":
        raise ValueError(f"unknown protocol {name!r} (paper, beyond, custom)")
    rot = 45.0 if rotation is None else rotation
    yw = rot if yaw is None else yaw
    tr = 15.0 if translation_m is None else translation_m
    return Protocol(name="custom", roll=rot, pitch=rot, yaw=yw, tx=tr, ty=tr, tz=tr)


def rotation_matrix(roll: float, pitch: float, yaw: float) -> np.ndarray:
    return Rotation.from_euler("ZYX", [yaw, pitch, roll], degrees=True).as_matrix()


def params_to_matrix(params, centre=(0.0, 0.0, 0.0)) -> np.ndarray:
    """4x4 transform rotating by (roll, pitch, yaw) about `centre`, then moving by (tx, ty, tz)."""
    p = np.asarray(params, dtype=np.float64)
    c = np.asarray(centre, dtype=np.float64)
    T = np.eye(4)
    T[:3, :3] = rotation_matrix(*p[:3])
    return translation(c + p[3:]) @ T @ translation(-c)


def sample_params(protocol: Protocol, n: int, seed: int) -> np.ndarray:
    """(n, 6) perturbations, each parameter uniform in +-its range, all six at once."""
    rng = np.random.default_rng(seed)
    return rng.uniform(-1.0, 1.0, size=(n, 6)) * protocol.ranges


def pose_error(T_est: np.ndarray, T_true: np.ndarray, centre) -> np.ndarray:
    """Signed (roll, pitch, yaw [deg], tx, ty, tz [m]) of T_est @ inv(T_true) about `centre`.

    `centre` is a point in the target frame (the aligned source's centroid): the translation
    error is how far that point lands from where it belongs.
    """
    c = np.asarray(centre, dtype=np.float64)
    E = (
        translation(-c)
        @ np.asarray(T_est, dtype=np.float64)
        @ np.linalg.inv(T_true)
        @ translation(c)
    )
    yaw, pitch, roll = Rotation.from_matrix(E[:3, :3]).as_euler("ZYX", degrees=True)
    return np.array([roll, pitch, yaw, *E[:3, 3]])


def rotation_angle(errors: np.ndarray) -> np.ndarray:
    """Total rotation angle (deg) of each error row (..., 6)."""
    e = np.atleast_2d(errors)
    rot = Rotation.from_euler("ZYX", e[:, [2, 1, 0]], degrees=True)
    return np.degrees(rot.magnitude())


def is_success(
    errors: np.ndarray, max_rotation_deg: float = 1.0, max_translation_m: float = 0.10
) -> np.ndarray:
    """The issue's success test: total rotation error < 1 deg and translation error < 10 cm."""
    e = np.atleast_2d(errors)
    return (rotation_angle(e) < max_rotation_deg) & (
        np.linalg.norm(e[:, 3:], axis=1) < max_translation_m
    )
