"""The chaos cases' count lines (tests/support/chaos.py ``Counts.report``) at the end of every run.

A passing test's output is captured and dropped, so each case's line would be seen only with
``-s`` (``make chaos``); this plugin picks the lines out of each test's captured stdout (on the
pytest-xdist controller too: the workers send the captured sections with their reports) and
prints them in a section of the terminal summary.
"""
from __future__ import annotations

import pytest

PREFIX = "chaos "
_lines: list[str] = []


def pytest_runtest_logreport(report: pytest.TestReport) -> None:
    if report.when != "call":
        return
    _lines.extend(line for line in report.capstdout.splitlines() if line.startswith(PREFIX))


def pytest_terminal_summary(terminalreporter) -> None:
    if _lines:
        terminalreporter.section("chaos counts")
        for line in _lines:
            terminalreporter.write_line(line)
