"""Ground-control station: global estimation, loop closing, maps, tasks, operator console."""
