"""Bench part of ``magic bench loops``: replay of real CARMEN logs through the GCS (issue 7).

Both logs go through :func:`mission.replay.run_replay` exactly as ``magic replay`` does (pose
nodes every 0.5 m or 15 deg, 10 cm scan grids, the GroundStation's loop closing and iSAM2):

- ``dpslam_loop5_closures``: automatic loop closures accepted on the raw Duke DP-SLAM log
  (its own wheel odometry; no reference poses exist). The Duke robot's odometry is worse than
  our robot's model: its heading drifts about 21 deg over the 56 m loop (10 rad of turning;
  measured against the closed-loop estimate), where the model's sigma is about 4 deg, so the
  replay states sigmas :data:`DUKE_SIGMA_SCALE` times the model's. Its map is written as an
  image, ``dpslam_loop5/map.png`` in ``mission.bench.output_dir("loops_replay")``, with the
  PGM + YAML, ``summary.json`` and ``poses.txt``.
- ``intel_relations_trans_err_m`` / ``intel_relations_rot_err_deg``: mean translation and
  rotation error of Kuemmerle et al.'s relations that fall on nodes, for the corrected Intel
  log with odometry noise added (``NOISE_SCALE`` times the pose-node model, seed ``SEED``).
  Also reported: the same for odometry alone (the baseline), how many relations matched
  (``intel_relations_matched``), the Intel ATE against the corrected poses with and without
  the GCS, closures and false closures (off the corrected poses by more than 0.5 m or 5 deg),
  and the wall time of each replay.

``--quick`` replays the same logs (the metrics are defined on the whole logs). Each
``GroundStation.step`` gets :data:`STEP_BUDGET_S`, a budget that does not bind on this
machine even when it is busy (the loop closer's match rate is limited per mission second, so
the result does not depend on the load); the replays take about 10 s and 15 s of CPU.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

from gcs.replay.carmen_log import read_carmen_log
from gcs.replay.relations import read_relations
from mission.bench import BenchError, output_dir
from mission.replay import OdometryNoiseConfig, ReplayConfig, ReplayResult, run_replay

__all__ = ["DUKE_SIGMA_SCALE", "NOISE_SCALE", "SEED", "STEP_BUDGET_S", "run"]

LASER = Path(__file__).resolve().parents[2] / ".." / "shared" / "datasets" / "laser"
NOISE_SCALE = 1.0
SEED = 1
DUKE_SIGMA_SCALE = 4.0
STEP_BUDGET_S = 10.0


def _file(name: str) -> Path:
    path = LASER / name
    if not path.is_file():
        raise BenchError(f"dataset {path} not found (loops_replay needs ../shared/datasets/laser)")
    return path


def _replay(
    name: str,
    log_name: str,
    config: ReplayConfig,
    progress: Callable[[str], None],
    relations_name: str | None = None,
) -> ReplayResult:
    log = read_carmen_log(_file(log_name))
    relations = read_relations(_file(relations_name)) if relations_name else None
    step = max(len(log) // 5, 1)
    marks = [0]

    def report(done: int, total: int, text: str) -> None:
        if done - marks[0] >= step or done == total:
            marks[0] = done
            progress(f"replay {name}: {done}/{total} scans, {text}")

    result = run_replay(
        log,
        config=config,
        relations=relations,
        out_dir=output_dir("loops_replay") / name,
        progress=report,
    )
    for kind, path in result.files.items():
        progress(f"replay {name}: {kind} written to {path}")
    return result


def run(*, quick: bool, progress: Callable[[str], None]) -> dict[str, float]:
    del quick  # both logs are short enough to replay whole
    duke_config = ReplayConfig(odometry_sigma_scale=DUKE_SIGMA_SCALE, step_budget_s=STEP_BUDGET_S)
    duke = _replay("dpslam_loop5", "dpslam_loop5.log", duke_config, progress)
    noisy = ReplayConfig(
        noise=OdometryNoiseConfig(scale=NOISE_SCALE, seed=SEED), step_budget_s=STEP_BUDGET_S
    )
    intel = _replay("intel", "intel-corrected.log.gz", noisy, progress, "intel.relations")
    if intel.relations is None or intel.relations_odometry is None or intel.ate is None:
        raise BenchError("intel replay: no relation fell on a node, or no reference poses")
    assert intel.relations_matched is not None and intel.ate_odometry is not None
    return {
        "dpslam_loop5_closures": float(duke.loop_closures),
        "dpslam_loop5_nodes": float(len(duke.scans)),
        "dpslam_loop5_replay_s": duke.wall_s,
        "intel_relations_trans_err_m": intel.relations.trans_mean_m,
        "intel_relations_rot_err_deg": intel.relations.rot_mean_deg,
        "intel_relations_odometry_trans_err_m": intel.relations_odometry.trans_mean_m,
        "intel_relations_odometry_rot_err_deg": intel.relations_odometry.rot_mean_deg,
        "intel_relations_matched": float(len(intel.relations_matched)),
        "intel_ate_rmse_m": intel.ate.rmse_m,
        "intel_ate_odometry_rmse_m": intel.ate_odometry.rmse_m,
        "intel_closures": float(intel.loop_closures),
        "intel_false_closures": float(intel.false_closures or 0),
        "intel_nodes": float(len(intel.scans)),
        "intel_replay_s": intel.wall_s,
    }
