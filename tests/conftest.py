"""What the whole suite shares: the LeRobot formats' tests are left out, and said so in the run's header,
where their optional packages (the `lerobot` extra: pyarrow, PyAV) are not installed: `make test` adds
them only where the disk has room (Makefile)."""

from __future__ import annotations

from importlib.util import find_spec

LEROBOT_TESTS = ["test_lerobot.py", "test_lerobot_slow.py"]
LEROBOT_INSTALLED = find_spec("pyarrow") is not None and find_spec("av") is not None
collect_ignore = [] if LEROBOT_INSTALLED else LEROBOT_TESTS


def pytest_report_header(config) -> list[str]:
    if LEROBOT_INSTALLED:
        return []
    return [f"the lerobot extra (pyarrow, PyAV) is not installed: {', '.join(LEROBOT_TESTS)} left out"]
