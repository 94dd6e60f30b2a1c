"""A pytest plugin (tests/conftest.py loads it): a skipped test of a device driver against an implementation benchctl
did not write (Xvfb, Aravis's fake cameras, libgphoto2's virtual camera, python-microscope's mocks) fails when
$BENCHCTL_REQUIRE_DEVICES is 1, as `.ci/run` sets it.

Such tests skip where their program is missing (no Xvfb on a laptop), which is fine for a developer's run: pytest
lists each skip and its reason. In CI the same skip would pass silently while proving nothing (the GigE Vision tests
skipped for months when CI installed the wrong Debian package), so there it is a failure naming what was missing.
"""

from __future__ import annotations

import os
from collections.abc import Generator
from typing import Any

import pytest

REQUIRE_ENV = "BENCHCTL_REQUIRE_DEVICES"
MARKER = "third_party"


def pytest_configure(config: pytest.Config) -> None:
    config.addinivalue_line("markers", f"{MARKER}: tests a driver against a device implementation benchctl did not "
                                       f"write; skipping it fails the run when ${REQUIRE_ENV}=1 (CI)")


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(item: pytest.Item, call: pytest.CallInfo[None]) -> Generator[None, Any, None]:
    outcome = yield
    report = outcome.get_result()
    if report.skipped and item.get_closest_marker(MARKER) and os.environ.get(REQUIRE_ENV) == "1":
        reason = report.longrepr[2] if isinstance(report.longrepr, tuple) else str(report.longrepr)
        reason = reason.removeprefix("Skipped: ")
        report.outcome = "failed"
        report.longrepr = (f"{item.nodeid} skipped ({reason}), but ${REQUIRE_ENV}=1: every test against a "
                           f"third-party device implementation must run here")
