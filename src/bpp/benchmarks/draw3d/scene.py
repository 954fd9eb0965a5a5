"""DrawAnything-Real's scene in MuJoCo: a Panda arm holding a pen in front of a whiteboard, a square canvas with four
red corner markers placed anywhere on the board at any rotation within ±45 degrees, a wrist camera and a scene camera.

The arm is robosuite's Panda model (its meshes ship in the ``libero`` extra's robosuite), driven by torques from an
operational-space controller: the pen tip is pulled toward its commanded pose by a critically damped 6-D spring
through the arm's task-space inertia, with gravity and Coriolis compensated. Commands are 6-DoF: each action moves
the commanded pen pose by a relative step in its own frame (:func:`bpp.core.poses.vector_to_pose`), as a robot
driver composes relative actions with its current target. The pen is compliant, like the paper's spring-loaded
marker: it inks where its tip is within :data:`PEN_REACH` of the board surface (ink as polylines in the canvas frame),
and the ink is painted into the canvas's texture so that the cameras see it.

Frames: the robot's base is the world origin (x forward, z up); the canvas frame has its origin at the canvas centre,
x right and y up as the robot sees the upright canvas, z out of the board toward the robot.
"""

from __future__ import annotations

import logging
import os
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field

import numpy as np

from bpp.core.poses import invert, make_pose, vector_to_pose
from bpp.drawing.marked_canvas import CANVAS_SIDE, MARKER_SIDE
from bpp.errors import require_extra
from bpp.media import headless_opengl

os.environ.setdefault("MUJOCO_GL", "egl")  # headless OpenGL (Mesa); MuJoCo reads it when first imported

BOARD_TILT_DEG = 45.0
"""The whiteboard leans back like an easel, its surface this far from vertical, facing the robot: the arm draws with
the pen pointing forward and down, where a Panda is dexterous (pointing it straight forward runs joint 6 into its
limit)."""
BOARD_CENTRE = np.array([0.55, 0.0, 0.30])
"""The centre of the board's surface in the base frame (m)."""
BOARD_HALF = (0.45, 0.25)
"""The board's half width (across, along -y) and half height (up its slope) (m)."""
PAPER = 0.0006
"""The canvas's thickness: its surface stands this far in front of the board's (m)."""
PEN_LENGTH = 0.13
"""From the hand's flange to the pen's tip (m)."""
PEN_REACH = 0.002
"""The tip inks when it is within this distance of the board's surface (the pen's spring travel, m)."""
TEXTURE = 256
"""The canvas texture's side (px): the ink the cameras see."""
SCENE_CAMERA = np.array([0.15, -0.6, 1.15])
"""Where the fixed scene camera stands (it looks at the board's centre), in the base frame (m)."""
CONTROL_HZ = 20.0
TIMESTEP = 0.002
HOME_QPOS = np.array([0.0, -0.35, 0.0, -2.2, 0.0, 1.9, np.pi / 4])
"""A joint configuration with the pen pointing at the board from about 30 cm away."""
STIFFNESS = 900.0
"""The pen tip's spring toward its commanded pose: natural frequency squared (1/s^2), critically damped, applied
through the arm's task-space inertia (operational-space control), so that every direction responds alike."""
POSTURE_STIFFNESS = 25.0
"""The same for the arm's spare joint motion, toward :data:`HOME_QPOS`."""
_T = np.deg2rad(BOARD_TILT_DEG)
BOARD = np.array([[0.0, np.sin(_T), -np.cos(_T)], [-1.0, 0.0, 0.0], [0.0, np.cos(_T), np.sin(_T)]])
"""The board's axes in the base frame (columns): x right as the robot sees it (-y), y up the board's slope, z its
normal toward the robot. An upright canvas has the same axes."""


def _look_at(eye, target, up=(0.0, 0.0, 1.0)) -> str:
    """A MuJoCo camera's ``xyaxes`` looking from `eye` at `target` (its -z axis points at the target)."""
    forward = np.asarray(target, float) - np.asarray(eye, float)
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, up)
    right /= np.linalg.norm(right)
    camera_up = np.cross(right, forward)
    return " ".join(f"{v:.6f}" for v in (*right, *camera_up))


def scene_xml() -> str:
    """The scene's MJCF: robosuite's Panda (no gripper: a pen on the flange), the board, the canvas, the cameras."""
    require_extra("robosuite", "libero")

    logging.getLogger("robosuite").setLevel(logging.ERROR)
    # robosuite: the libero extra
    from robosuite.models.robots import Panda
    from robosuite.models.world import MujocoWorldBase

    world = MujocoWorldBase()
    world.merge(Panda())
    root = ET.fromstring(world.get_xml())
    option = root.find("option") if root.find("option") is not None else ET.SubElement(root, "option")
    option.set("timestep", str(TIMESTEP))
    ET.SubElement(option, "flag", contact="disable")  # the pen inks by distance; nothing else touches
    visual = root.find("visual") if root.find("visual") is not None else ET.SubElement(root, "visual")
    ET.SubElement(visual, "global", offwidth="1024", offheight="1024")  # photos up to 1024 px
    asset = root.find("asset")
    ET.SubElement(asset, "texture", name="canvas_ink", type="2d", builtin="flat", width=str(TEXTURE),
                  height=str(TEXTURE), rgb1="0.96 0.96 0.93", rgb2="0.96 0.96 0.93")  # fmt: skip
    ET.SubElement(asset, "material", name="canvas_paper", texture="canvas_ink", texuniform="false")
    worldbody = root.find("worldbody")
    light = {"pos": "-0.5 0.3 2.0", "dir": "0.5 -0.2 -1", "diffuse": "0.55 0.55 0.55", "specular": "0.1 0.1 0.1"}
    ET.SubElement(worldbody, "light", directional="true", **light)
    ET.SubElement(
        worldbody, "geom", name="floor", group="2", type="plane", size="2 2 0.05", rgba="0.45 0.42 0.4 1", pos="0 0 0"
    )
    half_w, half_h = BOARD_HALF
    axes = " ".join(f"{v:.6f}" for v in (*BOARD[:, 0], *BOARD[:, 1]))
    centre = BOARD_CENTRE - 0.01 * BOARD[:, 2]
    ET.SubElement(worldbody, "geom", name="board", group="2", type="box", size=f"{half_w} {half_h} 0.01", xyaxes=axes,
                  pos=" ".join(f"{v:.6f}" for v in centre), rgba="0.82 0.85 0.88 1")  # fmt: skip
    canvas = ET.SubElement(worldbody, "body", name="canvas", mocap="true", pos=" ".join(map(str, BOARD_CENTRE)))
    # the canvas body's origin is the paper's surface (the canvas frame); the paper lies on the board behind it
    half = CANVAS_SIDE / 2
    ET.SubElement(canvas, "geom", name="canvas", group="2", type="box", size=f"{half} {half} 0.0003", pos="0 0 -0.0003",
                  material="canvas_paper")  # fmt: skip
    offset = CANVAS_SIDE / 2 - MARKER_SIDE / 2
    for i, (sx, sy) in enumerate(((-1, 1), (1, 1), (1, -1), (-1, -1))):
        # printed on the paper: its face 0.1 mm above the paper, so that no side of it shows
        half_marker = MARKER_SIDE / 2
        marker = {"size": f"{half_marker} {half_marker} 0.00015", "pos": f"{sx * offset} {sy * offset} -0.00005"}
        ET.SubElement(canvas, "geom", name=f"marker{i}", group="2", type="box", rgba="0.78 0.12 0.12 1", **marker)
    ET.SubElement(worldbody, "camera", name="scene", mode="fixed", pos=" ".join(map(str, SCENE_CAMERA)), fovy="55",
                  xyaxes=_look_at(SCENE_CAMERA, BOARD_CENTRE))  # fmt: skip
    hand = next(b for b in root.iter("body") if b.get("name", "").endswith("right_hand"))
    pen = ET.SubElement(hand, "body", name="pen", pos="0 0 0")
    ET.SubElement(pen, "geom", name="pen", group="2", type="capsule", fromto=f"0 0 0.01 0 0 {PEN_LENGTH - 0.005}",
                  size="0.005", rgba="0.1 0.1 0.12 1", mass="0.02")  # fmt: skip
    # the tip's frame is the flange's turned a quarter about the pen: a pen aligned with an upright canvas then puts
    # the last joint mid-range, so canvases turned ±45 degrees stay clear of its limits
    ET.SubElement(pen, "site", name="pen_tip", pos=f"0 0 {PEN_LENGTH}", quat="0.70710678 0 0 0.70710678", size="0.003",
                  rgba="0.9 0.1 0.1 1")  # fmt: skip
    # the wrist camera: beside the pen, looking along it, as the iPhone on the paper's gripper
    ET.SubElement(pen, "camera", name="wrist", mode="fixed", pos="0 0.07 0.03", fovy="75",
                  xyaxes="-1 0 0 0 0.819 0.573")  # fmt: skip
    return ET.tostring(root, encoding="unicode")


@dataclass
class Ink:
    """What the pen drew: strokes as (N, 2) polylines in the canvas frame (metres)."""

    strokes: list = field(default_factory=list)
    down: bool = False

    def add(self, point: np.ndarray, touching: bool) -> None:
        if touching:
            if not self.down:
                self.strokes.append([])
            self.strokes[-1].append(np.asarray(point, dtype=np.float64))
        self.down = touching

    def polylines(self) -> list[np.ndarray]:
        return [np.asarray(s) for s in self.strokes if len(s)]

    @property
    def length(self) -> float:
        return float(sum(np.linalg.norm(np.diff(p, axis=0), axis=1).sum() for p in self.polylines() if len(p) > 1))


def canvas_transform(u: float, v: float, angle_deg: float) -> np.ndarray:
    """``T_base_canvas`` of a canvas centred at (u, v) on the board (metres right and up its slope from the board's
    centre), rotated by `angle_deg` about the board's normal."""
    angle = np.deg2rad(angle_deg)
    spin = np.array([[np.cos(angle), -np.sin(angle), 0.0], [np.sin(angle), np.cos(angle), 0.0], [0.0, 0.0, 1.0]])
    surface = BOARD_CENTRE + u * BOARD[:, 0] + v * BOARD[:, 1] + PAPER * BOARD[:, 2]
    return make_pose(BOARD @ spin, surface)


class Scene:
    """The simulated arm, board and canvas. ``reset`` places the canvas, ``step`` takes a relative pen action."""

    def __init__(self, image_size: int = 96):
        headless_opengl()
        # MuJoCo: the libero extra
        import mujoco

        self.mujoco = mujoco
        self.model = mujoco.MjModel.from_xml_string(scene_xml())
        self.data = mujoco.MjData(self.model)
        self.tip = self.model.site("pen_tip").id
        self.canvas_body = self.model.body("canvas").mocapid[0]
        self.texture = self.model.texture("canvas_ink").id
        self.joints = np.arange(7)
        self.ranges = self.model.jnt_range[:7].copy()
        self.image_size = image_size
        self._renderers: dict = {}
        self._visible = mujoco.MjvOption()
        self._visible.geomgroup[0] = 0  # robosuite's collision meshes (the visual meshes are group 1)
        self._visible.sitegroup[:] = 0  # sites are reference points, not things a camera sees (the tip's is red)
        self.substeps = round(1.0 / (CONTROL_HZ * TIMESTEP))
        self._ctrl_low, self._ctrl_high = self.model.actuator_ctrlrange[:7].T.copy()

    # ------------------------------------------------------------------ state
    def reset(self, canvas: np.ndarray, qpos: np.ndarray = HOME_QPOS) -> None:
        """Place the canvas (``T_base_canvas``), put the arm at `qpos` at rest, and clear the ink."""
        mujoco = self.mujoco
        mujoco.mj_resetData(self.model, self.data)
        self.data.qpos[:7] = qpos
        self.canvas = np.asarray(canvas, dtype=np.float64)
        self._from_base = invert(self.canvas)
        quat = np.zeros(4)
        mujoco.mju_mat2Quat(quat, self.canvas[:3, :3].reshape(-1))
        self.data.mocap_pos[self.canvas_body] = self.canvas[:3, 3]
        self.data.mocap_quat[self.canvas_body] = quat
        mujoco.mj_forward(self.model, self.data)
        self.target = self.tip_pose()
        self._target_velocity = np.zeros(6)
        self.ink = Ink()
        self._paper = np.full((TEXTURE, TEXTURE, 3), (245, 245, 237), np.uint8)
        self._paper_dirty = True
        self._record_ink()

    def fold(self, qpos: np.ndarray) -> None:
        """Put the arm at `qpos` at rest, leaving the canvas and its ink as they are (to photograph the board)."""
        self.data.qpos[:7] = qpos
        self.data.qvel[:] = 0.0
        self.mujoco.mj_forward(self.model, self.data)
        self.ink.down = False

    def tip_pose(self) -> np.ndarray:
        """``T_base_tip`` (4, 4): the pen tip, z along the pen (toward the board when drawing)."""
        rotation = self.data.site_xmat[self.tip].reshape(3, 3)
        return make_pose(rotation, self.data.site_xpos[self.tip])

    def tip_in_canvas(self) -> np.ndarray:
        """The pen tip's position in the canvas frame (3,): z is its height above the surface."""
        return self._from_base[:3, :3] @ self.data.site_xpos[self.tip] + self._from_base[:3, 3]

    # ------------------------------------------------------------------ control
    def step(self, action: np.ndarray) -> None:
        """Move the commanded pen pose by `action` (9: position + 6-D rotation, in the commanded pose's frame; a tenth
        entry, the gripper's, is ignored: the pen is held), then simulate one control period."""
        previous = self.target
        self.target = self.target @ vector_to_pose(np.asarray(action, dtype=np.float64)[:9])
        # the commanded pose's velocity over the control period, fed forward so that a moving target is followed
        # without the lag of a spring pulled along a ramp
        self._target_velocity = (
            np.concatenate(
                [self.target[:3, 3] - previous[:3, 3], self._rotation_vector(self.target[:3, :3] @ previous[:3, :3].T)]
            )
            * CONTROL_HZ
        )
        for _ in range(self.substeps):
            self.data.ctrl[:7] = np.minimum(np.maximum(self._torques(), self._ctrl_low), self._ctrl_high)
            self.mujoco.mj_step(self.model, self.data)
            self._record_ink()

    def _torques(self) -> np.ndarray:
        """Operational-space control of the pen tip toward the commanded pose: a critically damped spring in the
        tip's 6-D space through the arm's task-space inertia, gravity and Coriolis compensated, and the arm's spare
        joint held near a comfortable posture without disturbing the tip."""
        mujoco, model, data = self.mujoco, self.model, self.data
        jac_p, jac_r = np.zeros((3, model.nv)), np.zeros((3, model.nv))
        mujoco.mj_jacSite(model, data, jac_p, jac_r, self.tip)
        jac = np.vstack([jac_p[:, :7], jac_r[:, :7]])
        mass = np.zeros((model.nv, model.nv))
        mujoco.mj_fullM(model, data, mass)
        mass_inv = np.linalg.inv(mass[:7, :7])
        task_inertia = np.linalg.inv(jac @ mass_inv @ jac.T + 1e-6 * np.eye(6))
        rotation = data.site_xmat[self.tip].reshape(3, 3)
        error = np.concatenate(
            [self.target[:3, 3] - data.site_xpos[self.tip], self._rotation_vector(self.target[:3, :3] @ rotation.T)]
        )
        velocity = jac @ data.qvel[:7]
        force = task_inertia @ (STIFFNESS * error + 2.0 * np.sqrt(STIFFNESS) * (self._target_velocity - velocity))
        dynamically_consistent = mass_inv @ jac.T @ task_inertia
        nullspace = np.eye(7) - jac.T @ dynamically_consistent.T
        posture = mass[:7, :7] @ (
            POSTURE_STIFFNESS * (HOME_QPOS - data.qpos[:7]) - 2.0 * np.sqrt(POSTURE_STIFFNESS) * data.qvel[:7]
        )
        return jac.T @ force + nullspace @ posture + data.qfrc_bias[:7]

    def _rotation_vector(self, rotation: np.ndarray) -> np.ndarray:
        """The rotation vector (axis times angle, at most pi) of a rotation matrix, through MuJoCo's quaternions:
        called at every physics step, where scipy's ``Rotation`` costs many times as much."""
        quat, vector = np.empty(4), np.empty(3)
        self.mujoco.mju_mat2Quat(quat, np.ascontiguousarray(rotation).reshape(-1))
        self.mujoco.mju_quat2Vel(vector, quat, 1.0)
        return vector

    def _record_ink(self) -> None:
        point = self.tip_in_canvas()
        inside = np.all(np.abs(point[:2]) <= CANVAS_SIDE / 2)
        touching = bool(point[2] <= PEN_REACH and inside)
        previous = self.ink.strokes[-1][-1] if self.ink.down and self.ink.strokes else None
        self.ink.add(point[:2], touching)
        if touching and previous is not None:
            self._ink_line(previous, point[:2])

    def _ink_line(self, a: np.ndarray, b: np.ndarray) -> None:
        """Paint the ink from canvas point `a` to `b` (metres) into the canvas's texture."""
        # OpenCV: the iphumi extra
        import cv2

        cv2.line(self._paper, _texture_px(a), _texture_px(b), (25, 25, 30), 2, lineType=cv2.LINE_AA)
        self._paper_dirty = True

    def paint(self, polylines) -> None:
        """Ink `polylines` ((N, 2) points in the canvas frame, metres) onto the canvas, as the pen would have drawn
        them (a demonstration made elsewhere, photographed here)."""
        for line in polylines:
            points = np.asarray(line, dtype=np.float64)
            for a, b in zip(points[:-1], points[1:], strict=True):
                self._ink_line(a, b)
            self.ink.strokes.append(list(points))

    # ------------------------------------------------------------------ cameras
    def render(self, camera: str, size: int | None = None) -> np.ndarray:
        """An RGB frame (size, size, 3) uint8 of camera ``wrist`` or ``scene``, with the ink drawn so far."""
        mujoco = self.mujoco
        size = size or self.image_size
        if size not in self._renderers:
            self._renderers[size] = mujoco.Renderer(self.model, size, size)
        renderer = self._renderers[size]
        if self._paper_dirty:
            start = self.model.tex_adr[self.texture]
            count = TEXTURE * TEXTURE * 3
            self.model.tex_data[start : start + count] = self._paper.reshape(-1)
            for r in self._renderers.values():
                r._gl_context.make_current()  # the upload goes to the current OpenGL context
                mujoco.mjr_uploadTexture(self.model, r._mjr_context, self.texture)
            self._paper_dirty = False
        renderer.update_scene(self.data, camera=camera, scene_option=self._visible)
        return renderer.render().copy()

    def camera_intrinsics(self, camera: str, size: int | None = None) -> np.ndarray:
        """The pinhole matrix K (3, 3) of `camera` rendered at size x size, in OpenCV's pixel convention (pixel i's
        centre at coordinate i, so the image's centre at (size - 1) / 2)."""
        size = size or self.image_size
        focal = size / 2 / np.tan(np.deg2rad(self.model.camera(camera).fovy[0]) / 2)
        centre = (size - 1) / 2
        return np.array([[focal, 0.0, centre], [0.0, focal, centre], [0.0, 0.0, 1.0]])

    def camera_pose(self, camera: str) -> np.ndarray:
        """``T_base_camera`` of `camera` with OpenCV's axes (x right, y down, z forward): a camera-to-robot
        extrinsic calibration."""
        index = self.model.camera(camera).id
        rotation = self.data.cam_xmat[index].reshape(3, 3) @ np.diag([1.0, -1.0, -1.0])  # MuJoCo's look along -z
        return make_pose(rotation, self.data.cam_xpos[index])

    def project(self, camera: str, points: np.ndarray, size: int | None = None) -> np.ndarray:
        """Base-frame points (N, 3) -> their pixels (N, 2) in `camera`'s size x size image."""
        in_camera = (invert(self.camera_pose(camera)) @ np.c_[points, np.ones(len(points))].T)[:3]
        pixels = self.camera_intrinsics(camera, size) @ in_camera
        return (pixels[:2] / pixels[2]).T  # OpenCV's convention: round to index the image

    def close(self) -> None:
        for renderer in self._renderers.values():
            renderer.close()
        self._renderers.clear()


def _texture_px(point: np.ndarray) -> tuple[int, int]:
    """A canvas point (m) -> the texture's pixel (column, row); the texture's rows run along the canvas's -y."""
    u = (point[0] / CANVAS_SIDE + 0.5) * (TEXTURE - 1)
    v = (0.5 - point[1] / CANVAS_SIDE) * (TEXTURE - 1)
    return int(round(u)), int(round(v))
