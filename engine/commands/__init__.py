"""One module per ``python -m engine`` sub-command (see :mod:`engine.cli`)."""
