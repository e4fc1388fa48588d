"""The docs a newcomer reads: a report of today's figures, not a work diary.

``docs/benchmarks.md`` is at most 600 lines and every ``##`` section names the ``python -m tools.NAME``
that writes it (and that tool exists); no doc or README speaks of work sessions or stops; the
README stays under 250 lines and opens with its two commands (install + demo, install + tests).
"""

from __future__ import annotations

import re
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
DIARY = re.compile(r"\b(stop \d+|stop-\d+|this stop|work session|this session|at stop)\b", re.IGNORECASE)


def _sections(text: str) -> list[tuple[str, str]]:
    """(title, body) of each ``##`` section (not ``###``)."""
    parts = re.split(r"^## (.+)$", text, flags=re.MULTILINE)
    return list(zip(parts[1::2], parts[2::2]))


def test_benchmarks_is_a_short_report_whose_sections_name_their_tool():
    text = (REPO / "docs" / "benchmarks.md").read_text(encoding="utf-8")
    assert len(text.splitlines()) <= 600
    sections = _sections(text)
    assert len(sections) >= 8
    for title, body in sections:
        tools = re.findall(r"python -m tools\.(\w+)", body)
        assert tools, f"section '{title}' does not name the tool that writes it"
        for name in tools:
            assert (REPO / "tools" / f"{name}.py").is_file(), f"section '{title}' names tools.{name}, which is missing"


def test_no_doc_speaks_of_sessions_or_stops():
    for path in [REPO / "README.md", *sorted((REPO / "docs").glob("*.md"))]:
        for n, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
            assert not DIARY.search(line), f"{path.name}:{n}: {line.strip()}"


def test_readme_is_short_and_opens_with_its_two_commands():
    lines = (REPO / "README.md").read_text(encoding="utf-8").splitlines()
    assert len(lines) < 250
    commands = [line for line in lines[:25] if line.startswith("python3 -m venv")]
    assert len(commands) == 2
    assert "photomap demo" in commands[0]
    assert 'pip install -e ".[test]"' in commands[1] and "pytest" in commands[1]
