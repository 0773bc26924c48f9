"""``ficap detect``: print every tag36h11 detection in images (not filtered by a cap model)."""

from __future__ import annotations

import argparse

HELP = "detect every tag36h11 tag in images and print ids and corners (OpenCV order and pixels)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("images", nargs="+", metavar="IMAGE", help="image files")
    parser.add_argument("--json", action="store_true", help="print JSON instead of a table")
    parser.add_argument("--backend", choices=("opencv", "apriltag"), default="opencv",
                        help="detector backend (default: opencv)")
    parser.add_argument("--refine", choices=("edge", "subpix", "apriltag", "none"), default="edge",
                        help="corner refinement (default: edge)")


def run(args: argparse.Namespace) -> int:
    import json

    import cv2

    from ficap_ros.detection import DetectorConfig, TagDetector
    from ficap_ros.errors import ImageError

    detector = TagDetector(DetectorConfig(backend=args.backend, corner_refine=args.refine))
    results = []
    for path in args.images:
        image = cv2.imread(path, cv2.IMREAD_GRAYSCALE)
        if image is None:
            raise ImageError(f"cannot read image {path!r} (missing, unreadable or not an image)")
        dets = detector.detect(image)
        results.append({
            "image": path,
            "detections": [
                {"id": d.tag_id, "corners_px": [[round(float(x), 4), round(float(y), 4)]
                                                for x, y in d.corners_px]}
                for d in dets
            ],
        })
    if args.json:
        print(json.dumps(results, indent=1))
        return 0
    for res in results:
        print(f"{res['image']}: {len(res['detections'])} tag(s)")
        for det in res["detections"]:
            corners = "  ".join(f"({x:8.2f}, {y:8.2f})" for x, y in det["corners_px"])
            print(f"  id {det['id']:4d}  {corners}")
    return 0
