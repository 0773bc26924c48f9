"""``ficap kit``: write the printable cap kit (1:1 tag sheets, assembly sheet, shell STL)."""

from __future__ import annotations

import argparse

from ficap_ros.cli.args import float_in

HELP = "write the printable cap kit: 1:1 tag sheets (PDF, SVG), assembly sheet, shell STL"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", required=True, help="output folder (created if missing; an existing one must be empty or ficap's)")
    parser.add_argument("--paper", choices=("a4", "letter"), default="a4",
                        help="paper size of the tag sheets (default a4)")
    parser.add_argument("--model", help="cap model YAML whose ids to print (default: nominal)")
    parser.add_argument("--no-stl", action="store_true", help="do not write the cap-shell STL")
    parser.add_argument("--shell-thickness-mm", type=float_in(0.0, 20.0, low_open=True,
                                                              high_open=True), default=2.0,
                        help="face plate thickness of the STL shell, mm, in (0, 20) (default 2)")


def run(args: argparse.Namespace) -> int:
    from ficap_ros.geometry.cap_model import load_model
    from ficap_ros.tools.kit import make_kit

    model = load_model(args.model) if args.model else None
    result = make_kit(args.out, paper=args.paper, model=model, stl=not args.no_stl,
                      shell_thickness_mm=args.shell_thickness_mm, inputs=(args.model,))
    for path in result.files:
        print(path)
    return 0
