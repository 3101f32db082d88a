"""The emulated robot with its physics in a process of its own (`PhysicsProcess`, what bruce-emulate runs on the wall
clock): what a host writes to the emulated BEARs still moves the robot, each step on the commands of its moment, and
the operator's commands still reach it."""

from __future__ import annotations

import numpy as np
from support.fake_bus import wait_for

from bruce_hw.config import load_config
from bruce_hw.emulation.physics_process import PhysicsProcess
from bruce_hw.emulation.robot import EmulatedRobot
from drivers.bear import BearBus


def test_the_physics_process_moves_the_robot_the_host_commands():
    config = load_config()
    ids = list(config.buses.bear.ids)
    with EmulatedRobot(config, physics_process=True) as robot:
        assert isinstance(robot.plant, PhysicsProcess)
        assert robot.plant.held  # on the stand of the operator's hands until a BEAR is enabled
        port = next(o.split("=", 1)[1] for o in robot.port_overrides() if o.startswith("buses.bear.port="))
        with BearBus(port, reply_timeout_s=0.05) as bus:
            standing = bus.bulk_cycle(ids, None).position
            steps = robot.plant.steps
            bus.set_torque_enable(ids, 1)  # torque mode, no current asked: the robot is let go and folds
            assert wait_for(lambda: not robot.plant.held)
            assert wait_for(lambda: np.max(np.abs(bus.bulk_cycle(ids, None).position - standing)) > 0.05)
            assert robot.plant.steps > steps
            # One exchange per physics step, at the step (not on a clock of the bridge's own): every step fetched the
            # devices' commands of its moment, so the counts agree but for the step under way.
            before = robot.plant.bridge_cycles
            done = robot.plant.steps
            after = robot.plant.bridge_cycles
            assert done > 0 and before - 1 <= done <= after, (before, done, after)
            nominal = robot.plant.nominal_base_height
            assert wait_for(lambda: robot.plant.ground_truth().base_pos[2] < nominal - 0.01)  # it sinks
            bus.set_torque_enable(ids, 0)  # every BEAR off: put back at the standing pose and held
            assert wait_for(lambda: robot.plant.held)
            assert wait_for(lambda: np.max(np.abs(bus.bulk_cycle(ids, None).position - standing)) < 1e-6)
        robot.plant.stand(True)  # the operator's command goes to the physics process and back
        assert robot.plant.ground_truth().base_pos[2] > nominal
    assert robot.plant.status()["steps"] > steps  # the counters outlive the process, for the shutdown's summary


def test_the_arms_follow_the_hosts_goals_through_the_physics_process():
    """The arm servos' goals and what they measure cross to the physics process only at the arms' own steps (50 Hz,
    as in one process): a goal the host writes over the real SDK still moves the servo it reads back, and torque off
    holds it where it is."""
    from drivers.dynamixel import DynamixelArms

    config = load_config()
    with EmulatedRobot(config, physics_process=True) as robot:
        port = next(o.split("=", 1)[1] for o in robot.port_overrides() if o.startswith("buses.dynamixel.port="))
        with DynamixelArms.from_config(config, port=port) as arms:
            start, _ = arms.read()
            goal = start + np.array([0.2, -0.2, 0.1, -0.1, 0.15, -0.15])
            arms.enable_torque()  # (which sets the goal to where the servo is)
            arms.write_positions(goal)
            assert wait_for(lambda: np.max(np.abs(arms.read()[0] - goal)) < 0.02)
            arms.disable_torque()
            held, _ = arms.read()
            arms.write_positions(start)
            steps = robot.plant.steps
            assert wait_for(lambda: robot.plant.steps > steps + 100)  # five arm steps at least
            np.testing.assert_allclose(arms.read()[0], held, atol=0.005)  # torque off: no motion toward the goal
