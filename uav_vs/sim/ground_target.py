"""A textured target moving on the ground plane (chapter section 5, following a target).

The target is a planar picture (the template the tracker looks for, e.g.
`assets/box.png`) lying on the ground plane z = 0 of `world` (ENU), `width` metres
wide, its centre driving round a circle at a steady speed, counter-clockwise, facing
the way it drives. `plane_from_template(t)` maps template pixels (u right, v down) to
ground points (x, y) at time t: what the onboard camera renders (OnboardScene.render's
`decals`) and what the scoring compares the vision estimate with.
"""
import math
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class CirclePath:
    """Round `center` (x, y, m) at `radius` (m) and `speed` (m/s), starting at `phase`
    (rad, 0 = east of the centre) at t = 0."""

    center: tuple[float, float] = (0.0, 0.0)
    radius: float = 0.4
    speed: float = 0.08
    phase: float = 0.0

    def __post_init__(self) -> None:
        if self.radius < 0 or self.speed < 0:
            raise ValueError('CirclePath: radius and speed must not be negative')

    def pose(self, t: float) -> tuple[np.ndarray, float]:
        """Centre (x, y), m, and heading (rad, ENU, the direction of travel) at time t, s."""
        angle = self.phase + (self.speed / self.radius * t if self.radius > 0 else 0.0)
        position = np.add(self.center, self.radius * np.array([math.cos(angle), math.sin(angle)]))
        return position, angle + math.pi / 2

    def velocity(self, t: float) -> np.ndarray:
        """Velocity (x, y), m/s, at time t."""
        _, heading = self.pose(t)
        return self.speed * np.array([math.cos(heading), math.sin(heading)])


class GroundTarget:
    """A picture lying on the ground and moving along `path`; the template's top edge is
    the target's front."""

    def __init__(self, template: np.ndarray, width: float, path: CirclePath) -> None:
        if width <= 0:
            raise ValueError(f'GroundTarget: width must be positive, got {width}')
        self.template = template
        self.width = width
        self.path = path
        h, w = template.shape[:2]
        s = width / w
        # Template (u, v, 1) -> target frame (forward, left, 1): v up is forward, u is right.
        self._local = np.array([[0.0, -s, s * h / 2], [-s, 0.0, s * w / 2], [0.0, 0.0, 1.0]])

    @property
    def length(self) -> float:
        """Extent along the direction of travel, m."""
        h, w = self.template.shape[:2]
        return self.width * h / w

    def decal(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        """What OnboardScene.render draws of it at time t: (template, plane_from_template)."""
        return self.template, self.plane_from_template(t)

    def plane_from_template(self, t: float) -> np.ndarray:
        """3x3 homography: template pixel (u, v, 1) -> ground point (x, y, 1) at time t."""
        (x, y), heading = self.path.pose(t)
        c, s = math.cos(heading), math.sin(heading)
        return np.array([[c, -s, x], [s, c, y], [0.0, 0.0, 1.0]]) @ self._local
