"""``python -m retarget_cli``: the ``retarget`` command."""

from .entry import main

main()
