"""ficap_ros.io.bag_writer: bags are written atomically."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from ficap_ros.io import messages
from ficap_ros.io.bag_writer import BagWriter
from ficap_ros.io.messages import ROSBAGS
from ficap_ros.io.sources import IMAGE_TYPE


def _grey(i: int) -> np.ndarray:
    return np.full((48, 64), 40 + i, np.uint8)


def test_bag_writer_is_atomic(tmp_path: Path) -> None:
    path = tmp_path / "out"

    class Boom(Exception):
        pass

    with pytest.raises(Boom):
        with BagWriter(path) as w:
            w.add_topic("/cam/image_raw", IMAGE_TYPE)
            w.write("/cam/image_raw", 1,
                    messages.image(ROSBAGS, messages.header(ROSBAGS, 1, "c"), _grey(0), "mono8"))
            raise Boom
    assert list(tmp_path.iterdir()) == []
