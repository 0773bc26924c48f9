"""``ficap detect``: print every tag36h11 detection in images (not filtered by a cap model)."""

from __future__ import annotations

import argparse

HELP = "detect every tag36h11 tag in images and print ids and corners (OpenCV order and pixels)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("images", nargs="+", metavar="IMAGE", help="JPEG or PNG image files")
    parser.add_argument("--json", action="store_true", help="print JSON instead of a table")
    parser.add_argument("--backend", choices=("opencv", "apriltag"), default="opencv",
                        help="detector backend (default: opencv)")
    parser.add_argument("--refine", choices=("edge", "subpix", "apriltag", "none"), default="edge",
                        help="corner refinement (default: edge)")
    parser.add_argument("--photometric", action=argparse.BooleanOptionalAction, default=None,
                        help="with edge refinement: fit each tag's pattern, blurred in linear light and "
                             "through a tone curve, to its pixels (more accurate on noisy frames, "
                             "at a CPU cost per tag: docs/detection.md): --photometric every tag's; "
                             "--no-photometric none (the cell-edge fit's corners); neither (the "
                             "default): the tags whose corners noise limits")


#: Largest image file read: a 40 MP PNG (the pixel budget) stays well below it.
MAX_IMAGE_BYTES = 512 << 20


def read_image(path: str):  # noqa: ANN201 - a grey numpy image
    """A JPEG or PNG file as a grey image: a regular file of at most ``MAX_IMAGE_BYTES``, its
    size in its header within the pixel budget, not damaged (``image_codec.decode_compressed``).

    Raises:
        ImageError: naming the file.
    """
    from ficap_ros.errors import ImageError
    from ficap_ros.files import read_bytes
    from ficap_ros.io.image_codec import decode_compressed

    data = read_bytes(path, "image", ImageError, MAX_IMAGE_BYTES)
    try:
        return decode_compressed(data)
    except ImageError as err:
        raise type(err)(f"image {path!r}: {err}") from None


def run(args: argparse.Namespace) -> int:
    import json
    import sys

    import cv2

    from ficap_ros.errors import FicapError
    from ficap_ros.vision.detector import DetectorConfig, TagDetector

    detector = TagDetector(DetectorConfig(backend=args.backend, corner_refine=args.refine,
                                          edge_photometric=args.photometric is True,
                                          edge_photometric_auto=args.photometric is None))
    results = []
    failed = 0
    # Each image is reported as soon as it is done: one bad file among many costs its own line,
    # not the results of the others.
    for path in args.images:
        try:
            dets = detector.detect(read_image(path))
        except (FicapError, cv2.error) as err:
            failed += 1
            message = str(err).strip().splitlines()[-1] if str(err).strip() else type(err).__name__
            print(f"ficap: error: {message}", file=sys.stderr)
            if args.json:
                results.append({"image": path, "error": message})
            continue
        res = {
            "image": path,
            "detections": [
                {"id": d.tag_id, "corners_px": [[round(float(x), 4), round(float(y), 4)]
                                                for x, y in d.corners_px]}
                for d in dets
            ],
        }
        if args.json:
            results.append(res)
            continue
        print(f"{res['image']}: {len(res['detections'])} tag(s)")
        for det in res["detections"]:
            corners = "  ".join(f"({x:8.2f}, {y:8.2f})" for x, y in det["corners_px"])
            print(f"  id {det['id']:4d}  {corners}", flush=True)
    if args.json:
        print(json.dumps(results, indent=1))
    return 1 if failed else 0
