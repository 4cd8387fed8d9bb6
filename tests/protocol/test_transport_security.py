"""Mutual TLS and access control over real zenoh sessions on loopback (issue 17 item 5).

Certificates are generated at test time (two CAs: the mission's and an impostor's)."""

from __future__ import annotations

import json
import os
import socket
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import zenoh

from protocol.config import ConfigError
from protocol.transport_security import (
    AccessConfig,
    Pki,
    SecurityConfig,
    apply_to,
    check_security,
    generate_pki,
    zenoh_entries,
)

MISSION = "m"


def _port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@pytest.fixture(scope="module")
def pki(tmp_path_factory: pytest.TempPathFactory) -> tuple[Pki, Pki]:
    base = tmp_path_factory.mktemp("pki")
    mission = generate_pki(base / "mission", ["gcs", "robot-1", "visitor"])
    impostor = generate_pki(base / "impostor", ["gcs", "robot-1"], ca_name="impostor CA")
    return mission, impostor


def _session(
    pki: Pki,
    cn: str,
    *,
    listen: str | None = None,
    connect: str | None = None,
    access: AccessConfig | None = None,
) -> Any:
    cfg = zenoh.Config()
    cfg.insert_json5("mode", '"peer"')
    cfg.insert_json5("scouting/multicast/enabled", "false")
    cfg.insert_json5("listen/endpoints", json.dumps([listen] if listen else []))
    cfg.insert_json5("connect/endpoints", json.dumps([connect] if connect else []))
    sec = SecurityConfig(tls=pki.tls(cn), access=access)
    apply_to(cfg, zenoh_entries(sec, base_dir=Path("/"), mission=MISSION))
    return zenoh.open(cfg)


class _Gcs:
    """The enforcing node: listens on TLS, hears robot 1's uplink."""

    def __init__(self, pki: Pki, access: AccessConfig | None) -> None:
        self.endpoint = f"tls/127.0.0.1:{_port()}"
        self.session = _session(pki, "gcs", listen=self.endpoint, access=access)
        self.heard: list[tuple[str, bytes]] = []
        self.sub = self.session.declare_subscriber(
            f"magic/{MISSION}/robot/*/*/*",
            lambda s: self.heard.append((str(s.key_expr), s.payload.to_bytes())),
        )


@pytest.fixture()
def gcs(pki: tuple[Pki, Pki]) -> Iterator[_Gcs]:
    node = _Gcs(pki[0], AccessConfig(robots={"robot-1": 1}))
    yield node
    node.session.close()


def _wait(pred: Any, timeout_s: float = 5.0) -> bool:
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        if pred():
            return True
        time.sleep(0.05)
    return pred()


def test_a_certified_robot_is_heard_and_an_impostor_is_not(pki: tuple[Pki, Pki], gcs: _Gcs) -> None:
    mission, impostor = pki
    robot = _session(mission, "robot-1", connect=gcs.endpoint)
    fake = _session(impostor, "robot-1", connect=gcs.endpoint)  # right name, wrong CA
    try:
        up = f"magic/{MISSION}/robot/1/up/pose_node"
        assert _wait(lambda: (robot.put(up, b"robot"), any(k == up for k, _ in gcs.heard))[1])
        for _ in range(10):
            fake.put(up, b"impostor")
            time.sleep(0.05)
        time.sleep(0.5)
        assert {p for _, p in gcs.heard} == {b"robot"}
    finally:
        robot.close()
        fake.close()


def test_a_robot_cannot_publish_tasks_and_a_stranger_cannot_read(
    pki: tuple[Pki, Pki], gcs: _Gcs
) -> None:
    mission, _ = pki
    robot = _session(mission, "robot-1", connect=gcs.endpoint)
    visitor = _session(mission, "visitor", connect=gcs.endpoint)  # our CA, on no roster
    seen_by_visitor: list[bytes] = []
    vsub = visitor.declare_subscriber(
        f"magic/{MISSION}/**", lambda s: seen_by_visitor.append(s.payload.to_bytes())
    )
    seen_by_robot: list[str] = []
    rsub = robot.declare_subscriber(
        f"magic/{MISSION}/robot/1/down/*", lambda s: seen_by_robot.append(str(s.key_expr))
    )
    try:
        task = f"magic/{MISSION}/robot/1/down/task"
        assert _wait(lambda: (gcs.session.put(task, b"gcs task"), task in seen_by_robot)[1])
        for _ in range(10):
            robot.put(task, b"forged task")  # a robot sends itself a task through the GCS
            visitor.put(f"magic/{MISSION}/robot/1/up/pose_node", b"visitor")
            time.sleep(0.05)
        time.sleep(0.5)
        assert all(p != b"forged task" for _, p in gcs.heard)  # it never reached the GCS
        assert all(p != b"visitor" for _, p in gcs.heard)
        assert b"gcs task" not in seen_by_visitor  # the GCS's traffic stays unread
    finally:
        vsub.undeclare()
        rsub.undeclare()
        robot.close()
        visitor.close()


def test_missing_files_and_open_keys_are_refused(pki: tuple[Pki, Pki], tmp_path: Path) -> None:
    mission, _ = pki
    good = SecurityConfig(tls=mission.tls("gcs"))
    check_security(good, base_dir=tmp_path, source="sec.yaml")
    missing = SecurityConfig(
        tls=mission.tls("gcs").__class__(
            ca_certificate="nope.pem",
            certificate=str(mission.certificates["gcs"][0]),
            private_key=str(mission.certificates["gcs"][1]),
        )
    )
    with pytest.raises(ConfigError, match=r"sec.yaml.*tls.ca_certificate.*no such file"):
        check_security(missing, base_dir=tmp_path, source="sec.yaml")
    key = mission.certificates["visitor"][1]
    os.chmod(key, 0o644)
    try:
        with pytest.raises(ConfigError, match="readable by others"):
            check_security(
                SecurityConfig(tls=mission.tls("visitor")), base_dir=tmp_path, source="sec.yaml"
            )
    finally:
        os.chmod(key, 0o600)


def test_the_example_config_loads_once_its_certificates_exist(tmp_path: Path) -> None:
    from protocol.config import config_path
    from protocol.transport_security import load_security

    example = config_path("example", "security")
    (tmp_path / "sec.yaml").write_text(example.read_text())
    with pytest.raises(ConfigError, match=r"tls.ca_certificate: no such file"):
        load_security(tmp_path / "sec.yaml")
    generate_pki(tmp_path / "pki", ["gcs"])
    config, base = load_security(tmp_path / "sec.yaml")
    assert base == tmp_path and config.access is not None
    entries = zenoh_entries(config, base_dir=base, mission="m")
    assert entries["transport/link/tls"]["enable_mtls"] is True
    assert entries["access_control"]["default_permission"] == "deny"


def _security_yaml(path: Path, pki: Pki, cn: str, access: str = "") -> Path:
    cert, key = pki.certificates[cn]
    path.write_text(
        f"tls:\n  ca_certificate: {pki.ca_certificate}\n  certificate: {cert}\n"
        f"  private_key: {key}\n" + access
    )
    return path


def test_the_radio_link_runs_over_mutual_tls(pki: tuple[Pki, Pki], tmp_path: Path) -> None:
    from protocol.link import Link, LinkConfig
    from protocol.messages import PoseNode

    mission, impostor = pki
    endpoint = f"tls/127.0.0.1:{_port()}"
    access = "access:\n  robots: {robot-1: 1}\n"
    gcs_sec = _security_yaml(tmp_path / "gcs.yaml", mission, "gcs", access)
    robot_sec = _security_yaml(tmp_path / "robot.yaml", mission, "robot-1")
    fake_sec = _security_yaml(tmp_path / "fake.yaml", impostor, "robot-1")
    node = PoseNode(0, 0.0, (0.0, 0.0, 0.0), (0.0, 0.0, 0.0), (1e-4, 0, 0, 1e-4, 0, 1e-5))
    with Link(LinkConfig(listen=(endpoint,), security_file=str(gcs_sec)), mission=MISSION) as g:
        gcs = g.gcs_endpoint()
        fake_cfg = LinkConfig(listen=(), connect=(endpoint,), security_file=str(fake_sec))
        with Link(fake_cfg, mission=MISSION) as f:
            f.robot_endpoint(1).send(node)
            assert gcs.recv(timeout_s=2.0) is None  # an impostor is never heard
        robot_cfg = LinkConfig(listen=(), connect=(endpoint,), security_file=str(robot_sec))
        with Link(robot_cfg, mission=MISSION) as r:
            r.robot_endpoint(1).send(node)
            got = gcs.recv(timeout_s=10.0)
    assert got is not None and got[0] == 1 and isinstance(got[1], PoseNode)


def test_security_is_off_unless_asked_and_checked_when_asked(tmp_path: Path) -> None:
    import argparse

    from protocol.process_cli import add_link_arguments, link_config
    from protocol.radio import RadioConfig

    parser = argparse.ArgumentParser(exit_on_error=False)
    add_link_arguments(parser)
    assert link_config(RadioConfig(), parser.parse_args([])).security_file == ""
    with pytest.raises(argparse.ArgumentError, match="missing.yaml: cannot read"):
        parser.parse_args(["--security", str(tmp_path / "missing.yaml")])
