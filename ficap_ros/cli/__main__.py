"""``python -m ficap_ros.cli``: the ``ficap`` command."""

import sys

from ficap_ros.cli.main import main

sys.exit(main())
