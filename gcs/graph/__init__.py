"""Global pose graph of every robot (paper 4.2, 4.6, 4.7): GTSAM factors, orderings, init, edits."""
