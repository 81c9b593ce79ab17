"""The ``ros`` marker is kept: a test without it cannot start DDS (conftest.NO_DDS_DOMAIN)."""

import os

import pytest

from conftest import NO_DDS_DOMAIN, ros_env


def test_a_test_without_the_ros_marker_cannot_start_dds(erva):
    # This test has no `ros` marker: it runs in NO_DDS_DOMAIN, as do the processes it starts.
    assert os.environ['ROS_DOMAIN_ID'] == ros_env()['ROS_DOMAIN_ID'] == str(NO_DDS_DOMAIN)
    rclpy = pytest.importorskip('rclpy')
    context = rclpy.Context()
    rclpy.init(args=[], context=context)
    try:
        with pytest.raises(RuntimeError, match='mark it @pytest.mark.ros'):
            rclpy.create_node('probe', context=context)
    finally:
        rclpy.shutdown(context=context)
    proc = erva('run', '--duration', 0.2, '--no-record')
    assert proc.returncode == 2
    assert proc.stderr.startswith(f"erva run: error: ROS_DOMAIN_ID='{NO_DDS_DOMAIN}' is not a "
                                  'ROS domain'), proc.stderr


@pytest.mark.ros
def test_a_test_with_the_marker_runs_in_the_runs_domain():
    from conftest import ROS_DOMAIN_ID
    assert os.environ['ROS_DOMAIN_ID'] == ros_env()['ROS_DOMAIN_ID'] == str(ROS_DOMAIN_ID)
