"""One module per ``ficap`` verb (see ``ficap_ros.cli``)."""
