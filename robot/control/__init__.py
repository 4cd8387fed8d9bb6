"""Control and safety: path following, keep-out disks, stuck detection, traversability."""
