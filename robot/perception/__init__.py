"""On-robot object detection (paper 5.2) and teammate fiducials (4.3.2)."""
