"""Which labels changed between two replays of the same input, and by how much.

    python scripts/compare_labels.py NEW_OUT REF_OUT

Both folders are ``ficap replay --out`` folders. labels.csv is compared column by column (rows that
differ, the largest absolute difference and the range of new / ref for numeric columns), labels.mcap
topic by topic and field by field (messages whose field differs and the largest absolute
difference; NaN equals NaN). A change meant to move only the bounds shows the bound, reliability
and covariance fields here and every pose field identical. Exits 0 when everything is identical,
1 when something differs.
"""

from __future__ import annotations

import argparse
import csv
import sys
from collections import defaultdict
from pathlib import Path
from typing import Any

import numpy as np


def csv_differences(new: Path, ref: Path) -> dict[str, str]:
    """Per column of labels.csv that differs: what differs (a row count mismatch under ``rows``)."""
    with open(new) as f:
        a = list(csv.DictReader(f))
    with open(ref) as f:
        b = list(csv.DictReader(f))
    if len(a) != len(b):
        return {"rows": f"{len(a)} rows vs {len(b)}"}
    out = {}
    for col in (a[0] if a else {}):
        pairs = [(x[col], y[col]) for x, y in zip(a, b) if x[col] != y[col]]
        if not pairs:
            continue
        try:
            num = [(float(x), float(y)) for x, y in pairs if x and y]
        except ValueError:
            out[col] = f"{len(pairs)}/{len(a)} rows differ (text)"
            continue
        diff = max((abs(x - y) for x, y in num), default=float("nan"))
        ratio = [x / y for x, y in num if y != 0]
        span = (f", new / ref {min(ratio):.3f}-{max(ratio):.3f} (median {np.median(ratio):.3f})"
                if ratio else "")
        out[col] = f"{len(pairs)}/{len(a)} rows differ, max |diff| {diff:.4g}{span}"
    return out


def _flat(obj: Any, prefix: str = "") -> dict[str, Any]:
    """A decoded ROS message as {dotted field path: value}."""
    names = getattr(obj, "__slots__", None)
    if names is None and hasattr(obj, "__dataclass_fields__"):
        names = list(obj.__dataclass_fields__)
    if names is not None:
        out: dict[str, Any] = {}
        for n in names:
            key = n.lstrip("_")
            out.update(_flat(getattr(obj, n), f"{prefix}.{key}" if prefix else key))
        return out
    if isinstance(obj, (list, tuple)) and obj and not isinstance(obj[0], (int, float, str)):
        out = {}
        for i, o in enumerate(obj):
            out.update(_flat(o, f"{prefix}[{i}]"))
        return out
    return {prefix: obj}


def _messages(path: Path) -> dict[str, list[tuple[int, dict[str, Any]]]]:
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    out: dict[str, list[tuple[int, dict[str, Any]]]] = defaultdict(list)
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        for _, channel, msg, decoded in reader.iter_decoded_messages():
            out[channel.topic].append((msg.log_time, _flat(decoded)))
    return out


def _field_difference(a: Any, b: Any) -> float | None:
    """None when equal (NaN equals NaN), else the largest absolute difference (NaN: not numeric)."""
    va, vb = np.asarray(a), np.asarray(b)
    floats = va.dtype.kind == "f" and vb.dtype.kind == "f"
    if va.shape == vb.shape and np.array_equal(va, vb, equal_nan=floats):
        return None
    try:
        return float(np.max(np.abs(va.astype(float) - vb.astype(float))))
    except (TypeError, ValueError):
        return float("nan")


def mcap_differences(new: Path, ref: Path) -> dict[str, str]:
    """Per topic of labels.mcap: ``identical`` or the fields that differ."""
    a, b = _messages(new), _messages(ref)
    out = {}
    for topic in sorted(set(a) | set(b)):
        ma, mb = a.get(topic, []), b.get(topic, [])
        if len(ma) != len(mb):
            out[topic] = f"{len(ma)} messages vs {len(mb)}"
            continue
        fields: dict[str, list[float]] = defaultdict(list)
        for (ta, fa), (tb, fb) in zip(ma, mb):
            if ta != tb:
                fields["log_time"].append(abs(ta - tb))
            for key in sorted(set(fa) | set(fb)):
                d = _field_difference(fa.get(key), fb.get(key))
                if d is not None:
                    fields[key].append(d)
        out[topic] = "identical" if not fields else "; ".join(
            f"{k}: {len(v)} messages, max |diff| {max(v):.3g}" for k, v in fields.items())
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("new", type=Path, help="replay output folder made with the new code")
    ap.add_argument("ref", type=Path, help="replay output folder of the reference")
    args = ap.parse_args(argv)
    same = True
    for col, what in csv_differences(args.new / "labels.csv", args.ref / "labels.csv").items():
        print(f"labels.csv {col}: {what}")
        same = False
    for topic, what in mcap_differences(args.new / "labels.mcap", args.ref / "labels.mcap").items():
        print(f"labels.mcap {topic}: {what}")
        same = same and what == "identical"
    if same:
        print("identical")
    return 0 if same else 1


if __name__ == "__main__":
    sys.exit(main())
