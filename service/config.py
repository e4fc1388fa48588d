"""The one YAML config: ``config/default.yaml`` documents every key; files and ``--set`` override it.

An override may only name keys that exist in the defaults, with a value of the same type
(an int is accepted where a float is expected; a key whose default is ``null`` takes any scalar).
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any, Iterable

import yaml

from photomap.errors import ConfigError

_CANDIDATES = (
    Path(__file__).resolve().parents[1] / "config" / "default.yaml",  # source checkout / editable
    Path(sys.prefix) / "share" / "photomap" / "config" / "default.yaml",  # wheel install
)


def default_config_path() -> Path:
    """Path of the bundled ``default.yaml``."""
    for path in _CANDIDATES:
        if path.is_file():
            return path
    raise ConfigError("config/default.yaml not found: reinstall photomap")


def _read_yaml(path: Path) -> dict:
    try:
        text = Path(path).read_text(encoding="utf-8")
    except OSError as exc:
        raise ConfigError(f"cannot read config file {path}: {exc.strerror}") from None
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise ConfigError(f"config file {path} is not valid YAML: {exc}") from None
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise ConfigError(f"config file {path} must hold a mapping of sections")
    return data


def _check_type(key: str, default: Any, value: Any) -> Any:
    if default is None:
        return value
    if isinstance(default, bool):
        if not isinstance(value, bool):
            raise ConfigError(f"config key '{key}' must be true or false, got {value!r}")
        return value
    if isinstance(default, float):
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"config key '{key}' must be a number, got {value!r}")
        return float(value)
    if isinstance(default, int):
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"config key '{key}' must be an integer, got {value!r}")
        return value
    if isinstance(default, str):
        if not isinstance(value, str):
            raise ConfigError(f"config key '{key}' must be a string, got {value!r}")
        return value
    if isinstance(default, list):
        if not isinstance(value, list):
            raise ConfigError(f"config key '{key}' must be a list, got {value!r}")
        return value
    return value


def _merge(base: dict, override: dict, prefix: str = "") -> None:
    for key, value in override.items():
        name = f"{prefix}{key}"
        if key not in base:
            known = ", ".join(sorted(base))
            raise ConfigError(f"unknown config key '{name}' (known here: {known})")
        if isinstance(base[key], dict):
            if not isinstance(value, dict):
                raise ConfigError(f"config key '{name}' is a section and needs a mapping")
            _merge(base[key], value, f"{name}.")
        else:
            base[key] = _check_type(name, base[key], value)


def parse_set(item: str) -> dict:
    """Turn ``section.key=value`` (value in YAML syntax) into a nested mapping."""
    if "=" not in item:
        raise ConfigError(f"--set needs key=value, got {item!r}")
    key, _, raw = item.partition("=")
    parts = [p for p in key.strip().split(".") if p]
    if not parts:
        raise ConfigError(f"--set needs key=value, got {item!r}")
    try:
        value = yaml.safe_load(raw) if raw.strip() else ""
    except yaml.YAMLError:
        value = raw
    out: dict = {parts[-1]: value}
    for part in reversed(parts[:-1]):
        out = {part: out}
    return out


def defaults() -> dict:
    """The bundled defaults, freshly read."""
    return _read_yaml(default_config_path())


def load_config(path: str | Path | None = None, overrides: Iterable[str] = ()) -> dict:
    """Defaults, then the file at ``path``, then each ``key=value`` of ``overrides``."""
    cfg = defaults()
    if path is not None:
        _merge(cfg, _read_yaml(Path(path)))
    for item in overrides:
        _merge(cfg, parse_set(item))
    return cfg
