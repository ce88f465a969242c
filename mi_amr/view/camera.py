"""The viewer's orbit camera, in world units.

The camera sits at ``distance`` from ``target``, at ``azimuth`` degrees about
the ``up`` axis and ``elevation`` degrees above the plane normal to it; it
looks at the target. Orbit changes the two angles, zoom the distance, pan the
target: the page does that arithmetic and sends the result (a
`protocol.CameraChange`), which `OrbitCamera.moved` applies.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .protocol import CameraChange, parse_message

#: Elevation stays this far from the poles (look_at needs up and view apart).
MAX_ELEVATION = 89.0


def _frame(up):
    """Orthonormal ``(e1, e2, up)`` with ``up`` normalised."""
    up = np.asarray(up, np.float64)
    up = up / np.linalg.norm(up)
    helper = np.array([1.0, 0, 0]) if abs(up[0]) < 0.9 else np.array([0, 1.0, 0])
    e1 = np.cross(helper, up)
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(up, e1), up


@dataclass
class OrbitCamera:
    target: tuple
    up: tuple
    azimuth: float
    elevation: float
    distance: float
    fov: float

    @classmethod
    def looking(cls, origin, target, up, fov: float) -> "OrbitCamera":
        """The orbit camera at ``origin`` looking at ``target``."""
        e1, e2, u = _frame(up)
        d = np.asarray(origin, np.float64) - np.asarray(target, np.float64)
        dist = float(np.linalg.norm(d))
        if not dist > 0:
            raise ValueError("the camera sits on its target")
        el = float(np.degrees(np.arcsin(np.clip(d @ u / dist, -1, 1))))
        az = float(np.degrees(np.arctan2(d @ e2, d @ e1)))
        return cls(tuple(map(float, target)), tuple(map(float, u)), az,
                   float(np.clip(el, -MAX_ELEVATION, MAX_ELEVATION)), dist, float(fov))

    @property
    def origin(self) -> np.ndarray:
        e1, e2, u = _frame(self.up)
        a, e = np.radians(self.azimuth), np.radians(self.elevation)
        d = np.cos(e) * (np.cos(a) * e1 + np.sin(a) * e2) + np.sin(e) * u
        return np.asarray(self.target) + self.distance * d

    def to_json(self) -> dict:
        return {"target": list(self.target), "up": list(self.up), "azimuth": self.azimuth,
                "elevation": self.elevation, "distance": self.distance, "fov": self.fov}

    def from_message(self, msg) -> "OrbitCamera":
        """This camera moved by a page message (a `protocol.CameraChange` or
        its JSON fields); a `ValueError` names a bad field."""
        if not isinstance(msg, CameraChange):
            msg = parse_message(dict(msg, type="camera"))
        return self.moved(msg)

    def moved(self, change: CameraChange) -> "OrbitCamera":
        """This camera with the angles, distance and target of ``change``
        (missing ones kept; its fields already checked by the protocol): the
        azimuth wrapped to [0, 360), the elevation clamped to
        +-`MAX_ELEVATION`, the distance within 10^+-6 of this one's."""
        az = (change.azimuth if change.azimuth is not None else self.azimuth) % 360.0
        el = change.elevation if change.elevation is not None else self.elevation
        el = float(np.clip(el, -MAX_ELEVATION, MAX_ELEVATION))
        dist = change.distance if change.distance is not None else self.distance
        lo, hi = 1e-6 * self.distance, 1e6 * self.distance
        if not lo <= dist <= hi:
            raise ValueError(f"distance: a finite number in [{lo}, {hi}]")
        target = change.target if change.target is not None else self.target
        return OrbitCamera(tuple(map(float, target)), self.up, float(az), el, float(dist), self.fov)

    def transform(self):
        """The sensor's ``to_world`` (a ``mi.ScalarTransform4f``)."""
        import mitsuba as mi
        return mi.ScalarTransform4f().look_at(self.origin.tolist(), list(self.target), list(self.up))
