"""Task allocation at the GCS (paper 5.1): frontier exploration for the sensor robots, static-OOI
dispatch and idle spread for the disruptors, hostile locks, all over the trajectory graph.
Pure: state in (:class:`~gcs.tasking.allocator.TaskingState`), tasks out; the GCS node does
the IO."""
