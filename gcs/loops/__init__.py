"""Loop closing: candidate search, correlative matching, cycle validation (paper 4.3.3, 4.5)."""
