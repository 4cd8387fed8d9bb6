"""On-robot path planning (paper 5.4): configuration space, Dijkstra, relaxation, smoothing."""
