"""YAML configuration: typed frozen structs; every error names the file and the dotted key."""

from __future__ import annotations

from pathlib import Path

import msgspec
import pytest

from protocol.config import (
    CONFIGS_DIR,
    ConfigError,
    config_path,
    decode_config,
    load_config,
    load_config_text,
)
from protocol.radio import RadioConfig


class MatcherConfig(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    levels: int = 3
    resolution_m: float = 0.1


class ItemConfig(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    name: str
    weight: float = 1.0


class LimitsConfig(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    low: float = 0.0
    high: float = 1.0

    def __post_init__(self) -> None:
        if self.low > self.high:
            raise ValueError(f"empty range: low {self.low} is above high {self.high}")


class LoopsConfig(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    matcher: MatcherConfig = MatcherConfig()
    items: list[ItemConfig] = []
    limits: LimitsConfig = LimitsConfig()
    radios: dict[str, RadioConfig] = {}


class GcsConfig(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    loops: LoopsConfig = LoopsConfig()
    radio: RadioConfig | None = None


class MissionConfig(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    gcs: GcsConfig = GcsConfig()
    seed: int = 0


def write(tmp_path: Path, text: str, name: str = "mission.yaml") -> Path:
    path = tmp_path / name
    path.write_text(text, encoding="utf-8")
    return path


def load_error(path: Path, config_type: type = MissionConfig) -> ConfigError:
    with pytest.raises(ConfigError) as info:
        load_config(path, config_type)
    return info.value


# ----------------------------------------------------------------------------- shipped files


def test_magic2010_radio() -> None:
    radio = load_config(CONFIGS_DIR / "radio" / "magic2010.yaml", RadioConfig)
    assert radio.shared_capacity_bps / 1000 == 115.2
    assert radio.framing_overhead_bytes == 8
    assert radio == RadioConfig(shared_capacity_bps=115_200.0, framing_overhead_bytes=8)


def test_configs_dir_is_the_repository_folder() -> None:
    assert CONFIGS_DIR == Path(__file__).resolve().parents[2] / "configs"


# ----------------------------------------------------------------------------- good input


def test_nested_values_and_defaults(tmp_path: Path) -> None:
    path = write(
        tmp_path,
        """
gcs:
  loops:
    matcher: {levels: 5}
    items:
      - {name: a}
      - {name: b, weight: 2}
    radios:
      slow: {shared_capacity_bps: 9600.0}
seed: 7
""",
    )
    cfg = load_config(path, MissionConfig)
    assert cfg.seed == 7
    assert cfg.gcs.loops.matcher == MatcherConfig(levels=5, resolution_m=0.1)
    assert cfg.gcs.loops.items == [ItemConfig(name="a"), ItemConfig(name="b", weight=2.0)]
    assert cfg.gcs.loops.radios["slow"].shared_capacity_bps == 9600.0
    assert cfg.gcs.radio is None
    with pytest.raises(AttributeError):
        cfg.seed = 8  # type: ignore[misc]


def test_empty_file_gives_defaults(tmp_path: Path) -> None:
    assert load_config(write(tmp_path, "# nothing\n"), MissionConfig) == MissionConfig()


# ----------------------------------------------------------------------------- errors


@pytest.mark.parametrize(
    ("text", "key", "problem"),
    [
        (
            "gcs: {loops: {matcher: {levels: '3'}}}",
            "gcs.loops.matcher.levels",
            "expected int, got str",
        ),
        (
            "gcs: {loops: {matcher: {levels: 3.0}}}",
            "gcs.loops.matcher.levels",
            "expected int, got float",
        ),
        (
            "gcs: {loops: {matcher: {levels: true}}}",
            "gcs.loops.matcher.levels",
            "expected int, got bool",
        ),
        (
            "gcs: {loops: {matcher: {resolution_m: 'fine'}}}",
            "gcs.loops.matcher.resolution_m",
            "expected float, got str",
        ),
        ("gcs: {loops: {matcher: {bogus: 1}}}", "gcs.loops.matcher.bogus", "unknown key"),
        ("gcs: {loop: {}}", "gcs.loop", "unknown key"),
        ("sead: 3", "sead", "unknown key"),
        (
            "gcs: {loops: {items: [{name: a}, {name: b, weight: x}]}}",
            "gcs.loops.items[1].weight",
            "expected float, got str",
        ),
        (
            "gcs: {loops: {items: [{name: a}, {weight: 1.0}]}}",
            "gcs.loops.items[1].name",
            "required key is missing",
        ),
        (
            "gcs: {loops: {items: [{name: a, color: red}]}}",
            "gcs.loops.items[0].color",
            "unknown key",
        ),
        ("gcs: {loops: {items: {name: a}}}", "gcs.loops.items", "expected array, got object"),
        ("gcs: {loops: {items: [{name: 5}]}}", "gcs.loops.items[0].name", "expected str, got int"),
        ("gcs: {loops: {matcher: 3}}", "gcs.loops.matcher", "expected object, got int"),
        (
            "gcs: {loops: {radios: {slow: {shared_capacity_bps: fast}}}}",
            "gcs.loops.radios[...].shared_capacity_bps",
            "expected float, got str",
        ),
        ("gcs: [1, 2]", "gcs", "expected object, got array"),
        ("seed: 2020-01-01", "seed", "expected int, got date"),
    ],
)
def test_errors_name_file_and_dotted_key(tmp_path: Path, text: str, key: str, problem: str) -> None:
    path = write(tmp_path, text)
    err = load_error(path)
    assert str(err) == f"{path}: {key}: {problem}"
    assert (err.source, err.key, err.problem) == (str(path), key, problem)


def test_top_level_must_be_a_mapping(tmp_path: Path) -> None:
    path = write(tmp_path, "- 1\n- 2\n")
    assert str(load_error(path)) == f"{path}: expected object, got array"


@pytest.mark.parametrize(
    ("text", "key", "problem"),
    [
        ("shared_capacity_bps: -1.0", "shared_capacity_bps", "must be > 0, got -1.0"),
        ("shared_capacity_bps: 0", "shared_capacity_bps", "must be > 0, got 0.0"),
        ("shared_capacity_bps: .nan", "shared_capacity_bps", "must be > 0, got nan"),
        ("framing_overhead_bytes: -1", "framing_overhead_bytes", "must be >= 0, got -1"),
    ],
)
def test_post_init_checks_name_file_and_key(
    tmp_path: Path, text: str, key: str, problem: str
) -> None:
    path = write(tmp_path, text, "radio.yaml")
    err = load_error(path, RadioConfig)
    assert str(err) == f"{path}: {key}: {problem}"
    assert err.key == key


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        (
            "gcs: {radio: {framing_overhead_bytes: -4}}",
            "gcs.radio.framing_overhead_bytes: must be >= 0, got -4",
        ),
        (
            "gcs: {loops: {radios: {a: {}, b: {shared_capacity_bps: -2.0}}}}",
            "gcs.loops.radios[...].shared_capacity_bps: must be > 0, got -2.0",
        ),
        # A check whose message does not start with a field is reported at its struct.
        (
            "gcs: {loops: {limits: {low: 2.0}}}",
            "gcs.loops.limits: empty range: low 2.0 is above high 1.0",
        ),
    ],
)
def test_nested_post_init_checks(tmp_path: Path, text: str, expected: str) -> None:
    path = write(tmp_path, text)
    assert str(load_error(path)) == f"{path}: {expected}"


def test_missing_file(tmp_path: Path) -> None:
    path = tmp_path / "nope.yaml"
    err = load_error(path)
    assert str(err) == f"{path}: cannot read: No such file or directory"
    assert err.source == str(path) and err.key == ""


def test_directory_instead_of_file(tmp_path: Path) -> None:
    assert str(load_error(tmp_path)).startswith(f"{tmp_path}: cannot read: ")


def test_invalid_yaml(tmp_path: Path) -> None:
    path = write(tmp_path, "gcs:\n  loops: [1, 2\nseed: 3\n")
    msg = str(load_error(path))
    assert msg.startswith(f"{path}: invalid YAML: line ")
    assert "column" in msg


def test_tab_indented_yaml(tmp_path: Path) -> None:
    path = write(tmp_path, "gcs:\n\tloops: {}\n")
    assert str(load_error(path)).startswith(f"{path}: invalid YAML: line 2, column 1: ")


def test_not_utf8(tmp_path: Path) -> None:
    path = tmp_path / "latin1.yaml"
    path.write_bytes(b"seed: 3 # caf\xe9\n")
    assert str(load_error(path)) == f"{path}: not UTF-8 text: invalid continuation byte at byte 13"


def test_strings_and_prefixes() -> None:
    with pytest.raises(ConfigError) as info:
        load_config_text("levels: '3'", MatcherConfig)
    assert str(info.value) == "<string>: levels: expected int, got str"
    with pytest.raises(ConfigError) as info:
        decode_config({"levels": "3"}, MatcherConfig, source="--set", prefix="gcs.loops.matcher")
    assert str(info.value) == "--set: gcs.loops.matcher.levels: expected int, got str"
    with pytest.raises(ConfigError) as info:
        decode_config([{"name": 1}], list[ItemConfig], source="--set", prefix="gcs.loops.items")
    assert str(info.value) == "--set: gcs.loops.items[0].name: expected str, got int"
    assert decode_config(None, MatcherConfig, source="x") == MatcherConfig()


def test_config_path_finds_names_paths_and_says_what_exists(tmp_path: Path) -> None:
    small = CONFIGS_DIR / "world" / "small.yaml"
    assert config_path("small", "world") == small
    assert config_path("world/small.yaml", "world") == small
    assert config_path(small, "world") == small
    mine = tmp_path / "mine.yaml"
    mine.write_text("seed: 3\n")
    assert config_path(mine, "world") == mine
    with pytest.raises(ConfigError, match=r"shipped: magic_phase, (\w+, )*small\)"):
        config_path("smal", "world")
    with pytest.raises(ConfigError, match="no such file"):
        config_path(tmp_path / "small.yaml", "world")  # an absolute path is taken as given


def test_shipped_configs_are_found_in_a_checkout_and_in_a_wheel_install(tmp_path) -> None:
    from protocol.config import CONFIGS_DIR, configs_dir

    assert (CONFIGS_DIR / "world" / "small.yaml").is_file()  # this checkout's
    checkout, prefix = tmp_path / "src", tmp_path / "venv"
    (checkout / "configs").mkdir(parents=True)
    (prefix / "share/magic-recon/configs/world").mkdir(parents=True)
    assert configs_dir(checkout, prefix) == checkout / "configs"  # the tree's first
    wheel = tmp_path / "site-packages"  # a wheel's packages: no configs/ beside them
    wheel.mkdir()
    assert configs_dir(wheel, prefix) == prefix / "share/magic-recon/configs"
