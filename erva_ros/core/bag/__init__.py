"""Session recording in rosbag2-compatible MCAP bags, and what is built on the bags.

Layout (do-mpc-like separation; no ROS needed except where noted):

* :mod:`~erva_ros.core.bag.schemas`  -- ros2msg definitions and RIHS01 type hashes, as rosbag2
  finds them (ament index share/<pkg>/msg);
* :mod:`~erva_ros.core.bag.qos`      -- offered QoS profiles in rosbag2's YAML form;
* :mod:`~erva_ros.core.bag.metadata` -- ``metadata.yaml`` (rosbag2 bag format version 9);
* :mod:`~erva_ros.core.bag.writer`   -- the MCAP writer (profile ``ros2``, ``cdr`` messages);
* :mod:`~erva_ros.core.bag.reader`   -- reading, ``erva bag info``;
* :mod:`~erva_ros.core.bag.repair`   -- recovering a bag whose recorder was killed;
* :mod:`~erva_ros.core.bag.session`  -- bag directory names and session metadata for ``erva run``;
* :mod:`~erva_ros.session.bag.bag_report`   -- comfort, power and timing figures from a bag alone
  (figures in :mod:`~erva_ros.core.plots.bag_report`);
* :mod:`~erva_ros.ros.replay`   -- publishing a bag with its original timing (rclpy), and
  what-if runs of another controller on a recorded road;
* :mod:`~erva_ros.session.bag.reevaluate` -- feeding recorded states and previews to a fresh
  controller (determinism check);
* :mod:`~erva_ros.session.bag.offline_bag`  -- writing an offline closed-loop run as a session bag;
* :mod:`~erva_ros.ros.traffic`, :mod:`~erva_ros.session.bench.recorder_bench` -- synthetic traffic
  and the recorder benchmark (``erva bag bench``).

The recorder node itself is :mod:`erva_ros.nodes.recorder_node`.
"""

from erva_ros.core.errors import CLIError


class BagError(CLIError):
    """A bag cannot be read or written; the message is one line for the user."""
