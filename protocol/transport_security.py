"""Secured transport across hosts: zenoh over mutual TLS with access control (issue 17 item 5).

A multi-host mission (DESIGN section 4) crosses networks the team does not own. Every process
then speaks zenoh over TLS with mutual authentication: each holds a certificate signed by the
mission's certificate authority (CA) and refuses peers whose certificate is not, so a peer
without the right certificate cannot connect at all, let alone publish tasks or read the map.
On the node that enforces it (the GCS, which robots connect to, or a router), access control
then limits what each authenticated peer may do by its certificate's common name (CN):

=====================  ================================================================
CN                     may
=====================  ================================================================
``gcs``                everything of the mission
``sim``                its clock, sensors, grants and truth; hear the radio (metering)
``robot-<id>``         send its uplink and simulator commands; hear its downlink, the
                       broadcast, the clock, its sensors and grants
``operator-<name>``    query and hear the GCS's state topics (console and views)
=====================  ================================================================

The config (YAML, :class:`SecurityConfig`; ``configs/security/example.yaml`` documents it)
names the CA, this process's certificate and key, and, on the enforcing node, the roster of
CNs per role. :func:`zenoh_entries` turns it into zenoh configuration entries;
:func:`generate_pki` makes a CA and certificates (for tests and first deployments, with the
``cryptography`` library). A private key readable by others is refused.
"""

from __future__ import annotations

import datetime
import ipaddress
import json
import os
import stat
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import msgspec

from protocol.config import ConfigError

__all__ = [
    "AccessConfig",
    "Pki",
    "SecurityConfig",
    "TlsConfig",
    "access_control_entry",
    "apply_to",
    "check_security",
    "generate_pki",
    "load_security",
    "zenoh_entries",
]


class TlsConfig(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    """This process's side of mutual TLS. Paths are relative to the config file's directory.

    ``ca_certificate``: the mission CA (PEM) every peer's certificate must chain to;
    ``certificate`` / ``private_key``: this process's (PEM; the key readable by its owner
    only); ``verify_name``: also check that a listener's certificate names the host dialled
    (off by default: missions dial addresses, and the CA is the mission's own).
    """

    ca_certificate: str
    certificate: str
    private_key: str
    verify_name: bool = False


class AccessConfig(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    """The roster the enforcing node grants by (module table): certificate CNs per role.
    A peer whose CN is on no list may do nothing."""

    gcs: tuple[str, ...] = ("gcs",)
    sim: tuple[str, ...] = ("sim",)
    robots: dict[str, int] = {}  # CN -> robot id
    operators: tuple[str, ...] = ()


class SecurityConfig(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    """``tls`` for every process; ``access`` only on the node that enforces it."""

    tls: TlsConfig
    access: AccessConfig | None = None


# ------------------------------------------------------------------------- zenoh entries


def _resolve(base_dir: Path, p: str) -> Path:
    path = Path(p)
    return path if path.is_absolute() else base_dir / path


def check_security(config: SecurityConfig, *, base_dir: Path, source: str) -> None:
    """Refuse, naming the file, a missing certificate or key or a key others can read."""
    tls = config.tls
    for key, value in (
        ("tls.ca_certificate", tls.ca_certificate),
        ("tls.certificate", tls.certificate),
        ("tls.private_key", tls.private_key),
    ):
        path = _resolve(base_dir, value)
        if not path.is_file():
            raise ConfigError(source, key, f"no such file: {path}")
    key_path = _resolve(base_dir, tls.private_key)
    mode = stat.S_IMODE(key_path.stat().st_mode)
    if mode & 0o077:
        raise ConfigError(
            source,
            "tls.private_key",
            f"{key_path} is readable by others (mode {mode:o}); run: chmod 600 {key_path}",
        )


def load_security(path: str | Path) -> tuple[SecurityConfig, Path]:
    """Read and check a security config file; returns it and the directory its paths are
    relative to. Problems raise :class:`ConfigError` naming the file and key."""
    from protocol.config import load_config

    p = Path(path)
    config = load_config(p, SecurityConfig)
    check_security(config, base_dir=p.parent, source=str(p))
    return config, p.parent


def zenoh_entries(config: SecurityConfig, *, base_dir: Path, mission: str) -> dict[str, Any]:
    """``{zenoh config path: value}`` to insert (``Config.insert_json5(path, json.dumps(v))``)
    for mutual TLS and, when ``config.access`` is set, access control for ``mission``."""
    tls = config.tls
    key = str(_resolve(base_dir, tls.private_key))
    cert = str(_resolve(base_dir, tls.certificate))
    entries: dict[str, Any] = {
        "transport/link/tls": {
            "root_ca_certificate": str(_resolve(base_dir, tls.ca_certificate)),
            "enable_mtls": True,
            "listen_private_key": key,
            "listen_certificate": cert,
            "connect_private_key": key,
            "connect_certificate": cert,
            "verify_name_on_connect": tls.verify_name,
        }
    }
    if config.access is not None:
        entries["access_control"] = access_control_entry(config.access, mission)
    return entries


# Message kinds by what a grant means, seen from the enforcing node: what a subject sends us
# is ingress, what we send it is egress (zenoh's access-control model). Data is limited to the
# grant's keys; declarations of interest flowing to the subject (our subscribers, queryables,
# liveliness interest) are allowed on the whole mission, since a declaration on a wildcard
# (the GCS hears ``robot/*/up/*``) is not included in one robot's keys, and a declaration
# carries no data.
_DATA_IN = ("put", "delete", "liveliness_token")
_DATA_OUT = ("put", "delete", "liveliness_token")
_INTEREST = ("declare_subscriber", "declare_liveliness_subscriber", "liveliness_query")
_PUBLISH = (("ingress", _DATA_IN),)
_SUBSCRIBE = (("ingress", _INTEREST), ("egress", _DATA_OUT))
_QUERY = (("ingress", ("query",)), ("egress", ("reply",)))
_SERVE = (("ingress", ("reply", "declare_queryable")), ("egress", ("query",)))
_HEAR_INTEREST = (("egress", _INTEREST + ("declare_queryable",)),)


def _grants(mission: str, access: AccessConfig) -> list[tuple[str, list[str], tuple[Any, ...]]]:
    """``(subject CN, key expressions, what)`` per grant."""
    root = f"magic/{mission}"
    out: list[tuple[str, list[str], tuple[Any, ...]]] = []
    everyone = (*access.gcs, *access.sim, *sorted(access.robots), *access.operators)
    for cn in everyone:
        out.append((cn, [f"{root}/**"], _HEAR_INTEREST))
    for cn in access.gcs:
        out.append((cn, [f"{root}/**"], _PUBLISH + _SUBSCRIBE + _QUERY + _SERVE))
    for cn in access.sim:
        out.append((cn, [f"{root}/sim/**"], _PUBLISH + _SUBSCRIBE + _SERVE))
        out.append((cn, [f"{root}/robot/**", f"{root}/broadcast/**"], _SUBSCRIBE))
    for cn, rid in sorted(access.robots.items()):
        out.append(
            (cn, [f"{root}/robot/{rid}/up/**", f"{root}/sim/robot/{rid}/commands"], _PUBLISH)
        )
        hears = [
            f"{root}/robot/{rid}/down/**",
            f"{root}/broadcast/down/**",
            f"{root}/sim/clock",
            f"{root}/sim/robot/{rid}/sensors",
            f"{root}/sim/radio/**",
        ]
        out.append((cn, hears, _SUBSCRIBE))
    for cn in access.operators:
        out.append((cn, [f"{root}/gcs/**"], _SUBSCRIBE + _QUERY))
    return out


def access_control_entry(access: AccessConfig, mission: str) -> dict[str, Any]:
    """zenoh's ``access_control`` object for ``mission``: deny by default, then the grants."""
    rules: list[dict[str, Any]] = []
    subjects: list[dict[str, Any]] = []
    policies: list[dict[str, Any]] = []
    subject_of: dict[str, str] = {}
    for i, (cn, key_exprs, what) in enumerate(_grants(mission, access)):
        if cn not in subject_of:
            subject_of[cn] = f"s{len(subject_of)}"
            subjects.append({"id": subject_of[cn], "cert_common_names": [cn]})
        ids = []
        for j, (flow, messages) in enumerate(what):
            rule_id = f"r{i}_{j}"
            rules.append(
                {
                    "id": rule_id,
                    "messages": list(messages),
                    "flows": [flow],
                    "permission": "allow",
                    "key_exprs": key_exprs,
                }
            )
            ids.append(rule_id)
        policies.append({"rules": ids, "subjects": [subject_of[cn]]})
    return {
        "enabled": True,
        "default_permission": "deny",
        "rules": rules,
        "subjects": subjects,
        "policies": policies,
    }


def apply_to(zenoh_config: Any, entries: dict[str, Any]) -> None:
    """Insert :func:`zenoh_entries` into a ``zenoh.Config``."""
    for path, value in entries.items():
        zenoh_config.insert_json5(path, json.dumps(value))


# ------------------------------------------------------------------------- certificates


@dataclass(frozen=True)
class Pki:
    """Files :func:`generate_pki` wrote: the CA certificate and, per CN, certificate and key."""

    ca_certificate: Path
    certificates: dict[str, tuple[Path, Path]]

    def tls(self, cn: str) -> TlsConfig:
        cert, key = self.certificates[cn]
        return TlsConfig(
            ca_certificate=str(self.ca_certificate), certificate=str(cert), private_key=str(key)
        )


def generate_pki(
    out_dir: Path, common_names: list[str], *, days: int = 30, ca_name: str = "magic-recon CA"
) -> Pki:
    """A new CA and a certificate per CN (ECDSA P-256) under ``out_dir``; keys mode 0600.
    Every certificate names ``localhost`` and ``127.0.0.1`` too, for ``verify_name``."""
    from cryptography import x509
    from cryptography.hazmat.primitives import hashes, serialization
    from cryptography.hazmat.primitives.asymmetric import ec
    from cryptography.x509.oid import NameOID

    out_dir.mkdir(parents=True, exist_ok=True)
    now = datetime.datetime.now(datetime.UTC)
    valid_from, valid_to = now - datetime.timedelta(minutes=5), now + datetime.timedelta(days=days)

    def write_key(path: Path, key: ec.EllipticCurvePrivateKey) -> None:
        data = key.private_bytes(
            serialization.Encoding.PEM,
            serialization.PrivateFormat.PKCS8,
            serialization.NoEncryption(),
        )
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
        with os.fdopen(fd, "wb") as f:
            f.write(data)
        os.chmod(path, 0o600)

    ca_key = ec.generate_private_key(ec.SECP256R1())
    ca_subject = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, ca_name)])
    ca_cert = (
        x509.CertificateBuilder()
        .subject_name(ca_subject)
        .issuer_name(ca_subject)
        .public_key(ca_key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(valid_from)
        .not_valid_after(valid_to)
        .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
        .add_extension(
            x509.KeyUsage(
                digital_signature=True,
                content_commitment=False,
                key_encipherment=False,
                data_encipherment=False,
                key_agreement=False,
                key_cert_sign=True,
                crl_sign=True,
                encipher_only=False,
                decipher_only=False,
            ),
            critical=True,
        )
        .sign(ca_key, hashes.SHA256())
    )
    ca_path = out_dir / "ca.pem"
    ca_path.write_bytes(ca_cert.public_bytes(serialization.Encoding.PEM))
    write_key(out_dir / "ca.key", ca_key)
    certs: dict[str, tuple[Path, Path]] = {}
    for cn in common_names:
        key = ec.generate_private_key(ec.SECP256R1())
        cert = (
            x509.CertificateBuilder()
            .subject_name(x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, cn)]))
            .issuer_name(ca_subject)
            .public_key(key.public_key())
            .serial_number(x509.random_serial_number())
            .not_valid_before(valid_from)
            .not_valid_after(valid_to)
            .add_extension(
                x509.SubjectAlternativeName(
                    [
                        x509.DNSName("localhost"),
                        x509.IPAddress(ipaddress.ip_address("127.0.0.1")),
                    ]
                ),
                critical=False,
            )
            .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
            .sign(ca_key, hashes.SHA256())
        )
        cert_path, key_path = out_dir / f"{cn}.pem", out_dir / f"{cn}.key"
        cert_path.write_bytes(cert.public_bytes(serialization.Encoding.PEM))
        write_key(key_path, key)
        certs[cn] = (cert_path, key_path)
    return Pki(ca_path, certs)
