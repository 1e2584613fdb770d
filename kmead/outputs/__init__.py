"""What leaves the daemon: UDP datagrams, Zenoh and ROS 2, the CSV log, snapshots,
the data directory, whole-run totals."""
