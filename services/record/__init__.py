"""Recording and replaying runs: ``racecav record`` writes one MCAP file per run (raw bus samples
plus ROS 2 copies), ``racecav replay`` feeds its scans back to a controller and compares the
commands. Needs the ``record`` extra (mcap, rosbags)."""
