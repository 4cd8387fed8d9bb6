"""Inertially-aided odometry and pose nodes in the private frame (paper 4.3.1, 4.2)."""
