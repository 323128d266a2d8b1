"""ROS 2 interop: the ``racecav ros2`` mirror (rmw_zenoh / zenoh-bridge-ros2dds) and the ROS 2
message definitions, CDR conversion and naming shared with ``racecav record`` and ``racecav viz``.

Needs the ``ros2`` extra (rosbags: CDR and RIHS01 type hashes, no ROS installation)."""
