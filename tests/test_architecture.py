"""The package's shape: one import package, layers that import only downward (import-linter),
a role stated by every subpackage, and a config whose every key is documented and read."""

from __future__ import annotations

import ast
import dataclasses
import json
import os
import re
import socket
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest
import yaml

from photomap.config import Config, default_config_path

REPO = Path(__file__).resolve().parents[1]
SERVICE = REPO / "service"


def _subpackages() -> list[str]:
    return sorted(p.parent.name for p in SERVICE.glob("*/__init__.py"))


def test_every_subpackage_is_installed_and_says_its_role():
    packages = tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["setuptools"]["packages"]
    assert set(packages) == {"photomap", "photomap.drivers"} | {f"photomap.{n}" for n in _subpackages()}
    for init in [*SERVICE.glob("*/__init__.py"), REPO / "drivers" / "__init__.py", SERVICE / "__init__.py"]:
        doc = ast.get_docstring(ast.parse(init.read_text()))
        assert doc and len(doc.split()) >= 5, f"{init.relative_to(REPO)} does not say what the package is for"


def test_import_rules_hold(tmp_path):
    """``lint-imports`` (import-linter, contracts in pyproject.toml) on the package as installed.

    The checkout maps ``service/`` to ``photomap`` and ``drivers/`` to ``photomap.drivers``; a
    tree of links gives import-linter that layout without building a wheel.
    """
    exe = Path(sys.executable).parent / "lint-imports"
    if not exe.exists():
        pytest.skip("import-linter is not installed (it comes with the test extra)")
    root = tmp_path / "photomap"
    root.mkdir()
    for entry in SERVICE.iterdir():
        if entry.name != "__pycache__":
            (root / entry.name).symlink_to(entry)
    (root / "drivers").symlink_to(REPO / "drivers")
    env = {**os.environ, "PYTHONPATH": str(tmp_path)}
    result = subprocess.run([str(exe), "--no-cache"], cwd=REPO, env=env, capture_output=True, text=True,
                            timeout=300)
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-2000:]
    assert "BROKEN" not in result.stdout and result.stdout.count("KEPT") >= 2


def test_default_yaml_documents_exactly_the_defaults():
    documented = yaml.safe_load(default_config_path().read_text(encoding="utf-8"))
    assert documented == Config().to_dict()
    text = default_config_path().read_text(encoding="utf-8")
    for section, keys in documented.items():
        for key in keys:  # every key has a comment above it (or above its group)
            assert re.search(rf"#[^\n]*\n(?:\s*#[^\n]*\n|\s*\w+:[^\n]*\n)*?\s*{key}:", text), f"{section}.{key}"


# --------------------------------------------------------------------------- every key is read
def _tracked(config: Config, seen: set[str]) -> Config:
    """``config`` whose sections record every attribute read into ``seen`` (as section.key)."""
    import photomap.config

    config_file = photomap.config.__file__
    sections = {}
    for f in dataclasses.fields(config):
        section = getattr(config, f.name)
        cls = type(section)
        names = {g.name for g in dataclasses.fields(section)}

        def getattribute(self, name, _names=names, _section=f.name):
            # reads by the config's own checks (photomap/config.py) do not count
            if name in _names and sys._getframe(1).f_code.co_filename != config_file:
                seen.add(f"{_section}.{name}")
            return object.__getattribute__(self, name)

        tracked_cls = type(f"Tracked{cls.__name__}", (cls,), {"__getattribute__": getattribute})
        sections[f.name] = tracked_cls(**{n: object.__getattribute__(section, n) for n in names})
    return Config(**sections)


def test_every_config_key_is_read(tmp_path, monkeypatch):
    """Each key of config/default.yaml is read by the code that a run, a live run, a simulation
    or the viewer executes: a key that nothing reads would be accepted and do nothing."""
    pytest.importorskip("rerun")
    import photomap.config as config_module
    from photomap.cli import main as cli

    seen: set[str] = set()
    load = config_module.load_config

    def load_tracked(*args, **kwargs):
        return _tracked(load(*args, **kwargs), seen)

    monkeypatch.setattr(cli, "load_config", load_tracked)
    flight = tmp_path / "flight"
    assert cli.main(["simulate", "--out", str(flight), "--frames", "180", "--size", "320x240",
                     "--pattern", "figure8", "--fps", "10", "--altitude", "25:35", "--speed", "6",
                     "--yaw-mode", "heading", "--gsd", "0.1", "--set", "simulate.terrain_zoom=3", "-q"]) == 0
    # a replay with telemetry, loop closure, checkpoints, a recorded view and a spilling tile store
    args = ["replay", str(flight / "video.mp4"), "--out", str(tmp_path / "run"), "--no-progress", "-q",
            "--mavlink", str(flight / "telemetry.tlog"), "--viewer", f"save={tmp_path / 'view.rrd'}", "--hazards",
            "--set", "mosaic.max_tiles_in_memory=64", "--set", "mapping.map_relative=true",
            "--set", "output.checkpoint_interval=0.000001"]
    with socket.socket() as s:  # and the live map served on loopback
        s.bind(("127.0.0.1", 0))
        args += ["--map-server", str(s.getsockname()[1])]
    assert cli.main(args) == 0
    assert json.loads((tmp_path / "run" / "run.json").read_text())["loop_closure"]["corrections"] >= 1
    # a live run: the camera is missing, but everything it reads before opening it is read
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    assert cli.main(["run", "--camera", "/dev/video99", "--set", f"output.data_dir={tmp_path / 'live'}", "-q",
                     "--mavlink", f"udpin:127.0.0.1:{port}"]) != 0
    unread = sorted(f"{s}.{k}" for s, keys in Config().to_dict().items() for k in keys
                    if f"{s}.{k}" not in seen)
    assert not unread, f"config keys that nothing read: {unread}"
