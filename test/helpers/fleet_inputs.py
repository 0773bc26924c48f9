"""The small fleet the tools tests replay (``test/tools/conftest.py``'s ``fleet_in``)."""

#: Frames of each fleet recording.
FLEET_FRAMES = 20
#: Segments of 8 frames, so 20-frame recordings span three segments (two full, one short) and
#: an engine must put them back in order (``small_segments``).
FLEET_SEGMENT = 8
