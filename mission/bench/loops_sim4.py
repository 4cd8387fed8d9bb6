"""Bench part of ``magic bench loops``: the 4-robot simulated team mapping run (issue 7).

``sim4_false_closures``: accepted automatic loop closures whose relative pose is off the
truth by more than 0.5 m or 5 deg; ``sim4_ate_rmse_m``: RMSE of every node's posterior position
after a rigid alignment with the truth. Also reported: how many closures (and across robots),
and the ATE before the first closure (odometry and operator start hints only), the baseline.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from mission.team_mapping import TeamMappingConfig, run_team_mapping


def run(*, quick: bool, progress: Callable[[str], None]) -> dict[str, float]:
    config = TeamMappingConfig(duration_s=150.0 if quick else 300.0)
    report, _ = run_team_mapping(config, progress=progress)
    errors = np.asarray(report.closure_errors_m or [np.nan])
    return {
        "sim4_false_closures": float(report.false_closures),
        "sim4_ate_rmse_m": report.ate_rmse_m,
        "sim4_ate_rmse_before_closures_m": report.ate_rmse_prior_m,
        "sim4_closures": float(report.closures),
        "sim4_cross_robot_closures": float(report.cross_robot_closures),
        "sim4_closure_err_p95_m": float(np.nanpercentile(errors, 95)) if report.closures else 0.0,
        "sim4_nodes": float(report.nodes),
        "sim4_rtf": report.mission_s / max(report.wall_s, 1e-9),
    }
