"""Task execution: what the GCS asks, turned into goals and status reports (paper 5.1)."""
