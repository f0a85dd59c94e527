"""ROS 2 fixtures shared by the integration tests that use rclpy.

A module sets ``DOMAIN_ID`` (its own, so developers' and CI's test runs do not hear each other)
and uses the ``context`` fixture; subprocesses get the same DDS settings from ``ros_env``.
"""

from __future__ import annotations

import os

import pytest


@pytest.fixture(scope="module")
def ros_env(request) -> dict[str, str]:
    """Environment for a ROS 2 process on the module's ``DOMAIN_ID``, discovery on localhost only."""
    env = dict(os.environ, ROS_DOMAIN_ID=str(request.module.DOMAIN_ID), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    env.pop("ROS_LOCALHOST_ONLY", None)
    return env


@pytest.fixture(scope="module")
def context(request, ros_env):
    """An rclpy context on the module's ``DOMAIN_ID``, shut down after the module."""
    rclpy = pytest.importorskip("rclpy")
    os.environ.update(ros_env)
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=request.module.DOMAIN_ID)
    yield ctx
    rclpy.try_shutdown(context=ctx)
