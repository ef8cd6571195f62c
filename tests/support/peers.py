"""What a test does when a real peer it needs (a binary, a broker, a server) is missing."""
from __future__ import annotations

import os
from typing import NoReturn

import pytest


def peer_missing(reason: str) -> NoReturn:
    """Skip with ``reason`` on a user's machine; fail under CI (``CI=true``), where every peer must be there."""
    if os.environ.get("CI") == "true":
        pytest.fail(reason)
    pytest.skip(reason)
