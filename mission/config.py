"""Configuration loading for the composition root: re-exports :mod:`protocol.config`.

The loader lives in ``protocol/`` because every process (``sim/``, ``robot/``, ``gcs/``) reads
typed YAML configs and none of them may import ``mission/`` (DESIGN section 2).
"""

from protocol.config import (
    CONFIGS_DIR,
    ConfigError,
    config_path,
    decode_config,
    load_config,
    load_config_text,
)

__all__ = [
    "CONFIGS_DIR",
    "ConfigError",
    "config_path",
    "decode_config",
    "load_config",
    "load_config_text",
]
