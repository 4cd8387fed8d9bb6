"""The global map: rasterization of the pose graph into an occupancy grid (paper 4.8) and its
export for planners and operators."""
