"""Typed configuration from YAML files (DESIGN section 3).

Every configurable class has an ``XConfig`` beside it: a ``msgspec.Struct`` declared with
``frozen=True, forbid_unknown_fields=True, kw_only=True`` whose fields mirror the object tree.
This module turns YAML into those structs and reports problems by file and dotted key path::

    configs/gcs.yaml: gcs.loops.matcher.levels: expected int, got str

Configuration is decoded strictly: no str-to-number coercion, unknown keys are errors.
"""

from __future__ import annotations

import re
import sys
from pathlib import Path
from typing import Any, TypeVar

import msgspec
import yaml
from msgspec import inspect as mi

__all__ = [
    "ConfigError",
    "config_path",
    "configs_dir",
    "decode_config",
    "load_config",
    "load_config_text",
]

T = TypeVar("T")


def configs_dir(source_root: Path | None = None, prefix: Path | None = None) -> Path:
    """The shipped configuration files: the source tree's ``configs/`` (a checkout, an
    editable install; ``source_root``: the folder above the packages), else the copy a wheel
    installs as data files under ``<prefix>/share/magic-recon/configs`` (pyproject's
    ``data-files``; ``prefix``: default ``sys.prefix``)."""
    root = Path(__file__).resolve().parent.parent if source_root is None else source_root
    tree = root / "configs"
    installed = (Path(sys.prefix) if prefix is None else prefix) / "share/magic-recon/configs"
    return installed if not tree.is_dir() and installed.is_dir() else tree


#: Where the shipped configuration files live (the repository's ``configs/`` folder).
CONFIGS_DIR = configs_dir()

_PATH_RE = re.compile(r" - at `\$(?P<path>[^`]*)`$")
_EXPECTED_RE = re.compile(r"^Expected `(?P<want>[^`]+)`, got `(?P<got>[^`]+)`")
_UNKNOWN_RE = re.compile(r"^Object contains unknown field `(?P<name>[^`]+)`")
_MISSING_RE = re.compile(r"^Object missing required field `(?P<name>[^`]+)`")
#: A ``__post_init__`` check's message that starts with the field it is about, e.g.
#: ``shared_capacity_bps must be > 0`` or ``RadioGrant.loss must be in [0, 1)``.
_FIELD_FIRST_RE = re.compile(r"^(?:[A-Za-z_]\w*\.)?(?P<name>[A-Za-z_]\w*):? (?P<rest>.+)$", re.S)


class ConfigError(ValueError):
    """A configuration file or value is invalid; the message names the file and the dotted key."""

    def __init__(self, source: str, key: str, problem: str) -> None:
        self.source = source
        self.key = key
        self.problem = problem
        where = f"{source}: {key}: " if key else f"{source}: "
        super().__init__(where + problem)


def _dotted(path: str, prefix: str) -> str:
    """``.loops.names[1].rate`` -> ``gcs.loops.names[1].rate`` (with ``prefix='gcs'``)."""
    path = path.lstrip(".")
    if prefix:
        path = f"{prefix}.{path}" if path and not path.startswith("[") else prefix + path
    return path


def _struct_at(config_type: Any, path: str) -> mi.StructType | None:
    """The struct at msgspec error ``path`` inside ``config_type``, or None."""

    def unwrap(tinfo: mi.Type) -> mi.Type:
        if isinstance(tinfo, mi.UnionType):  # Optional[...] and the like: take the struct
            structs = [t for t in tinfo.types if isinstance(t, mi.StructType)]
            return structs[0] if len(structs) == 1 else tinfo
        return tinfo

    tinfo = mi.type_info(config_type)
    for m in re.finditer(r"\.(?P<field>[^.\[]+)|\[(?P<index>[^\]]*)\]", path):
        tinfo = unwrap(tinfo)
        if m.group("field") is not None and isinstance(tinfo, mi.StructType):
            fields = {f.encode_name: f.type for f in tinfo.fields}
            if m.group("field") not in fields:
                return None
            tinfo = fields[m.group("field")]
        elif m.group("index") is not None and isinstance(
            tinfo, mi.ListType | mi.VarTupleType | mi.SetType | mi.FrozenSetType
        ):
            tinfo = tinfo.item_type
        elif m.group("index") is not None and isinstance(tinfo, mi.DictType):
            tinfo = tinfo.value_type
        else:
            return None
    tinfo = unwrap(tinfo)
    return tinfo if isinstance(tinfo, mi.StructType) else None


def _translate(
    err: msgspec.ValidationError, source: str, prefix: str, config_type: Any = None
) -> ConfigError:
    text = str(err)
    path = ""
    if m := _PATH_RE.search(text):
        path = m.group("path")
        text = text[: m.start()]
    if m := _EXPECTED_RE.match(text):
        problem = f"expected {m.group('want')}, got {m.group('got')}"
        return ConfigError(source, _dotted(path, prefix), problem)
    if m := _UNKNOWN_RE.match(text):
        key = _dotted(f"{path}.{m.group('name')}", prefix)
        return ConfigError(source, key, "unknown key")
    if m := _MISSING_RE.match(text):
        key = _dotted(f"{path}.{m.group('name')}", prefix)
        return ConfigError(source, key, "required key is missing")
    # Anything else is a struct's own check (``__post_init__``), reported at the struct: when
    # the message starts with one of its fields, report it at that field's key.
    st = _struct_at(config_type, path) if config_type is not None else None
    m = _FIELD_FIRST_RE.match(text)
    if st is not None and m and m.group("name") in {f.encode_name for f in st.fields}:
        key = _dotted(f"{path}.{m.group('name')}", prefix)
        return ConfigError(source, key, m.group("rest"))
    return ConfigError(source, _dotted(path, prefix), text[:1].lower() + text[1:])


def decode_config(data: Any, config_type: type[T], *, source: str, prefix: str = "") -> T:
    """Convert already-parsed data (dicts, lists, scalars) into ``config_type``.

    ``source`` names where the data came from (a file path, ``--set``); ``prefix`` is the dotted
    key of ``data`` inside a larger file, used in error messages.
    """
    if data is None:
        data = {}
    try:
        return msgspec.convert(data, config_type, strict=True)
    except msgspec.ValidationError as err:
        raise _translate(err, source, prefix, config_type) from None


def load_config_text(text: str, config_type: type[T], *, source: str = "<string>") -> T:
    """Parse YAML text and decode it into ``config_type``."""
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as err:
        mark = getattr(err, "problem_mark", None)
        where = f"line {mark.line + 1}, column {mark.column + 1}: " if mark is not None else ""
        problem = getattr(err, "problem", None) or str(err)
        raise ConfigError(source, "", f"invalid YAML: {where}{problem}") from None
    return decode_config(data, config_type, source=source)


def config_path(name: str | Path, kind: str) -> Path:
    """The YAML file a command line names: ``name`` as a path if it exists, else under
    ``configs/`` (``world/small.yaml``), else ``configs/<kind>/<name>.yaml`` (``small``).
    Raises :class:`ConfigError` listing the shipped ``kind`` configs when none exists."""
    given = Path(name)
    candidates = [given]
    if not given.is_absolute():
        candidates += [CONFIGS_DIR / given, CONFIGS_DIR / kind / given.with_suffix(".yaml")]
    for path in candidates:
        if path.is_file():
            return path
    shipped = sorted(p.stem for p in (CONFIGS_DIR / kind).glob("*.yaml"))
    problem = f"no such file, nor a {kind} config under {CONFIGS_DIR} (shipped: "
    raise ConfigError(str(name), "", problem + ", ".join(shipped) + ")")


def load_config(path: str | Path, config_type: type[T]) -> T:
    """Read a YAML file into ``config_type``; errors name the file and the dotted key."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as err:
        raise ConfigError(str(path), "", f"cannot read: {err.strerror or err}") from None
    except UnicodeDecodeError as err:
        problem = f"not UTF-8 text: {err.reason} at byte {err.start}"
        raise ConfigError(str(path), "", problem) from None
    return load_config_text(text, config_type, source=str(path))
