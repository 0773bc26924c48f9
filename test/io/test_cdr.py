"""ficap_ros.io.cdr: the label messages serialised straight to CDR are rosbags' bytes."""

from __future__ import annotations

import numpy as np
from hypothesis import given
from hypothesis import strategies as st

from ficap_ros.io import messages
from ficap_ros.io.cdr import CdrWriter, named_values_cdr
from ficap_ros.io.messages import ROSBAGS


@given(st.lists(st.tuples(st.text(max_size=12), st.one_of(st.floats(), st.just(np.nan))),
                max_size=8, unique_by=lambda kv: kv[0]),
       st.integers(-2**40, 2**40), st.text(max_size=9))
def test_named_values_are_rosbags_bytes_of_the_joint_state(items, stamp_ns: int, frame: str) -> None:  # noqa: ANN001
    values = dict(items)
    store = messages.jazzy_typestore()
    msg = messages.named_values(ROSBAGS, messages.header(ROSBAGS, stamp_ns, frame), values)
    expect = bytes(store.serialize_cdr(msg, "sensor_msgs/msg/JointState"))
    got = named_values_cdr(stamp_ns, frame, values, np.array(list(values.values()), dtype=float))
    assert got == expect
    back = store.deserialize_cdr(got, "sensor_msgs/msg/JointState")
    assert list(back.name) == list(values) and back.header.frame_id == frame


def test_fields_align_to_their_size_after_the_encapsulation_header() -> None:
    out = CdrWriter()
    out.string("ab")  # length 3 (with the NUL), 4 + 3 bytes
    out.float64s(np.array([1.5]))  # length at offset 8, the value at 16
    data = out.data()
    assert data[:4] == b"\x00\x01\x00\x00"
    body = data[4:]
    assert body[:7] == b"\x03\x00\x00\x00ab\x00" and body[7:8] == b"\x00"
    assert body[8:12] == b"\x01\x00\x00\x00" and body[12:16] == bytes(4)
    assert np.frombuffer(body[16:24], dtype="<f8")[0] == 1.5 and len(body) == 24
