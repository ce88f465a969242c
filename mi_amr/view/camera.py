"""The viewer's orbit camera, in world units.

The camera sits at ``distance`` from ``target``, at ``azimuth`` degrees about
the ``up`` axis and ``elevation`` degrees above the plane normal to it; it
looks at the target. Orbit changes the two angles, zoom the distance, pan the
target: the page does that arithmetic and sends the result, which
`OrbitCamera.from_message` checks.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

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

    def from_message(self, msg: dict) -> "OrbitCamera":
        """This camera with the angles, distance and target of a page
        message (missing ones kept); a `ValueError` names a bad field."""
        def number(name, lo=-np.inf, hi=np.inf):
            v = msg.get(name, getattr(self, name))
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not np.isfinite(v) or not lo <= v <= hi:
                raise ValueError(f"{name}: a finite number in [{lo}, {hi}]")
            return float(v)
        az = number("azimuth", -1e6, 1e6) % 360.0
        el = float(np.clip(number("elevation", -90, 90), -MAX_ELEVATION, MAX_ELEVATION))
        dist = number("distance", 1e-6 * self.distance, 1e6 * self.distance)
        target = msg.get("target", list(self.target))
        try:
            t = np.array(target, dtype=np.float64)
        except (TypeError, ValueError):
            raise ValueError("target: three numbers") from None
        if t.shape != (3,) or not np.all(np.isfinite(t)) or np.abs(t).max() > 1e9:
            raise ValueError("target: three finite numbers")
        return OrbitCamera(tuple(t.tolist()), self.up, az, el, dist, self.fov)

    def transform(self):
        """The sensor's ``to_world`` (a ``mi.ScalarTransform4f``)."""
        import mitsuba as mi
        return mi.ScalarTransform4f().look_at(self.origin.tolist(), list(self.target), list(self.up))
