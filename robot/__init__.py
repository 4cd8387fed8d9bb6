"""On-board autonomy: everything a robot does in its private frame ``odom/<id>`` (DESIGN 1)."""
