"""``ficap <verb>``: argument parsing for every verb, each a thin layer over ``tools`` and ``ros``.

The top layer: it may import every other subpackage.
"""
