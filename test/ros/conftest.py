"""Fixtures of the node tests: ``harness_factory`` makes harnesses (``node_harness.Harness``) and
closes them after the test."""

from __future__ import annotations

from typing import Any

import pytest
from node_harness import Harness


@pytest.fixture
def harness_factory():
    made: list[Harness] = []

    def make(**kw: Any) -> Harness:
        h = Harness(**kw)
        made.append(h)
        return h

    yield make
    for h in made:
        h.close()
