"""Shared helper code of the benchmark scripts (``benchmarks/bench_*.py``); not a runnable script.

Modules: ``cli`` (the options every script takes: ``--quick``, ``--data``, ``--cache``, ``--no-doc``),
``report`` (machine line, load, tables, plots, each script's section of docs/benchmarks.md),
``methods`` (ours, the naive peer, AprilTag 3: the pipelines every table compares), ``devsets``
(the blender_dev reader), ``synthdata`` (rendered drives and cached ``ficap synth`` bags),
``timing`` (CPU time of a child command, own CPU time of the package's public functions) and
``stats`` (quantiles that skip NaN).
"""
