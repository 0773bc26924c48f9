"""``ficap model``: print or write the cap model."""

from __future__ import annotations

import argparse

HELP = "print the cap model (nominal, or --model FILE) as JSON or YAML, or write it with --out"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--model", help="as-built model YAML (default: the nominal cap-spec model)")
    fmt = parser.add_mutually_exclusive_group()
    fmt.add_argument("--json", action="store_true", help="print JSON (default)")
    fmt.add_argument("--yaml", action="store_true", help="print YAML")
    parser.add_argument("--out", help="write the model as YAML to this file instead of printing")
    # ``ficap model build ...``: an optional sub-verb; plain ``ficap model [--json|--yaml|--out]``
    # is unchanged.
    from ficap_ros.cli import model_build

    actions = parser.add_subparsers(dest="model_action", metavar="ACTION")
    build = actions.add_parser("build", help=model_build.HELP, description=model_build.HELP)
    model_build.add_build_arguments(build)
    build.set_defaults(_run=model_build.run_build)


def run(args: argparse.Namespace) -> int:
    from ficap_ros.geometry.cap_model import load_model, nominal_model

    model = load_model(args.model) if args.model else nominal_model()
    if args.out:
        model.save(args.out, inputs=(args.model,))
    elif args.yaml:
        print(model.to_yaml(), end="")
    else:
        print(model.to_json())
    return 0
