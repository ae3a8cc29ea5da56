"""The Fast DDS profile and the safe defaults every entry point applies."""

from __future__ import annotations

import os
import subprocess
import sys
import xml.etree.ElementTree as ET

import numpy as np
import pytest
from sensor_msgs.msg import PointCloud2

from conftest import spin_until
from terrain_ros.conversions import cloud_to_xyz
from terrain_ros.env import config_path, safe_env
from terrain_ros.qos import SENSOR_QOS

PUBLISHER = '''
import time, numpy as np, rclpy
import terrain_ros
from terrain_ros.conversions import xyz_to_cloud
from terrain_ros.qos import SENSOR_QOS
from sensor_msgs.msg import PointCloud2
rclpy.init()
node = rclpy.create_node('big_cloud_pub')
pub = node.create_publisher(PointCloud2, '/big_cloud', SENSOR_QOS)
pts = np.random.default_rng(7).normal(size=(480, 640, 3)).astype(np.float32)
pts[::7, ::5] = np.nan
msg = xyz_to_cloud(pts, 'camera_optical', 1.0)
for _ in range(150):
    pub.publish(msg)
    time.sleep(0.1)
'''


def test_safe_env_defaults_and_respects_user_values():
    env = safe_env({})
    assert env['ROS_AUTOMATIC_DISCOVERY_RANGE'] == 'LOCALHOST'
    assert env['FASTRTPS_DEFAULT_PROFILES_FILE'] == str(config_path('fastdds.xml'))
    user = safe_env({'ROS_AUTOMATIC_DISCOVERY_RANGE': 'SUBNET'})
    assert user['ROS_AUTOMATIC_DISCOVERY_RANGE'] == 'SUBNET'


@pytest.mark.parametrize('name', ['fastdds.xml', 'fastdds_network.xml'])
def test_profiles_have_a_shm_segment_for_640x480_clouds(name):
    ns = {'f': 'http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles'}
    root = ET.parse(config_path(name)).getroot()
    seg = root.find('.//f:transport_descriptor[f:type="SHM"]/f:segment_size', ns)
    # An organized xyz cloud of 640x480 float32 is 3.7 MB; the segment holds several.
    assert int(seg.text) >= 4 * 640 * 480 * 12
    udp_whitelist = root.findall('.//f:transport_descriptor[f:type="UDPv4"]'
                                 '/f:interfaceWhiteList/f:address', ns)
    if name == 'fastdds.xml':
        assert [a.text for a in udp_whitelist] == ['127.0.0.1']
    else:
        assert udp_whitelist == []


@pytest.mark.graph
def test_a_640x480_best_effort_cloud_crosses_processes_intact(ros_context, executor):
    from rclpy.node import Node
    proc = subprocess.Popen([sys.executable, '-c', PUBLISHER], env=dict(os.environ))
    try:
        node = Node('big_cloud_sub', context=ros_context)
        got = []
        node.create_subscription(PointCloud2, '/big_cloud', got.append, SENSOR_QOS)
        executor.add_node(node)
        assert spin_until(executor, lambda: got, timeout_s=12.0), 'no 640x480 cloud arrived'
    finally:
        proc.kill()
        proc.wait()
    pts = np.random.default_rng(7).normal(size=(480, 640, 3)).astype(np.float32)
    pts[::7, ::5] = np.nan
    np.testing.assert_array_equal(cloud_to_xyz(got[0]), pts)
