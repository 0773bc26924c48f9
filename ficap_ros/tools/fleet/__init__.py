"""Label a fleet of recordings: many inputs, one command, resumable, optionally on Ray.

``ficap replay`` hands this package every recording it finds (several inputs, folder trees searched
for recordings, a manifest: ``manifest``). Each recording is replayed by
``ficap_ros.tools.replay.replay`` (one code path: the same labels.mcap / labels.csv / summary.json
as a single replay) into a folder under ``--out`` that mirrors where the input sits, and a fleet
summary (CSV, JSON, PNG: ``summary``) is written at the top of ``--out``.

Resuming: summary.json carries a *fingerprint* of everything that decides the labels
(``fingerprints``). A recording whose three outputs exist with the fingerprint of this run is
skipped, so an interrupted fleet resumes where it stopped and a second run does nothing; ``--force``
redoes them.

Engines (``run``): without Ray, recordings are replayed one after the other, each with ``--jobs``
processes; with Ray (``ray_engine``), the segments of all recordings are spread over the cluster's
CPUs with byte-identical labels. Progress is one bar over the fleet's frames (``progress``).
Nothing here imports ray unless a Ray engine is asked for.
"""
