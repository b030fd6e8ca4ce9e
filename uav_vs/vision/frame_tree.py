"""The graph's TF tree (REP-105): where the cameras are and where each pose source puts
the vehicle.

    world ─┬─> camK_optical        static: each ground camera (eq 16 inverted)
           ├─> base_link           one of the pose sources
           │     └─> onboard_camera_optical    static: the camera's mounting
           ├─> base_link_ground    ground/pose
           ├─> base_link_onboard   onboard/pose
           └─> base_link_odom      autopilot/odom

A transform parent -> child is the child's pose in the parent, x_parent = R x_child + t,
as tf2 stores it.
"""
from dataclasses import dataclass
from typing import Mapping

import numpy as np

from uav_vs.vision.body_pose import quaternion_xyzw
from uav_vs.vision.camera import Camera


@dataclass(frozen=True)
class Transform:
    """The pose of frame `child` in frame `parent`."""

    parent: str
    child: str
    translation: np.ndarray    # (3,) m
    quaternion: np.ndarray     # (4,) unit, xyzw


def camera_transform(world: str, camera: Camera) -> Transform:
    """world -> the camera's optical frame: its pose R^T, -R^T t from the world-to-camera
    R, t of eq 16 (x_c = R x_w + t)."""
    R_wc, centre = camera.pose_in_world()
    return Transform(world, camera.frame_id, centre, quaternion_xyzw(R_wc))


def mounting_transform(base_link: str, frame_id: str, camera_to_body: np.ndarray) -> Transform:
    """base_link -> a camera's optical frame from its 4x4 pose in base_link (x_b = T x_c)."""
    T = np.asarray(camera_to_body, float)
    return Transform(base_link, frame_id, T[:3, 3].copy(), quaternion_xyzw(T[:3, :3]))


def frame_name_problem(frames: Mapping[str, str]) -> str | None:
    """Why the frames named (parameter -> frame name) cannot make one tree, or None.

    tf2 refuses an empty name or one starting with '/'; no two parameters may name the
    same frame (one frame with two parents, or a frame its own parent).
    """
    seen: dict[str, str] = {}
    for param, name in frames.items():
        if not name or name.startswith('/') or any(c.isspace() for c in name):
            return f'{param}: {name!r} is no frame name (empty, a leading / or white space)'
        if name in seen:
            return (f'{param}: {name!r} is also {seen[name]}; every frame of the tree needs '
                    'its own name')
        seen[name] = param
    return None
