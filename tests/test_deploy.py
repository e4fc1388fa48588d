"""The onboard deployment files: the systemd unit, the example config, the install guide."""

from __future__ import annotations

import configparser
import re
import shlex
from pathlib import Path

import pytest

from photomap.cli.main import build_parser, main
from photomap.config import load_config
from photomap.cli.run import flight_folder

REPO = Path(__file__).resolve().parents[1]
UNIT = REPO / "config" / "photomap.service"
ONBOARD = REPO / "config" / "photomap-onboard.yaml"
GUIDE = REPO / "docs" / "onboard.md"


@pytest.fixture(scope="module")
def unit() -> configparser.ConfigParser:
    parser = configparser.ConfigParser(interpolation=None, strict=True)  # strict: no key twice
    parser.optionxform = str  # systemd keys are case-sensitive
    parser.read_string(UNIT.read_text(encoding="utf-8"))
    return parser


def _words(value: str) -> list[str]:
    return value.split()


def _under(path: str, folders: list[str]) -> bool:
    return any(Path(path).is_relative_to(folder) for folder in folders)


def test_unit_has_the_three_sections(unit):
    assert unit.sections() == ["Unit", "Service", "Install"]
    assert unit["Install"]["WantedBy"] == "multi-user.target"


def test_unit_runs_photomap_run_on_the_camera_with_the_etc_config(unit):
    argv = shlex.split(unit["Service"]["ExecStart"])
    assert argv[0] == "/opt/photomap/venv/bin/photomap"
    args = build_parser().parse_args(argv[1:])
    assert args.command == "run"
    assert args.camera == "/dev/video0"
    assert args.config == "/etc/photomap/photomap.yaml"
    assert args.out is None  # each flight in its own time-stamped folder under output.data_dir


def test_unit_runs_unprivileged_with_camera_and_serial_groups(unit):
    service = unit["Service"]
    assert service["User"] == "photomap"
    assert service.get("Group", "photomap") != "root"
    assert {"video", "dialout"} <= set(_words(service["SupplementaryGroups"]))


def test_unit_restarts_on_failure_and_stops_with_a_signal_the_service_handles(unit):
    service = unit["Service"]
    assert service["Restart"] == "on-failure"
    assert service["KillSignal"] in ("SIGINT", "SIGTERM")  # both write the map (photomap.cli.replay)
    assert int(service["TimeoutStopSec"]) >= 60


def test_unit_hardening_leaves_the_data_and_cache_folders_writable(unit):
    service = unit["Service"]
    assert service["NoNewPrivileges"] == "yes"
    assert service["ProtectSystem"] == "strict"
    assert service["PrivateTmp"] == "yes"
    writable = _words(service["ReadWritePaths"])
    env = dict(item.split("=", 1) for item in _words(service["Environment"]))
    assert _under(env["TMPDIR"], writable)  # spilled map tiles
    cfg = load_config(ONBOARD)
    assert _under(cfg.output.data_dir, writable)
    assert _under(str(flight_folder(cfg.output.data_dir)), writable)
    for kind in ("StateDirectory", "CacheDirectory"):
        assert _under(f"/var/{'lib' if kind == 'StateDirectory' else 'cache'}/{service[kind]}", writable)


def test_onboard_config_loads_over_the_defaults():
    cfg = load_config(ONBOARD)
    defaults = load_config()
    assert cfg.output.data_dir == "/var/lib/photomap/flights"
    assert cfg.mosaic.max_tiles_in_memory == 256
    assert (cfg.capture.width, cfg.capture.height) == (640, 480)
    assert cfg.output.max_mosaic_px == 4096
    assert cfg.registration == defaults.registration  # only the keys it names change


def test_missing_camera_is_a_failure_that_systemd_restarts(capsys):
    # Restart=on-failure restarts on a non-zero exit: a camera that is not there (yet) must give one.
    code = main(["run", "--camera", "/dev/video99", "--config", str(ONBOARD), "-q"])
    assert code == 3
    err = capsys.readouterr().err
    assert "photomap run: error:" in err and "Traceback" not in err


def test_guide_names_files_that_exist():
    text = GUIDE.read_text(encoding="utf-8")
    named = set(re.findall(r"\b(?:config|docs|tools)/[\w.-]+\.\w+", text))
    assert {"config/photomap.service", "config/photomap-onboard.yaml"} <= named
    for rel in named:
        assert (REPO / rel).is_file(), rel


def test_benchmarks_rewrite_only_their_own_section(tmp_path):
    from tools.report import replace_section

    start, end = "<!-- pipeline:start -->", "<!-- pipeline:end -->"
    path = tmp_path / "benchmarks.md"
    other = "# Registration benchmarks\n\n<!-- registration:start -->\n| a | b |\n<!-- registration:end -->\n"
    path.write_text(other, encoding="utf-8")
    replace_section(path, "pipeline", "## Pipeline\n\nfirst\n")
    assert path.read_text(encoding="utf-8") == other + f"\n{start}\n## Pipeline\n\nfirst\n{end}\n"
    path.write_text(path.read_text(encoding="utf-8") + "\n## Later section\n", encoding="utf-8")
    replace_section(path, "pipeline", "## Pipeline\n\nsecond\n")
    assert path.read_text(encoding="utf-8") == (other + f"\n{start}\n## Pipeline\n\nsecond\n{end}\n"
                                                 "\n## Later section\n")
    replace_section(path, "registration", "| c | d |\n")
    assert "| a | b |" not in path.read_text(encoding="utf-8")
    assert "second" in path.read_text(encoding="utf-8")
