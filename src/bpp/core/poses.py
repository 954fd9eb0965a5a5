"""Rigid poses for benchmarks whose actions are 6-DoF: 4x4 homogeneous transforms, the continuous 6-D rotation
representation, relative actions, and interpolation on the rotation group.

Conventions: a pose ``T_a_b`` (..., 4, 4) maps points in frame b to frame a; a *pose vector* is (..., 9): the
position (metres) followed by the 6-D rotation, the first two columns of the rotation matrix (Zhou et al., "On the
continuity of rotation representations", 2019), which a network regresses without the discontinuities of Euler angles
or quaternions' sign.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

POSE_DIM = 9
"""Position (3) + 6-D rotation (6)."""


def rot6d_from_matrix(rotation: np.ndarray) -> np.ndarray:
    """(..., 3, 3) rotation matrices -> (..., 6): the first column, then the second."""
    rotation = np.asarray(rotation)
    return np.concatenate([rotation[..., :, 0], rotation[..., :, 1]], axis=-1)


def matrix_from_rot6d(rot6d: np.ndarray) -> np.ndarray:
    """(..., 6) -> (..., 3, 3) rotation matrices by Gram-Schmidt (any two independent vectors give a rotation)."""
    rot6d = np.asarray(rot6d, dtype=np.float64)
    a, b = rot6d[..., :3], rot6d[..., 3:6]
    x = a / np.linalg.norm(a, axis=-1, keepdims=True)
    b = b - np.sum(x * b, axis=-1, keepdims=True) * x
    y = b / np.linalg.norm(b, axis=-1, keepdims=True)
    z = np.cross(x, y)
    return np.stack([x, y, z], axis=-1)


def make_pose(rotation: np.ndarray, position: np.ndarray) -> np.ndarray:
    """(..., 3, 3) and (..., 3) -> (..., 4, 4)."""
    rotation, position = np.asarray(rotation, dtype=np.float64), np.asarray(position, dtype=np.float64)
    pose = np.zeros((*np.broadcast_shapes(rotation.shape[:-2], position.shape[:-1]), 4, 4))
    pose[..., :3, :3] = rotation
    pose[..., :3, 3] = position
    pose[..., 3, 3] = 1.0
    return pose


def invert(pose: np.ndarray) -> np.ndarray:
    """The inverse of rigid poses (..., 4, 4), without a general matrix inverse."""
    rotation_t = np.swapaxes(pose[..., :3, :3], -1, -2)
    return make_pose(rotation_t, -np.einsum("...ij,...j->...i", rotation_t, pose[..., :3, 3]))


def pose_to_vector(pose: np.ndarray) -> np.ndarray:
    """(..., 4, 4) -> (..., 9) position + 6-D rotation."""
    return np.concatenate([pose[..., :3, 3], rot6d_from_matrix(pose[..., :3, :3])], axis=-1)


def vector_to_pose(vector: np.ndarray) -> np.ndarray:
    """(..., 9) position + 6-D rotation -> (..., 4, 4)."""
    vector = np.asarray(vector, dtype=np.float64)
    return make_pose(matrix_from_rot6d(vector[..., 3:9]), vector[..., :3])


def relative_to_first(poses: np.ndarray) -> np.ndarray:
    """(N, 4, 4) poses in any world frame -> the same poses in the frame of the first: ``T_0^-1 T_t``. A phone's
    world frame (ARKit's) is arbitrary per recording, so only poses relative to the episode's start carry over."""
    return invert(poses[0]) @ poses


def relative_actions(poses: np.ndarray) -> np.ndarray:
    """(N, 4, 4) poses -> (N, 9) per-step relative actions: step t moves from pose t to pose t+1, expressed in pose
    t's own frame (``T_t^-1 T_{t+1}``), so an action means the same motion wherever the robot stands. The last step
    repeats the one before (an episode's last action has no next pose; a single pose gives the identity)."""
    if len(poses) < 2:
        return np.repeat(pose_to_vector(np.eye(4))[None], len(poses), axis=0)
    steps = invert(poses[:-1]) @ poses[1:]
    return pose_to_vector(np.concatenate([steps, steps[-1:]], axis=0))


def integrate_actions(start: np.ndarray, actions: np.ndarray) -> np.ndarray:
    """The inverse of :func:`relative_actions`: (4, 4) start pose and (N, 9) actions -> (N + 1, 4, 4) poses."""
    poses = [np.asarray(start, dtype=np.float64)]
    for step in vector_to_pose(actions):
        poses.append(poses[-1] @ step)
    return np.stack(poses)


def interpolate_poses(times: np.ndarray, poses: np.ndarray, at: np.ndarray) -> np.ndarray:
    """Poses (N, 4, 4) sampled at increasing `times` (N,) -> poses at `at` (M,) inside [times[0], times[-1]]: positions
    linearly, rotations by spherical linear interpolation on the rotation group (never per matrix entry, which leaves
    the group)."""

    times, at = np.asarray(times, dtype=np.float64), np.asarray(at, dtype=np.float64)
    assert np.all(np.diff(times) > 0), "interpolation times must increase"
    rotations = Slerp(times, Rotation.from_matrix(poses[:, :3, :3]))(at).as_matrix()
    positions = np.stack([np.interp(at, times, poses[:, :3, 3][:, i]) for i in range(3)], axis=-1)
    return make_pose(rotations, positions)


def rotation_angle(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The angle (radians) between rotations (..., 3, 3) a and b."""
    relative = np.swapaxes(a, -1, -2) @ b
    cosine = (np.trace(relative, axis1=-2, axis2=-1) - 1.0) / 2.0
    return np.arccos(np.clip(cosine, -1.0, 1.0))
