"""Stream codings: pose nodes against the previous node (bounded error, no drift, small),
grids (lossless), broadcast hazard updates (quantised frames); bad bytes are refused."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from protocol.messages import (
    Hazard,
    HazardUpdate,
    ObjectKind,
    PoseNode,
    PoseNodeCoded,
    RobotFrame,
    TerrainGrid,
    TerrainGridCoded,
    encode_frame,
)
from protocol.stream_coding import (
    PoseNodeCoder,
    TerrainGridCoder,
    decode_hazard_update,
    encode_hazard_update,
)
from protocol.wire import ProtocolError


def _drive(n: int, seed: int) -> list[PoseNode]:
    rng = np.random.default_rng(seed)
    pose = np.zeros(3)
    out = []
    t = 0.0
    for i in range(n):
        step = np.array([rng.uniform(0.9, 1.1), rng.normal(0, 0.02), rng.normal(0, 0.05)])
        if i == 0:
            step[:] = 0.0
        c, s = math.cos(pose[2]), math.sin(pose[2])
        pose = pose + np.array([c * step[0] - s * step[1], s * step[0] + c * step[1], step[2]])
        t += float(rng.uniform(0.9, 1.6))
        sxy = 0.03 * math.sqrt(max(step[0], 1e-3)) + 0.005
        cov = (sxy**2, 1e-5, -2e-6, 0.3 * sxy**2, 1e-6, 4e-4)
        out.append(PoseNode(i, t, tuple(pose), tuple(step), cov))  # type: ignore[arg-type]
    return out


def test_pose_nodes_decode_within_half_a_quantum_with_no_drift_and_are_small() -> None:
    sender, receiver = PoseNodeCoder(), PoseNodeCoder()
    nodes = _drive(3000, seed=1)
    sizes = []
    for seq, node in enumerate(nodes, 1):
        coded = sender.encode(node)
        assert isinstance(coded, PoseNodeCoded)
        sizes.append(len(encode_frame(seq, coded)))
        got = receiver.decode(coded)
        assert got.node_index == node.node_index
        assert abs(got.time_s - node.time_s) <= 0.5e-3 + 1e-9
        # absolute quantisation (then float32): error bounded however long the trajectory
        np.testing.assert_allclose(got.pose_in_odom[:2], node.pose_in_odom[:2], atol=1.2e-4)
        np.testing.assert_allclose(got.pose_in_odom[2], node.pose_in_odom[2], atol=6e-6)
        # exact: the GCS warps the previous grid by it to decode an inter-frame grid
        assert got.odom_delta == node.odom_delta
        np.testing.assert_allclose(got.odom_covariance, node.odom_covariance, rtol=3e-3)
        assert all(
            (a < 0) == (b < 0)
            for a, b in zip(got.odom_covariance, node.odom_covariance, strict=True)
        )
    plain = len(encode_frame(1000, nodes[1000]))
    assert plain >= 78  # the plain node (78 B at small indices)
    assert float(np.median(sizes)) <= 36, f"median coded pose node {np.median(sizes)} B"


def test_a_node_that_cannot_be_coded_goes_plain_and_both_ends_restart() -> None:
    sender, receiver = PoseNodeCoder(), PoseNodeCoder()
    nodes = _drive(20, seed=2)
    bad = PoseNode(20, 30.0, (math.nan, 0.0, 0.0), (1.0, 0.0, 0.0), (1e-3, 0, 0, 1e-3, 0, 1e-4))
    after = _drive(25, seed=3)[21:]
    for node in [*nodes, bad, *after]:
        coded = sender.encode(node)
        got = receiver.decode(coded)
        if node is bad:
            assert coded is bad and got is bad  # the GCS sees the NaN and refuses it itself
        else:
            assert isinstance(coded, PoseNodeCoded)
            assert got.odom_delta == node.odom_delta


def test_grids_round_trip_exactly_and_save_the_index_and_resolution() -> None:
    sender, receiver = TerrainGridCoder(), TerrainGridCoder()
    for i in range(50):
        grid = TerrainGrid(i + (5 if i > 30 else 0), 0.1 if i < 40 else 0.2, bytes([i]) * 20)
        coded = sender.encode(grid)
        assert receiver.decode(coded) == grid
        if 0 < i < 30:
            assert len(encode_frame(500, coded)) <= len(encode_frame(500, grid)) - 4


@settings(max_examples=60, deadline=None)
@given(data=st.binary(max_size=40))
def test_garbage_pose_bytes_are_refused_or_decode_to_a_node(data: bytes) -> None:
    try:
        node = PoseNodeCoder().decode(PoseNodeCoded(data))
    except ProtocolError as err:
        assert "PoseNodeCoded" in str(err) or "covariance" in str(err)
    else:
        assert isinstance(node, PoseNode)


def test_truncated_grid_bytes_name_the_problem() -> None:
    with pytest.raises(ProtocolError, match="TerrainGridCoded.data: truncated"):
        TerrainGridCoder().decode(TerrainGridCoded(b""))
    with pytest.raises(ProtocolError, match="no previous resolution"):
        TerrainGridCoder().decode(TerrainGridCoded(b"\x00\x00"))


def test_hazard_update_frames_are_quantised_to_a_millimetre_and_smaller() -> None:
    rng = np.random.default_rng(4)
    frames = [RobotFrame(r, tuple(rng.normal(0, 80, 3))) for r in range(100)]  # type: ignore[arg-type]
    update = HazardUpdate(12.5, [Hazard(1, ObjectKind.STATIC_OOI, (3.0, 4.0), 10.0)], frames)
    coded = encode_hazard_update(update)
    got = decode_hazard_update(coded)
    assert got.time_s == update.time_s and got.hazards == update.hazards
    assert [f.robot_id for f in got.frames] == list(range(100))
    for a, b in zip(got.frames, frames, strict=True):
        np.testing.assert_allclose(a.map_from_odom[:2], b.map_from_odom[:2], atol=6e-4)
        np.testing.assert_allclose(a.map_from_odom[2], b.map_from_odom[2], atol=6e-5)
    assert len(encode_frame(1, coded)) < 0.65 * len(encode_frame(1, update))
    # a frame that is not finite (or a repeated id): the update goes as it is
    odd = HazardUpdate(1.0, [], [RobotFrame(1, (math.inf, 0.0, 0.0))])
    assert encode_hazard_update(odd) is odd
