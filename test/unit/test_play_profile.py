"""``play``'s Fast DDS writer profile: written when the user has none, never over theirs."""

from __future__ import annotations

import os
import xml.etree.ElementTree as ET

from rtabmap_ros2.ros.play import FASTDDS_PROFILE_VARIABLES, WRITER_HEARTBEAT_S, use_writer_heartbeat_profile

NAMESPACE = "{http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles}"


def test_profile_sets_the_default_writer_heartbeat():
    environ: dict[str, str] = {}
    path = use_writer_heartbeat_profile(environ)
    try:
        assert path is not None and all(environ[name] == path for name in FASTDDS_PROFILE_VARIABLES)
        writer = ET.parse(path).getroot().find(f"{NAMESPACE}data_writer")
        assert writer.get("is_default_profile") == "true"
        period = writer.find(f"{NAMESPACE}times/{NAMESPACE}heartbeatPeriod")
        seconds = int(period.find(f"{NAMESPACE}sec").text) + int(period.find(f"{NAMESPACE}nanosec").text) / 1e9
        assert seconds == WRITER_HEARTBEAT_S < 3.0   # Fast DDS's default is 3 s
    finally:
        if path is not None:
            os.unlink(path)


def test_profile_keeps_the_users_configuration():
    for name in FASTDDS_PROFILE_VARIABLES:
        environ = {name: "/etc/my_fastdds.xml"}
        assert use_writer_heartbeat_profile(environ) is None
        assert environ == {name: "/etc/my_fastdds.xml"}
    environ = {"RMW_IMPLEMENTATION": "rmw_cyclonedds_cpp"}
    assert use_writer_heartbeat_profile(environ) is None
    assert environ == {"RMW_IMPLEMENTATION": "rmw_cyclonedds_cpp"}
