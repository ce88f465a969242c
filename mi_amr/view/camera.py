"""The viewer's orbit camera, in world units.

The camera sits at ``distance`` from ``target``, at ``azimuth`` degrees about
the ``up`` axis and ``elevation`` degrees above the plane normal to it; it
looks at the target. ``up`` is the scene's up, a world axis (`world_up`),
never the sensor's own tilted one: orbiting keeps the horizon level. The
elevation stays `MAX_ELEVATION` short of the poles and, where the scene has
a ground (``floor``: the least height along ``up`` of its non-medium
shapes), high enough that an orbit or zoom keeps the eye above it (a pan
may take it below). Orbit changes the two angles, zoom the distance, pan the
target: the page does that arithmetic (and the same clamps, static/viewer.js)
and sends the result (a `protocol.CameraChange`), which `OrbitCamera.moved`
applies.
"""

from __future__ import annotations

from dataclasses import dataclass

import mitsuba as mi
import numpy as np

from .protocol import CameraChange, parse_message

#: Largest elevation (degrees) either way: short of the poles, where the
#: azimuth turns the picture about the view direction.
MAX_ELEVATION = 85.0
#: An orbit or zoom keeps the eye this share of its distance above the floor.
FLOOR_MARGIN = 0.01


def world_up(up) -> tuple:
    """The world axis (+-x, +-y, +-z) nearest to the direction ``up``."""
    up = np.asarray(up, np.float64)
    k = int(np.argmax(np.abs(up)))
    if not np.isfinite(up).all() or up[k] == 0:
        raise ValueError(f"up: a finite non-zero direction, got {up.tolist()}")
    axis = np.zeros(3)
    axis[k] = np.sign(up[k])
    return tuple(axis.tolist())


def floor_height(boxes, up) -> float | None:
    """The least height along ``up`` (a unit vector) of boxes ``(n, 2, 3)``
    (min and max corners); None without boxes."""
    boxes = np.asarray(boxes, np.float64).reshape(-1, 2, 3)
    if not len(boxes):
        return None
    # the lowest corner of each box along up: per axis the min corner where up > 0
    low = np.where(np.asarray(up) > 0, boxes[:, 0, :], boxes[:, 1, :]) @ np.asarray(up, np.float64)
    return float(low.min())


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
    floor: float | None = None          # least height of the eye along up on orbit and zoom

    @classmethod
    def looking(cls, origin, target, up, fov: float, floor: float | None = None) -> "OrbitCamera":
        """The orbit camera at ``origin`` looking at ``target`` about ``up``
        (the elevation clamped to +-`MAX_ELEVATION`)."""
        e1, e2, u = _frame(up)
        d = np.asarray(origin, np.float64) - np.asarray(target, np.float64)
        dist = float(np.linalg.norm(d))
        if not dist > 0:
            raise ValueError("the camera sits on its target")
        el = float(np.degrees(np.arcsin(np.clip(d @ u / dist, -1, 1))))
        az = float(np.degrees(np.arctan2(d @ e2, d @ e1)))
        return cls(tuple(map(float, target)), tuple(map(float, u)), az,
                   float(np.clip(el, -MAX_ELEVATION, MAX_ELEVATION)), dist, float(fov),
                   None if floor is None else float(floor))

    @property
    def origin(self) -> np.ndarray:
        e1, e2, u = _frame(self.up)
        a, e = np.radians(self.azimuth), np.radians(self.elevation)
        d = np.cos(e) * (np.cos(a) * e1 + np.sin(a) * e2) + np.sin(e) * u
        return np.asarray(self.target) + self.distance * d

    def to_json(self) -> dict:
        return {"target": list(self.target), "up": list(self.up), "azimuth": self.azimuth,
                "elevation": self.elevation, "distance": self.distance, "fov": self.fov, "floor": self.floor}

    def lowest_elevation(self, target, distance: float) -> float:
        """The least elevation (degrees) an orbit or zoom may take with this
        ``target`` and ``distance``: the eye `FLOOR_MARGIN` of the distance
        above the floor (none while the target itself is below it)."""
        if self.floor is None:
            return -MAX_ELEVATION
        height = float(np.dot(target, self.up))
        if height < self.floor:
            return -MAX_ELEVATION
        s = (self.floor - height) / distance + FLOOR_MARGIN
        return float(np.clip(np.degrees(np.arcsin(np.clip(s, -1.0, 1.0))), -MAX_ELEVATION, MAX_ELEVATION))

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
        +-`MAX_ELEVATION` and, when the angles or the distance change (an
        orbit or zoom, not a pan), to `lowest_elevation`; the distance
        within 10^+-6 of this one's."""
        az = (change.azimuth if change.azimuth is not None else self.azimuth) % 360.0
        el = change.elevation if change.elevation is not None else self.elevation
        el = float(np.clip(el, -MAX_ELEVATION, MAX_ELEVATION))
        dist = change.distance if change.distance is not None else self.distance
        lo, hi = 1e-6 * self.distance, 1e6 * self.distance
        if not lo <= dist <= hi:
            raise ValueError(f"distance: a finite number in [{lo}, {hi}]")
        target = change.target if change.target is not None else self.target
        if (az, el, dist) != (self.azimuth % 360.0, self.elevation, self.distance):
            el = max(el, self.lowest_elevation(target, dist))
        return OrbitCamera(tuple(map(float, target)), self.up, float(az), el, float(dist), self.fov, self.floor)

    def transform(self):
        """The sensor's ``to_world`` (a ``mi.ScalarTransform4f``)."""
        return mi.ScalarTransform4f().look_at(self.origin.tolist(), list(self.target), list(self.up))
