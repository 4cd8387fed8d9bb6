"""Terrain classification (paper 5.3) and the vertical-surface grid for loop closing (4.3.3)."""
