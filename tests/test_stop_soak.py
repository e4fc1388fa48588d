"""``photomap replay`` stopped, interrupted and killed at random moments always exits, and leaves
sound outputs (tools/soak_stop.py does the same at length)."""

from __future__ import annotations

import pytest

from tools.soak_stop import KINDS, check_run, make_material, plan, report, soak


@pytest.fixture(scope="module")
def material(tmp_path_factory):
    return make_material(tmp_path_factory.mktemp("soak") / "flight", frames=40, size=(640, 480))


def test_the_plan_covers_every_kind_and_moment():
    todo = plan(20, seed=11)
    assert {kind for kind, _ in todo} == set(KINDS)
    assert any(d < 0 for _, d in todo) and any(d > 0.5 for _, d in todo)


#: What Python's ``site`` printed in a CI run when SIGINT landed while it ran the editable
#: install's ``.pth`` line (before any photomap code).
SITE_REPORT = """Error processing line 1 of /venv/lib/python3.11/site-packages/__editable__.ifmi_photomap-0.1.0.pth:

  Traceback (most recent call last):
    File "/usr/lib/python3.11/site.py", line 186, in addpackage
      exec(line)
    File "<string>", line 1, in <module>
    File "/venv/__editable___ifmi_photomap_0_1_0_finder.py", line 7, in <module>
      from pathlib import Path
  RuntimeError: Error calling __set_name__ on 'cached_property' instance 'broadcast_address' in '_BaseNetwork'

Remainder of file ignored
"""


def test_the_interpreters_start_up_report_is_not_photomaps_traceback(tmp_path):
    error = "photomap replay: error: registration.band_high must be below 0.5\n"
    out = tmp_path / "none"
    assert check_run("video:error", 2, SITE_REPORT + error, out, None) == []
    ours = "Traceback (most recent call last):\n  File \"x.py\", line 1\nValueError: x\n"
    assert any("traceback" in p for p in check_run("video:error", 2, SITE_REPORT + ours + error, out, None))
    assert any("traceback" in p for p in check_run("video:error", 2, ours + error, out, None))


def test_random_signals_never_hang_and_leave_sound_outputs(material, tmp_path):
    """20 runs (seeded), two at a time: SIGINT, SIGTERM and SIGKILL at random moments of a video
    and a stills replay, and the band_high=0.9 error path. A run that does not exit within 60 s
    of its signal is killed and fails the test (a hang); so does any unsound output."""
    results = soak(material, tmp_path, runs=20, seed=11, jobs=2, timeout=60.0, span=1.0)
    text = report(results)
    assert not any(r.hang for r in results), text
    assert not any(r.problems for r in results), text
    # the signals did land while mapping ran: some runs stopped part-way with a complete map
    stopped = [r for r in results if r.frames_in is not None and 0 < r.frames_in < material.frames]
    assert stopped, text
