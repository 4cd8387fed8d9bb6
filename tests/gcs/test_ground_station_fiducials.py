"""Fiducial edges at the GCS: a sighting whose heading is too loose to be a true edge makes none
(``GroundStationConfig.fiducial_max_sigma_yaw_rad``)."""

from __future__ import annotations

import math

import numpy as np

from gcs.graph.pose_graph import Provenance
from gcs.ground_station import GroundStation, GroundStationConfig
from protocol.messages import FiducialObservation, covariance_to_upper
from protocol.se2 import compose, relative
from tests.gcs.test_ground_station import nodes_along, straight


def _station_with_tag(sigma_yaw_rad: float, **config: float) -> GroundStation:
    """Robot 0 (map) and robot 1 drive 10 nodes each; robot 1's node 6 sees robot 0's node 6
    (exact position, the tag's heading sigma ``sigma_yaw_rad``)."""
    path0, path1 = straight(10), straight(10, heading=0.4)
    seen = relative(compose(np.array([2.0, -1.0, 0.3]), path1[6]), path0[6])
    cov = covariance_to_upper(np.diag([0.02**2, 0.02**2, sigma_yaw_rad**2]))
    tag = FiducialObservation(6, 6.0, 0, 7, tuple(seen), cov)  # type: ignore[arg-type]
    gs = GroundStation(GroundStationConfig(robots=(0, 1), **config))  # type: ignore[arg-type]
    n0, n1 = nodes_along(path0), nodes_along(path1)
    for i in range(10):
        assert gs.handle(0, n0[i], now_s=float(i)) and gs.handle(1, n1[i], now_s=float(i))
        if i == 6:
            assert gs.handle(1, tag, now_s=float(i))
        gs.step(now_s=float(i))
    return gs


def test_a_tag_whose_heading_is_loose_makes_no_edge_and_is_counted_not_rejected() -> None:
    # one face seen: the detector's heading sigma is 17 deg (19 of the full mission's 20 false
    # fiducial edges in its first 720 s were such, 5-25 deg off, positions within 0.5 m)
    assert GroundStationConfig().fiducial_max_sigma_yaw_rad == 0.0  # no bound by default
    bound = math.radians(5.0)  # as measured on the full mission
    loose = _station_with_tag(math.radians(17.2), fiducial_max_sigma_yaw_rad=bound)
    assert loose.graph.edges(Provenance.FIDUCIAL) == []
    assert loose.stats.fiducials == 0 and loose.stats.fiducials_loose_heading == 1
    assert loose.stats.rejected_total == 0  # not bad input: the robot measured what it could
    # the map robot alone is placed: robot 1 is not linked by a loose tag
    assert not loose.linked(1)
    # a tag whose heading is known to 1 deg links the two robots
    tight = _station_with_tag(math.radians(1.0), fiducial_max_sigma_yaw_rad=bound)
    (edge,) = tight.graph.edges(Provenance.FIDUCIAL)
    assert edge.key_a == tight.key_of(1, 6) and edge.key_b == tight.key_of(0, 6)
    assert tight.stats.fiducials == 1 and tight.stats.fiducials_loose_heading == 0
    assert tight.linked(1)
    pose = tight.pose_in_map(1)
    truth = compose(np.array([2.0, -1.0, 0.3]), straight(10, heading=0.4)[9])
    assert pose is not None and np.allclose(pose, truth, atol=1e-3)
    # the bound is the config's: raised above the tag's sigma, the loose tag links them too
    wide = _station_with_tag(math.radians(17.2), fiducial_max_sigma_yaw_rad=math.radians(20.0))
    assert wide.stats.fiducials == 1 and len(wide.graph.edges(Provenance.FIDUCIAL)) == 1
